"""Memory that `render2spike simulate` keeps instead of asking the OS afresh per block, and frames read a
group at a time: neither may change a spike, a value or an error."""

import struct

import numpy as np
import pytest

import sensor
from sensor.io.buffers import RecyclingPool
from sensor.io.spikefile import SpikeWriter, pack_dat_frames
from sensor.io.frames import FrameSequence
from sensor.units import photoelectron_scale

OpenEXR = pytest.importorskip("OpenEXR")


# ------------------------------------------------------------------------------------------ the pool
def test_pool_recycles_only_arrays_nobody_holds_and_counts_it():
    pool = RecyclingPool(np.uint8, keep=2)
    a = pool.take((3, 4))
    assert a.dtype == np.uint8 and a.shape == (3, 4) and pool.recycled == 0
    a_id, held = id(a), a[:, 1]  # a view holds its base
    del a
    assert id(pool.take((3, 4))) != a_id and pool.recycled == 0
    del held
    assert id(pool.take((3, 4))) == a_id and pool.recycled == 1
    pool.take((5,))  # keep=2: the oldest array leaves the pool
    assert len(pool.arrays) == 2


def test_reserved_arrays_are_faulted_in_and_handed_out_only_once_written(monkeypatch):
    import threading
    from sensor.io import buffers
    gate, started = threading.Event(), threading.Event()
    real = buffers._fault_in

    def held(arrays):  # the helper, stopped before it writes: it holds every reserved array
        for a in arrays:
            a.fill(np.nan)  # so that "zeroed" below is the helper's doing, not the allocator's
        del a
        started.set()
        gate.wait(10)
        real(arrays)

    monkeypatch.setattr(buffers, "_fault_in", held)
    pool = RecyclingPool(np.float32, keep=4)
    th = pool.reserve((2, 3), 2)
    assert th is not None and len(pool.arrays) == 2 and all(a.shape == (2, 3) for a in pool.arrays)
    reserved = {a.__array_interface__["data"][0] for a in pool.arrays}  # addresses: no reference held here
    assert started.wait(10)
    a = pool.take((2, 3))  # the helper still holds both: a new array, not a reserved one
    assert pool.recycled == 0 and a.__array_interface__["data"][0] not in reserved
    gate.set()
    th.join(10)
    assert not th.is_alive()
    b = pool.take((2, 3))  # written and dropped by the helper: recycled, zeros
    assert pool.recycled == 1 and b.__array_interface__["data"][0] in reserved
    np.testing.assert_array_equal(b, 0)
    del a, b
    assert pool.reserve((2, 3), 0) is None and pool.reserve((0, 3), 2) is None
    pool._free = None  # where reference counts are deferred nothing is recycled, so nothing is reserved
    assert pool.reserve((2, 3), 2) is None


def test_reserve_never_holds_more_than_keep_arrays():
    pool = RecyclingPool(np.uint8, keep=3)
    pool.take((4,))
    pool.reserve((5,), 9).join(10)
    assert len(pool.arrays) == 3 and all(a.shape == (5,) for a in pool.arrays)


# ------------------------------------------------------------------------------------------ spike blocks
@pytest.fixture(scope="module")
def stream():
    prof = sensor.SensorProfile.synthetic(24, 40, threshold_e=20, dark_rate=0.01, prnu_sigma=0.05, seed=1,
                                          hot_pixel_fraction=0.02)
    t = np.arange(0, 0.16, 1e-3)
    rate = np.random.default_rng(5).uniform(0, 4, (t.size, 24, 40)).astype(np.float32)
    return prof, rate, t


def test_blocks_written_into_recycled_memory_are_the_fresh_blocks(stream):
    prof, rate, t = stream
    kept = sensor.SpikeSimulator(prof, "elssim", seed=7)
    want = [b.copy() for b in kept.iter_feed_packed(rate, t)]  # copies: every block's array is dropped
    want.append(kept.finish_packed())
    assert kept._bits.recycled >= 1  # so the later blocks were written into memory holding an earlier block
    fresh = sensor.SpikeSimulator(prof, "elssim", seed=7)
    fresh._bits._free = None  # recycling off: every block in a new array
    got = list(fresh.iter_feed_packed(rate, t)) + [fresh.finish_packed()]
    assert fresh._bits.recycled == 0
    assert len(want) == len(got) >= 3
    for w, g in zip(want, got):
        np.testing.assert_array_equal(w, g)
    # blocks the caller keeps are never written over
    held = list(sensor.SpikeSimulator(prof, "elssim", seed=7).iter_feed_packed(rate, t))
    assert len({id(b) for b in held}) == len(held)
    for w, g in zip(want, held):
        np.testing.assert_array_equal(w, g)


