"""Frames held in memory (sensor.io.frames.MemoryFrameSequence) read exactly as the same frames through a folder."""

import numpy as np
import pytest

import sensor
from sensor.errors import FrameFileError
from sensor.io.frames import MemoryFrameSequence, manifest_record, read_frames
from sensor.io.reader import RateSource
from sensor.io.stream import open_stream


def _frames(tmp_path, K=7, H=8, W=16):
    """Float64 Phi as a renderer makes it, written as a frames folder (float32 EXR) and held in memory as the
    render job's memory sink holds it (rounded to float32)."""
    rng = np.random.default_rng(4)
    phi64 = rng.gamma(2.0, 4e15, size=(K, H, W))  # e-/(s m^2): ~1-40 e- per interval at the default profile
    t = np.arange(K) * 1.6e-3
    sensor.write_frames(tmp_path / "frames", phi64, t)
    names = [{"file": f"frame_{i:06d}.exr", "time_s": float(s)} for i, s in enumerate(t)]
    mem = MemoryFrameSequence([p.astype(np.float32) for p in phi64], manifest_record(H, W, names))
    return tmp_path / "frames", mem


def test_memory_frames_give_the_folders_rates_and_spikes_bit_for_bit(tmp_path):
    folder, mem = _frames(tmp_path)
    seq = read_frames(folder)
    assert np.array_equal(seq.times_s, mem.times_s)
    for i in range(len(seq)):
        assert np.array_equal(seq.read(i).phi, mem.read(i).phi)
    prof = sensor.SensorProfile.load("vidar-default").centred(*mem.shape)
    a, b = RateSource(folder), RateSource(mem)
    assert b.kind == "frames" and b.shape == a.shape and np.array_equal(a.t_s, b.t_s)
    ra, rb = a._read(prof, 0, len(seq)), b._read(prof, 0, len(seq))
    assert ra.dtype == rb.dtype == np.float32 and np.array_equal(ra, rb)
    got = [open_stream(src, "vidar-default", "elssim", 3).collect().packed for src in (folder, mem)]
    assert got[0].any() and np.array_equal(got[0], got[1])


@pytest.mark.parametrize("bad", [-1.0, np.nan])
def test_a_bad_value_in_memory_is_named_like_a_files(tmp_path, bad):
    _, mem = _frames(tmp_path, K=3)
    mem._phi[1][2, 5] = bad
    with pytest.raises(FrameFileError, match=r"frame_000001\.exr.*Phi.*\(2, 5\)"):
        open_stream(mem, "vidar-default", "elssim", 0).collect()


def test_times_are_refused_beside_frames_in_memory(tmp_path):
    from sensor.errors import InputError
    _, mem = _frames(tmp_path, K=3)
    with pytest.raises(InputError, match="t_s"):
        open_stream(mem, "vidar-default", t_s=mem.times_s)
