"""A SpikeStream's life: close() stops the read-ahead thread and closes the file (also unread), a second
collect() gives the same spikes, a second run is refused, open_stream releases what it opened when it
refuses, and t_s is honoured (or refused) for file inputs."""

import os
import threading

import numpy as np
import pytest

import sensor
from sensor.io.stream import open_stream

H, W = 8, 16


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("rates")
    rate = np.full((3000, H, W), 2.0, np.float32)
    np.savez_compressed(d / "deflated.npz", rate_e=rate)  # decoded by a reader thread, its file kept open
    np.savez(d / "stored.npz", rate_e=rate)
    np.save(d / "r.npy", rate)
    np.savez(d / "timed.npz", rate_e=rate, t_s=np.arange(3000) * 1e-4)
    return d


@pytest.fixture
def prof():
    return sensor.SensorProfile.synthetic(H, W, threshold_e=50, seed=1)


def readers():
    return [t for t in threading.enumerate() if t.name.startswith("r2s-read")]


def open_fds(path):
    n = 0
    for fd in os.listdir("/proc/self/fd"):
        try:
            n += os.path.realpath(f"/proc/self/fd/{fd}") == str(path)
        except OSError:
            pass
    return n


needs_proc = pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="needs /proc")


@needs_proc
def test_close_stops_an_unread_started_stream(files, prof):
    path = files / "deflated.npz"
    s = open_stream(path, prof, seed=1).start(chunk=1)
    assert readers() and open_fds(path) >= 1
    s.close()
    assert readers() == [] and open_fds(path) == 0
    s.close()  # idempotent
    with pytest.raises(RuntimeError, match="closed"):
        s.collect()


@needs_proc
def test_context_manager_closes(files, prof):
    path = files / "deflated.npz"
    with open_stream(path, prof, seed=1) as s:
        s.start(chunk=1)
    assert readers() == [] and open_fds(path) == 0


def test_collect_twice_gives_the_same_spikes_and_a_second_run_is_refused(files, prof):
    with open_stream(files / "stored.npz", prof, seed=1) as s:
        a = s.collect()
        assert a.packed.shape[0] == 3000
        assert s.collect() is a
        with pytest.raises(RuntimeError, match="already run"):
            list(s.blocks())


@needs_proc
def test_open_stream_releases_its_source_when_the_profile_is_refused(files):
    small = sensor.SensorProfile.synthetic(4, 4, threshold_e=50, seed=1)
    path = files / "deflated.npz"
    with pytest.raises(sensor.ProfileError) as refused:
        open_stream(path, small)
    assert open_fds(path) == 0  # closed, not left to the collector (the traceback still holds the source)
    assert refused.tb is not None


def test_t_s_is_honoured_for_an_npy_and_refused_where_the_file_has_times(files, prof):
    t = np.arange(3000) * 1e-4  # keyframes 2 intervals apart: 2999 x 2 intervals
    with open_stream(files / "r.npy", prof, seed=1, t_s=t) as s:
        assert not s.source.per_interval and s.total == 5998
        assert s.collect().packed.shape[0] == 5998
    with open_stream(files / "r.npy", prof, seed=1) as s:
        assert s.total == 3000  # without t_s: one row per interval
    with pytest.raises(sensor.InputError, match="its own 't_s'"):
        open_stream(files / "timed.npz", prof, t_s=t)
    with pytest.raises(sensor.InputError, match="t_s"):
        open_stream(files / "r.npy", prof, t_s=t[:5])