def test_run_segments_clears_a_dirty_out_and_checks_its_shape(stream):
    prof, rate, t = stream
    from sensor.models.step import block_generator
    from sensor.rates import RateSchedule
    sim = sensor.SpikeSimulator(prof, "elssim", seed=3)
    sched = RateSchedule(prof.interval_s)
    sched.add(rate, t)
    seg = sched.segments(0, sim.block)
    model = sim.model
    want = model.run_segments(seg, model.init_state(), block_generator(3, "elssim", 0, "fast"))
    dirty = np.full_like(want, 0xFF)
    got = model.run_segments(seg, model.init_state(), block_generator(3, "elssim", 0, "fast"), out=dirty)
    assert got is dirty
    np.testing.assert_array_equal(got, want)
    with pytest.raises(ValueError, match="out must be"):
        model.run_segments(seg, model.init_state(), block_generator(3, "elssim", 0, "fast"), out=dirty[:, 1:])


# ------------------------------------------------------------------------------------------ frame groups
@pytest.fixture()
def folder(tmp_path, monkeypatch):
    monkeypatch.setattr(FrameSequence, "GROUP_FRAMES", 3)  # groups of 3 and a partial one
    p = sensor.SensorProfile.load("vidar-default")
    phi = np.random.default_rng(8).uniform(1e14, 2e16, (11, 7, 9)).astype(np.float32)
    t = np.arange(11) * 1e-3
    sensor.write_frames(tmp_path / "fr", phi, t)
    return p, photoelectron_scale(p.pixel_pitch_m, p.fill_factor, p.interval_s), phi, t, tmp_path / "fr"


def _one_by_one(folder, scale, i, j):
    seq = sensor.read_frames(folder)
    out = np.empty((j - i,) + seq.shape, np.float32)
    for q in range(i, j):
        seq.read_scaled(q, scale, out[q - i])
    return out


def test_groups_equal_frames_read_one_by_one(folder):
    p, scale, phi, t, fr = folder
    seq = sensor.read_frames(fr)
    calls = []
    orig = seq.read_scaled
    seq.read_scaled = lambda q, *a: calls.append(q) or orig(q, *a)
    for i, j in [(0, 5), (4, 11)]:  # ranges that overlap and end in partial groups
        got = seq.read_scaled_many(i, j, scale, np.empty((j - i, 7, 9), np.float32))
        np.testing.assert_array_equal(got, sensor.photoelectron_rate(phi[i:j], p))
    assert calls == [0]  # only the first frame (which teaches the layout) went the general way


def test_a_frame_of_another_layout_in_a_group_is_read_the_general_way(folder):
    p, scale, phi, t, fr = folder
    seq = sensor.read_frames(fr)
    f = sensor.read_frame(seq.path(4))  # a compressed frame in the middle: another size and header
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
                       "time_s": np.array(f.time_s, np.float64)}, {"Phi": f.phi, "E": f.illuminance_lux}) as x:
        x.write(str(seq.path(4)))
    got = seq.read_scaled_many(0, 11, scale, np.empty((11, 7, 9), np.float32))
    np.testing.assert_array_equal(got, sensor.photoelectron_rate(phi, p))


@pytest.mark.parametrize("damage", ["nan", "negative", "time", "table", "scanline y", "missing", "truncated",
                                    "longer"])
