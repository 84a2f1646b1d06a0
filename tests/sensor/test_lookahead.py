"""Lookahead in the streaming simulator (``iter_feed_packed(lookahead=True)``): each block's tiles start on
the thread pool while the caller handles the block before, each tile after the same tile of the previous
block. It must change no spike, in any model, chunking or thread count, and hand every block over in order."""

import numpy as np
import pytest

import sensor
import sensor.models.fast as fast
from sensor.models.registry import get_model
from sensor.models.step import block_generator
from sensor.rates import Segments
from sensor.io.spikefile import unpack_frames

pytestmark = pytest.mark.skipif(not fast.HAVE_NUMBA, reason="lookahead is a feature of the fast kernels")

H, W = 12, 20  # 240 pixels: with 64-pixel tiles, 4 tiles (the last one short)


@pytest.fixture
def small_tiles(monkeypatch):
    """Tiles of 64 pixels, so a small profile has several (the tiling fixes the random streams; both sides
    of each comparison use the same one)."""
    monkeypatch.setattr(fast, "TILE_PIXELS", 64)


def _profile(reset="interval"):
    return sensor.SensorProfile.synthetic(H, W, threshold_e=30, dark_rate=0.03, prnu_sigma=0.05,
                                          hot_pixel_fraction=0.05, seed=4, reset=reset)


def _keyframes(n=40, seed=2):
    rng = np.random.default_rng(seed)
    t = np.concatenate([[0.0], np.sort(rng.uniform(0.0, 0.25, n - 1))])
    return t, rng.uniform(0.0, 6.0, (n, H, W)).astype(np.float32)


def _stream(prof, model, rate, t, step, lookahead, switch_at=None):
    """Spikes (n, H, W) of a stream fed ``step`` rows at a time; ``switch_at``: the call from which
    lookahead is turned off."""
    sim = sensor.SpikeSimulator(prof, model, seed=11, per_interval=t is None)
    blocks = []
    for k, i in enumerate(range(0, rate.shape[0], step)):
        ahead = lookahead and (switch_at is None or k < switch_at)
        blocks += list(sim.iter_feed_packed(rate[i:i + step].copy(), None if t is None else t[i:i + step],
                                            owned=True, lookahead=ahead))
    blocks += list(sim.iter_finish_packed())
    assert all(b.shape[0] == sim.block for b in blocks[:-1])  # whole blocks, in order, the partial one last
    return unpack_frames(np.concatenate(blocks), prof.shape), sim


@pytest.mark.parametrize("threads", ["1", "2"])
@pytest.mark.parametrize("model,reset", [("elssim", "interval"), ("elssim", "crossing"), ("ideal", "interval"),
                                         ("isi", "interval")])
def test_lookahead_gives_the_spikes_of_the_plain_stream(small_tiles, monkeypatch, model, reset, threads):
    monkeypatch.setenv("RENDER2SPIKE_THREADS", threads)
    prof = _profile(reset)
    t, rate = _keyframes()
    plain, _ = _stream(prof, model, rate, t, step=7, lookahead=False)
    assert plain.shape[0] > 4 * sensor.SpikeSimulator(prof, model).block  # several blocks in flight in turn
    assert plain.any() and not plain.all()
    for step in (3, 7, 40):  # keyframes in small chunks (blocks span calls) and all at once
        got, sim = _stream(prof, model, rate, t, step=step, lookahead=True)
        np.testing.assert_array_equal(got, plain)
        assert sim._inflight is None and sim.finished


def test_lookahead_with_rates_per_interval_joined_from_chunks(small_tiles, monkeypatch):
    """One rate per interval in chunks that are not whole blocks: each block's rows are joined in a scratch
    buffer, and the block in flight still reads its own while the next block's are joined (two buffers in
    turn; with one, the spikes of the block in flight change)."""
    monkeypatch.setenv("RENDER2SPIKE_THREADS", "2")  # blocks run beside the main thread even on one CPU
    prof = _profile()
    block = sensor.SpikeSimulator(prof).block
    rate = np.random.default_rng(9).uniform(0.0, 4.0, (6 * block + 123, H, W)).astype(np.float32)
    rate[block:2 * block] *= 5.0  # blocks of different light: a block read with another's rows shows it
    plain, _ = _stream(prof, "elssim", rate, None, step=700, lookahead=False)
    got, sim = _stream(prof, "elssim", rate, None, step=700, lookahead=True)
    np.testing.assert_array_equal(got, plain)
    assert sum(b is not None for b in sim.schedule._scratch_pair) == 2  # both buffers were used


