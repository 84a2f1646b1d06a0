"""`render2spike simulate` input paths: streamed .npz, memory-mapped .npy, prefetched frames, bit counting."""

import numpy as np
import pytest

import sensor
from render2spike.cli import main
from sensor.io.npzrows import NpzMember as _NpzMember
from sensor.io.reader import RESERVE_MAX_BYTES, RateSource, reserve_count
from sensor.io.spikefile import count_bits


@pytest.fixture
def prof(tmp_path):
    p = sensor.SensorProfile.synthetic(8, 16, threshold_e=40, dark_rate=0.01, prnu_sigma=0.05, seed=3)
    return p, p.save(tmp_path / "cam.npz")


def test_count_bits_matches_unpackbits():
    b = np.random.default_rng(0).integers(0, 256, (37, 19), dtype=np.uint8)
    assert count_bits(b) == int(np.unpackbits(b).sum())
    assert count_bits(np.zeros((0, 4), np.uint8)) == 0


@pytest.mark.parametrize("compressed", [False, True])
def test_npz_member_streams_rows_in_chunks(tmp_path, compressed):
    a = np.random.default_rng(1).uniform(0, 5, (23, 4, 5)).astype(np.float64)
    (np.savez_compressed if compressed else np.savez)(tmp_path / "a.npz", rate_e=a)
    m = _NpzMember(tmp_path / "a.npz", "rate_e")
    assert m.shape == a.shape
    parts = [m.rows(i, min(i + 7, 23)) for i in range(0, 23, 7)]
    m.close()
    np.testing.assert_array_equal(np.concatenate(parts), a)


@pytest.mark.parametrize("order", ["C", "F"])
def test_npy_rows_are_read_in_chunks(tmp_path, order):
    a = np.asarray(np.random.default_rng(4).uniform(0, 9, (5, 4, 3)), order=order)
    np.save(tmp_path / "r.npy", a)
    src = RateSource(tmp_path / "r.npy")
    assert src.per_interval and src.n == 5
    np.testing.assert_array_equal(np.concatenate([src._npy_rows(0, 2), src._npy_rows(2, 5)]), a.astype(np.float32))


@pytest.mark.parametrize("suffix", [".npy", ".npz"])
def test_per_interval_input_matches_python_api(tmp_path, prof, suffix):
    p, path = prof
    # 2.5 simulator blocks of per-interval rates: crosses block boundaries and ends in a partial block
    sim = sensor.SpikeSimulator(p, "elssim", 0, per_interval=True)
    T = int(2.5 * sim.block)
    rate = np.random.default_rng(2).uniform(0, 3, (T, 8, 16)).astype(np.float32)
    f = tmp_path / ("r" + suffix)
    np.save(f, rate) if suffix == ".npy" else np.savez_compressed(f, rate_e=rate)
    rc = main(["simulate", str(f), "--out", str(tmp_path / "s.npz"), "--profile", str(path), "--seed", "4",
               "--quiet", "--chunk", "5"])
    assert rc == 0
    spikes = sensor.read_spikes(tmp_path / "s.npz")
    np.testing.assert_array_equal(spikes, sensor.simulate(rate, p, "elssim", seed=4))


def test_frames_prefetch_gives_the_same_chunks(tmp_path):
    p = sensor.SensorProfile.load("vidar-default").window(0, 0, 4, 6)
    phi = np.random.default_rng(5).uniform(1e15, 2e16, (7, 4, 6)).astype(np.float32)
    sensor.write_frames(tmp_path / "fr", phi, np.arange(7) * 1e-3)
    a = list(RateSource(tmp_path / "fr").chunks(p, [(0, 3), (3, 6), (6, 7)], prefetch=True))
    b = list(RateSource(tmp_path / "fr").chunks(p, [(0, 3), (3, 6), (6, 7)], prefetch=False))
    assert [x[0].shape[0] for x in a] == [3, 3, 1]
    for (ra, ta, _), (rb, tb, _) in zip(a, b):
        np.testing.assert_array_equal(ra, rb)
        np.testing.assert_array_equal(ta, tb)


def test_reserve_count_covers_the_run_but_not_large_chunks():
    """The reader's arrays faulted in at start-up: the depth + 2 the run holds less the first (taken new at
    once), never more than the chunks after the first, nothing past RESERVE_MAX_BYTES in all."""
    mb = 1 << 20
    assert reserve_count(80, 2, 20 * mb) == 3  # a frames folder at 400 x 250: 51-keyframe chunks
    assert reserve_count(80, 1, 20 * mb) == 2
    assert reserve_count(2, 2, 20 * mb) == 1 and reserve_count(1, 2, 20 * mb) == 0
    assert reserve_count(80, 2, RESERVE_MAX_BYTES // 2) == 2
    assert reserve_count(80, 1, 400 * mb) == 0  # one rate per interval: 1000-row chunks are not reserved
    assert reserve_count(80, 2, 0) == 3