def test_a_damaged_frame_in_a_group_raises_what_read_scaled_raises(folder, damage):
    p, scale, phi, t, fr = folder
    seq = sensor.read_frames(fr)
    seq.read_scaled(0, scale, np.empty((7, 9), np.float32))  # the layout is known
    path = seq.path(5)
    if damage in ("nan", "negative"):
        bad = phi[5].copy()
        bad[2, 3] = np.nan if damage == "nan" else -1.0
        sensor.write_frame(path, bad, time_s=t[5])
    elif damage == "time":
        sensor.write_frame(path, phi[5], time_s=t[5] + 1e-4)
    elif damage == "missing":
        path.unlink()
    else:
        data = bytearray(path.read_bytes())
        pos, H = seq._hdr[4], 7
        if damage == "table":
            struct.pack_into("<Q", data, pos + 8 * 2, 7)
        elif damage == "scanline y":
            struct.pack_into("<i", data, pos + 8 * H + 3 * (8 + 2 * 9 * 4), 99)
        elif damage == "truncated":
            data = data[:-10]
        else:
            data += b"\0" * 4
        path.write_bytes(bytes(data))
    try:
        want = _one_by_one(fr, scale, 0, 11)
    except sensor.FrameFileError as exc:
        with pytest.raises(sensor.FrameFileError) as got:
            seq.read_scaled_many(0, 11, scale, np.empty((11, 7, 9), np.float32))
        assert str(got.value) == str(exc)
        return
    # read one by one without error (a reader that repairs the damage): then grouped, the same values
    np.testing.assert_array_equal(seq.read_scaled_many(0, 11, scale, np.empty((11, 7, 9), np.float32)), want)


def test_the_compiled_group_pass_is_the_numpy_one(folder, monkeypatch):
    """exr_group_scale_checked over the files' bytes: compiled (each scanline's channel a contiguous row) and
    numpy (strided views) give the same values, bad-value counts and refusal, bit for bit."""
    from sensor.io import fastio
    from sensor.io.frames import _exr_header
    if not fastio.HAVE_NUMBA:
        pytest.skip("numba is not installed: only the numpy path exists")
    p, scale, phi, t, fr = folder
    seq = sensor.read_frames(fr)
    files = [bytearray(seq.path(q).read_bytes()) for q in range(6)]
    hdr = _exr_header(files[0], "Phi")
    pos, H, W, y0, line, offset = hdr[:6]
    bad_phi = phi[1].copy()
    bad_phi[0, 0], bad_phi[3, 4], bad_phi[6, 8] = np.nan, -2.0, np.inf
    sensor.write_frame(seq.path(1), bad_phi, time_s=t[1])
    files[1] = bytearray(seq.path(1).read_bytes())
    struct.pack_into("<i", files[4], pos + 8 * H + 5 * (8 + line), 99)  # frame 4: scanline 5 says y = 99
    buf = np.stack([np.frombuffer(f, np.uint8) for f in files])
    results = []
    for compiled in (True, False):
        monkeypatch.setattr(fastio, "HAVE_NUMBA", compiled and fastio.HAVE_NUMBA)
        out = np.full((6, H, W), -7.0, np.float32)
        bad = np.full(6, -1, np.int64)
        n = fastio.exr_group_scale_checked(buf, pos, H, W, y0, line, offset, scale, out, bad)
        results.append((n, out, bad))
    (n1, out1, bad1), (n2, out2, bad2) = results
    assert n1 == n2 == 4  # refused at the damaged frame; nothing of it written
    np.testing.assert_array_equal(bad1, bad2)
    assert list(bad1[:4]) == [0, 3, 0, 0]
    np.testing.assert_array_equal(out1.view(np.uint32), out2.view(np.uint32))
    assert (out1[4:] == -7.0).all()
    want = sensor.photoelectron_rate(phi[[0, 2, 3]], p)
    np.testing.assert_array_equal(out1[[0, 2, 3]], want)


@pytest.mark.parametrize("bad", [dict(offset=4 * 9 + 8), dict(offset=-4), dict(pos=-8), dict(W=0), dict(H=0),
                                 dict(line=4 * 9 - 4, offset=0)])
def test_the_group_pass_refuses_a_layout_whose_channel_leaves_its_scanline(bad):
    """The compiled pass trusts the layout (no bounds checks inside): the wrapper refuses one that is not."""
    from sensor.io.fastio import exr_group_scale_checked
    lay = dict(pos=0, H=2, W=9, y0=0, line=2 * 9 * 4, offset=9 * 4)
    lay.update(bad)
    buf = np.zeros((1, 4096), np.uint8)
    with pytest.raises(ValueError, match="not a layout"):
        exr_group_scale_checked(buf, lay["pos"], lay["H"], lay["W"], lay["y0"], lay["line"], lay["offset"], 1.0,
                                np.zeros((1, max(lay["H"], 0), max(lay["W"], 0)), np.float32), np.zeros(1, np.int64))