def test_turning_lookahead_off_hands_over_the_block_in_flight_first(small_tiles):
    prof = _profile()
    t, rate = _keyframes()
    plain, _ = _stream(prof, "elssim", rate, t, step=5, lookahead=False)
    got, _ = _stream(prof, "elssim", rate, t, step=5, lookahead=True, switch_at=3)
    np.testing.assert_array_equal(got, plain)


def test_finish_packed_includes_the_block_in_flight(small_tiles):
    prof = _profile()
    t, rate = _keyframes()
    plain, _ = _stream(prof, "elssim", rate, t, step=40, lookahead=False)
    sim = sensor.SpikeSimulator(prof, "elssim", seed=11)
    head = list(sim.iter_feed_packed(rate.copy(), t, owned=True, lookahead=True))
    assert sim._inflight is not None  # the last whole block is still running, or done and not yet handed over
    got = unpack_frames(np.concatenate(head + [sim.finish_packed()]), prof.shape)
    np.testing.assert_array_equal(got, plain)
    assert sim.finish_packed().shape == (0, sim.n_bytes)  # the stream has ended


def test_lookahead_needs_owned_input():
    prof = _profile()
    t, rate = _keyframes()
    sim = sensor.SpikeSimulator(prof, "elssim", seed=1)
    with pytest.raises(ValueError, match="owned=True"):
        list(sim.iter_feed_packed(rate, t, lookahead=True))


def test_reference_models_ignore_lookahead():
    prof = _profile()
    t, rate = _keyframes(12)
    runs = []
    for ahead in (False, True):
        sim = sensor.SpikeSimulator(prof, "elssim", seed=11, implementation="reference")
        runs.append(list(sim.iter_feed_packed(rate.copy(), t, owned=True, lookahead=ahead)))
        runs[-1].append(sim.finish_packed())
    np.testing.assert_array_equal(np.concatenate(runs[0]), np.concatenate(runs[1]))
    assert len(runs[0]) == len(runs[1]) > 2


@pytest.mark.parametrize("model", ["elssim", "ideal", "isi"])
def test_submit_segments_agrees_with_run_segments(small_tiles, model):
    """The model's two entry points: blocks started with ``after`` chained, and blocks run one at a time."""
    prof = _profile()
    a, b = get_model(model, prof, "fast"), get_model(model, prof, "fast")
    sa, sb = a.init_state(), b.init_state()
    rng = np.random.default_rng(0)
    futs, outs, ref = None, [], []
    for k in range(5):
        m0, m1 = 37 * k, 37 * (k + 1)
        seg = Segments.per_interval(rng.uniform(0, 9, (m1 - m0, H * W)).astype(np.float32), m0)
        out = np.full((m1 - m0, a.n_bytes), 0xFF, np.uint8)  # whatever it holds: the tiles clear their bytes
        futs = a.submit_segments(seg, sa, block_generator(3, model, k, "fast"), out, after=futs)
        outs.append(out)
        ref.append(b.run_segments(seg, sb, block_generator(3, model, k, "fast")))
    for f in futs:
        f.result()
    np.testing.assert_array_equal(np.concatenate(outs), np.concatenate(ref))
    assert sa["m"] == sb["m"] == 185
    for key in sa:
        np.testing.assert_array_equal(sa[key], sb[key])
    with pytest.raises(ValueError, match="one future per tile"):
        a.submit_segments(Segments.per_interval(np.ones((2, H * W), np.float32), 185), sa,
                          block_generator(3, model, 5, "fast"), np.empty((2, a.n_bytes), np.uint8), after=futs[:1])