def test_cli_from_frames_in_groups_gives_the_python_api_spikes(folder, tmp_path):
    p, scale, phi, t, fr = folder
    from render2spike.cli import main
    cam = sensor.SensorProfile.synthetic(7, 9, threshold_e=300, dark_rate=0.01, prnu_sigma=0.05, seed=2)
    cam_path = cam.save(tmp_path / "cam.npz")
    assert main(["simulate", str(fr), "--out", str(tmp_path / "s.npz"), "--profile", str(cam_path), "--seed", "4",
                 "--quiet"]) == 0
    want = sensor.simulate(sensor.photoelectron_rate(phi, cam), cam, "elssim", seed=4, t_s=t)
    assert want.sum() > 100
    np.testing.assert_array_equal(sensor.read_spikes(tmp_path / "s.npz"), want)


# ------------------------------------------------------------------------------------------ direct writes
@pytest.mark.parametrize("direct", ["1", "0"])
def test_direct_stream_writes_the_bytes_given_whatever_the_block_sizes(tmp_path, monkeypatch, direct):
    from sensor.io.fileio import DirectStream
    monkeypatch.setenv("RENDER2SPIKE_DIRECT_IO", direct)
    rng = np.random.default_rng(9)
    sizes = [1, 4095, 4096, 4097, 3 << 20, 12345, 0, 2 << 20, 7, 0]  # the staging buffer grows past 1 MiB
    blocks = [rng.integers(0, 256, n, dtype=np.uint8) for n in sizes]
    f = DirectStream(tmp_path / "x.bin")
    if direct == "0":
        assert not f.direct
    for k, b in enumerate(blocks):
        if k % 2:
            f.write(b)
        else:  # fill in place, as the .dat writer does
            np.frombuffer(f.reserve(b.size), np.uint8)[:] = b
            f.commit(b.size)
    f.close()
    assert (tmp_path / "x.bin").read_bytes() == b"".join(b.tobytes() for b in blocks)


def test_direct_stream_falls_back_when_a_direct_write_is_refused(tmp_path, monkeypatch):
    import errno
    import os
    from sensor.io import fileio
    f = fileio.DirectStream(tmp_path / "x.bin")
    if not f.direct:
        f.close()
        pytest.skip("this file system has no O_DIRECT")
    real, calls = os.write, []

    def refuse_once(fd, data):
        calls.append(len(data))
        if len(calls) == 1:
            raise OSError(errno.EINVAL, "Invalid argument")
        return real(fd, data)
    monkeypatch.setattr(fileio.os, "write", refuse_once)
    data = np.arange(3 * 4096 + 5, dtype=np.uint32).view(np.uint8)
    f.write(data)
    assert not f.direct
    f.close()
    assert (tmp_path / "x.bin").read_bytes() == data.tobytes()


@pytest.mark.parametrize("width", [40, 37])  # whole bytes per row (re-ordered in place) or not
def test_dat_written_directly_equals_the_buffered_file(tmp_path, monkeypatch, width):
    bits = np.random.default_rng(2).random((70, 24, width)) < 0.1
    paths = {}
    for direct in ("1", "0"):
        monkeypatch.setenv("RENDER2SPIKE_DIRECT_IO", direct)
        paths[direct] = tmp_path / f"s{direct}.dat"
        with SpikeWriter(paths[direct], interval_s=50e-6, model="elssim", profile_id="x", seed=0,
                                background=True) as w:
            for k in range(0, 70, 30):  # blocks of 30, 30 and 10 frames
                w.write(bits[k:k + 30])
    if width * 24 % 8 == 0:
        assert paths["1"].read_bytes() == paths["0"].read_bytes() == pack_dat_frames(bits).tobytes()
        np.testing.assert_array_equal(sensor.read_spikes(paths["1"], height=24, width=width), bits)
    else:
        assert paths["1"].read_bytes() == paths["0"].read_bytes()


# ------------------------------------------------------------------------------------------ streamed .npz
@pytest.mark.parametrize("expected", [70, 50, 90, None])  # right, too few, too many, unknown
def test_a_streamed_container_holds_what_the_in_memory_one_holds(tmp_path, expected):
    bits = np.random.default_rng(4).random((70, 24, 40)) < 0.1
    kw = dict(interval_s=50e-6, model="elssim", profile_id="x", seed=3, source="s", extra={"k": 1})
    with SpikeWriter(tmp_path / "s.npz", background=True, expected_intervals=expected, **kw) as w:
        for k in range(0, 70, 30):
            w.write(bits[k:k + 30])
        assert (w._zip is not None) == (expected is not None) and (not w._blocks or expected is None)
    sensor.io.spikefile.write_spikes(tmp_path / "ref.npz", bits, **kw)
    got, meta = sensor.io.spikefile.read_spikes_with_meta(tmp_path / "s.npz")
    want, ref = sensor.io.spikefile.read_spikes_with_meta(tmp_path / "ref.npz")
    np.testing.assert_array_equal(got, want)
    for m in (meta, ref):
        m.pop("provenance")
    assert meta == ref and meta["n_intervals"] == 70
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ref.npz", "s.npz"]  # no temp file left