def test_the_schedule_joins_rows_into_two_buffers_in_turn():
    """Rows joined from two chunks stay as they were through the next join (the block in flight reads them)."""
    from sensor.rates import RateSchedule
    sched = RateSchedule(50e-6, per_interval=True)
    rows = np.arange(10 * 6, dtype=np.float32).reshape(10, 2, 3)
    for a, b in ((0, 3), (3, 7), (7, 10)):
        sched.add(rows[a:b].copy(), copy=False, owned=True)
    first = sched._gather(2, 5, scratch=True)  # spans the first two chunks
    kept = first.copy()
    second = sched._gather(5, 9, scratch=True)  # spans the last two
    np.testing.assert_array_equal(first, kept)
    np.testing.assert_array_equal(second, rows[5:9])
    assert not np.shares_memory(first, second)


def test_each_tile_waits_for_the_same_tile_of_the_block_before(small_tiles, monkeypatch):
    """Tile 0 of every block is made slow; with two threads the next block's tile 0 would start on the other
    thread while it still runs, unless it waits for it."""
    import threading
    import time
    monkeypatch.setenv("RENDER2SPIKE_THREADS", "2")
    log, lock = [], threading.Lock()
    tile = fast.ELSSimFast._tile

    def timed(self, seg, state, rng, p0, p1, out):
        t0 = time.perf_counter()
        if p0 == 0:
            time.sleep(0.02)
        tile(self, seg, state, rng, p0, p1, out)
        with lock:
            log.append((p0, seg.m0, t0, time.perf_counter()))

    monkeypatch.setattr(fast.ELSSimFast, "_tile", timed)
    prof = _profile()
    t, rate = _keyframes()
    _stream(prof, "elssim", rate, t, step=40, lookahead=True)
    for p0 in {e[0] for e in log}:
        runs = sorted((m0, t0, t1) for q, m0, t0, t1 in log if q == p0)
        assert len(runs) >= 5
        for (_, _, end), (_, start, _) in zip(runs, runs[1:]):
            assert start >= end  # this tile of block k + 1 began after it ended in block k


def test_feed_after_lookahead_hands_over_the_block_in_flight_unpacked(small_tiles):
    prof = _profile()
    t, rate = _keyframes()
    plain, _ = _stream(prof, "elssim", rate, t, step=40, lookahead=False)
    sim = sensor.SpikeSimulator(prof, "elssim", seed=11)
    head = list(sim.iter_feed_packed(rate[:20].copy(), t[:20], owned=True, lookahead=True))
    assert sim._inflight is not None
    rest = sim.feed(rate[20:], t[20:])  # begins with the block in flight, as bool frames like the rest
    assert rest.dtype == bool and rest.ndim == 3
    got = np.concatenate([unpack_frames(np.concatenate(head), prof.shape), rest, sim.finish()])
    np.testing.assert_array_equal(got, plain)


def test_a_failed_block_ends_the_stream(small_tiles, monkeypatch):
    monkeypatch.setenv("RENDER2SPIKE_THREADS", "2")
    tile = fast.ELSSimFast._tile

    def failing(self, seg, state, rng, p0, p1, out):
        if seg.m0 == 2 * fast.FAST_BLOCK_INTERVALS and p0 == 64:  # tile 1 of the third block
            raise FloatingPointError("tile broke")
        tile(self, seg, state, rng, p0, p1, out)

    monkeypatch.setattr(fast.ELSSimFast, "_tile", failing)
    prof = _profile()
    t, rate = _keyframes()
    sim = sensor.SpikeSimulator(prof, "elssim", seed=11)
    got = []
    with pytest.raises(FloatingPointError, match="tile broke"):
        for bits in sim.iter_feed_packed(rate.copy(), t, owned=True, lookahead=True):
            got.append(bits)
    assert len(got) == 2  # the blocks before the failed one were handed over
    with pytest.raises(RuntimeError, match="start a new SpikeSimulator"):
        sim.finish_packed()  # no silent gap where the failed block was
    with pytest.raises(RuntimeError, match="FloatingPointError"):
        list(sim.iter_feed_packed(rate[:2].copy(), t[:2] + 1.0, owned=True, lookahead=True))