def test_a_streamed_container_of_no_intervals_and_one_aborted(tmp_path):
    kw = dict(interval_s=50e-6, model="elssim", profile_id="x", seed=3)
    with SpikeWriter(tmp_path / "e.npz", expected_intervals=10, **kw):
        pass
    with np.load(tmp_path / "e.npz") as z:  # as the in-memory writer writes it (no frame: no frame size)
        assert z["packed"].shape == (0, 0)
    with pytest.raises(RuntimeError):
        with SpikeWriter(tmp_path / "a.npz", expected_intervals=10, background=True, **kw) as w:
            w.write(np.ones((4, 8, 8), bool))
            raise RuntimeError("stop")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["e.npz"]


def test_frames_of_a_layout_not_grouped_are_read_one_at_a_time_once(folder, monkeypatch):
    """A folder whose layout the groups do not take (e.g. half-float Phi; here by decree) is read frame by frame,
    each file once."""
    p, scale, phi, t, fr = folder
    seq = sensor.read_frames(fr)
    import sensor.io.frames as F
    monkeypatch.setattr(F, "_groupable", lambda hdr: False)
    opened = []
    monkeypatch.setattr(F, "_read_files", lambda *a: opened.append(a) or 0)
    got = seq.read_scaled_many(0, 11, scale, np.empty((11, 7, 9), np.float32))
    np.testing.assert_array_equal(got, sensor.photoelectron_rate(phi, p))
    assert not opened


def test_a_dat_whose_last_write_fails_leaves_nothing_behind(tmp_path, monkeypatch):
    import errno
    from sensor.io import fileio
    w = SpikeWriter(tmp_path / "s.dat", interval_s=50e-6, model="elssim", profile_id="x", seed=0)
    w.write(np.ones((3, 8, 8), bool))  # 24 bytes: staged, written at close

    def full(fd, data):
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(fileio.os, "write", full)
    with pytest.raises((OSError, sensor.errors.Render2SpikeError)):
        w.close()
    assert list(tmp_path.iterdir()) == []


def test_a_truncated_frame_the_size_of_a_compressed_one_raises_read_scaled_s_error(folder):
    """The group width is the size of the last file read: after a compressed (smaller) frame, a truncated frame
    of exactly that size must still raise what read_scaled raises, not a reshape error (found in review)."""
    import os
    p, scale, phi, t, fr = folder
    seq = sensor.read_frames(fr)
    f = sensor.read_frame(seq.path(4))
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
                       "time_s": np.array(f.time_s, np.float64)}, {"Phi": f.phi, "E": f.illuminance_lux}) as x:
        x.write(str(seq.path(4)))
    seq.path(5).write_bytes(seq.path(5).read_bytes()[:os.path.getsize(seq.path(4))])
    with pytest.raises(sensor.FrameFileError) as one:
        _one_by_one(fr, scale, 0, 11)
    with pytest.raises(sensor.FrameFileError) as many:
        sensor.read_frames(fr).read_scaled_many(0, 11, scale, np.empty((11, 7, 9), np.float32))
    assert str(many.value) == str(one.value)


@pytest.mark.parametrize("suffix", [".dat", ".npz"])
def test_closing_a_writer_twice_keeps_the_file(tmp_path, suffix):
    bits = np.random.default_rng(1).random((5, 8, 8)) < 0.3
    kw = dict(interval_s=50e-6, model="elssim", profile_id="x", seed=0)
    with SpikeWriter(tmp_path / f"s{suffix}", expected_intervals=5, **kw) as w:
        w.write(bits)
        w.close()
    w.close()
    np.testing.assert_array_equal(sensor.read_spikes(tmp_path / f"s{suffix}", height=8, width=8), bits)
    with pytest.raises(ValueError, match="expected_intervals"):
        SpikeWriter(tmp_path / "n.npz", expected_intervals=-1, **kw)
