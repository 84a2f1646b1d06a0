"""`render2spike simulate`'s fast path: what it imports, Phi-only EXR reads, and that none of its shortcuts
(no duplicate check, no copies, background writing, warm-up, memory-mapped .npy rows) changes a spike."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import sensor
from render2spike.cli import build_parser, main, requested_command
from sensor.io.reader import RateSource
from sensor.io.frames import _exr_channel_fast, read_frame, read_phi, write_frame
from sensor.io.spikefile import SpikeWriter, count_bits, unpack_frames

ROOT = Path(__file__).resolve().parents[2]
OpenEXR = pytest.importorskip("OpenEXR")


def _frames(folder, n=6, shape=(8, 16), seed=0, compression=None):
    """n frames 1 ms apart of random Phi [e-/(s m^2)] (about 5-150 e-/interval at vidar-default's pixel)."""
    phi = np.random.default_rng(seed).uniform(5e14, 1.5e16, (n,) + shape).astype(np.float32)
    sensor.write_frames(folder, phi, np.arange(n) * 1e-3)
    if compression is not None:  # rewrite every frame compressed, same channels and header
        for i in range(n):
            p = Path(folder) / f"frame_{i:06d}.exr"
            fr = read_frame(p)
            hdr = {"compression": compression, "type": OpenEXR.scanlineimage,
                   "time_s": np.array(fr.time_s, np.float64)}
            with OpenEXR.File(hdr, {"Phi": fr.phi, "E": fr.illuminance_lux}) as f:
                f.write(str(p))
    return phi


def test_simulate_imports_neither_torch_nor_mitsuba_nor_scipy_stats(tmp_path):
    _frames(tmp_path / "fr")
    code = ("import sys; from render2spike.cli import main; "
            f"rc = main(['simulate', {str(tmp_path / 'fr')!r}, '--out', {str(tmp_path / 's.dat')!r}, '--quiet']); "
            "print(rc, sorted(m for m in sys.modules if m.split('.')[0] in "
            "('torch', 'mitsuba', 'drjit', 'skimage', 'matplotlib', 'dask', 'OpenEXR', 'numba') "
            "or m in ('scipy.stats', 'scipy.optimize', 'scipy.special', 'render2spike.commands.calibrate')))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=str(ROOT),
                       env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    assert r.returncode == 0, r.stderr
    rc, mods = r.stdout.split(" ", 1)
    assert rc == "0"
    loaded = {m.split(".")[0] for m in eval(mods)}  # noqa: S307 - our own repr of a list of names
    assert "numba" in loaded  # it did run the fast kernel
    assert loaded <= {"numba"}, loaded  # ... and nothing else of that list: not even OpenEXR, for these frames


def test_only_the_requested_command_is_registered():
    assert requested_command(["simulate", "x", "--out", "y"]) == "simulate"
    assert requested_command(["--help"]) is None and requested_command([]) is None
    assert requested_command(["no-such-command"]) is None
    sub = next(a for a in build_parser("simulate")._actions if a.dest == "command")
    assert list(sub.choices) == ["simulate"]
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    assert {"simulate", "calibrate", "render", "train"} <= set(sub.choices)


def test_unknown_command_still_lists_the_choices(capsys):
    with pytest.raises(SystemExit):
        main(["simulat"])
    assert "simulate" in capsys.readouterr().err


def test_phi_only_read_equals_openexr(tmp_path):
    phi = np.random.default_rng(1).uniform(0, 1e17, (5, 7)).astype(np.float32)
    E = np.random.default_rng(2).uniform(0, 9, (5, 7)).astype(np.float32)
    write_frame(tmp_path / "a.exr", phi, E, time_s=0.125, attrs={"made_by": {"x": [1, 2]}, "n": 3})
    t, got = read_phi(tmp_path / "a.exr")
    fr = read_frame(tmp_path / "a.exr")
    assert t == 0.125 == fr.time_s
    np.testing.assert_array_equal(got, fr.phi)
    np.testing.assert_array_equal(got, phi)
    assert got.dtype == np.float32 and got.flags.c_contiguous and got.flags.writeable
    out = np.zeros((5, 7), np.float32)
    assert read_phi(tmp_path / "a.exr", out=out)[1] is out
    np.testing.assert_array_equal(out, phi)


@pytest.mark.parametrize("ptype", ["half", "float"])
def test_phi_only_read_other_channel_sets_and_types(tmp_path, ptype):
    rng = np.random.default_rng(3)
    dt = np.float16 if ptype == "half" else np.float32
    chans = {"A": rng.uniform(0, 1, (4, 6)).astype(np.float32), "Phi": rng.uniform(0, 60000, (4, 6)).astype(dt),
             "Zeta": rng.uniform(0, 1, (4, 6)).astype(np.float16)}  # channels on both sides of Phi, mixed types
    hdr = {"compression": OpenEXR.NO_COMPRESSION, "type": OpenEXR.scanlineimage, "time_s": np.array(2.5)}
    with OpenEXR.File(hdr, chans) as f:
        f.write(str(tmp_path / "b.exr"))
    data = (tmp_path / "b.exr").read_bytes()
    fast = _exr_channel_fast(data, "Phi")
    assert fast is not None  # the uncompressed file is sliced, not decoded by OpenEXR
    with OpenEXR.File(str(tmp_path / "b.exr"), separate_channels=True) as f:
        ref = np.asarray(f.channels()["Phi"].pixels)
    np.testing.assert_array_equal(fast[1], ref)
    t, phi = read_phi(tmp_path / "b.exr")
    assert t == 2.5 and phi.dtype == np.float32
    np.testing.assert_array_equal(phi, ref.astype(np.float32))
    assert _exr_channel_fast(data, "E") is None  # no such channel: left to OpenEXR (which reports it)


def test_compressed_or_damaged_exr_falls_back_to_openexr(tmp_path):
    _frames(tmp_path / "z", n=2, compression=OpenEXR.ZIP_COMPRESSION)
    p = tmp_path / "z" / "frame_000001.exr"
    assert _exr_channel_fast(p.read_bytes(), "Phi") is None
    t, phi = read_phi(p)
    assert t == pytest.approx(1e-3)
    np.testing.assert_array_equal(phi, read_frame(p).phi)
    write_frame(tmp_path / "c.exr", np.ones((4, 4), np.float32), time_s=0.0)
    cut = tmp_path / "cut.exr"
    cut.write_bytes((tmp_path / "c.exr").read_bytes()[:-10])
    assert _exr_channel_fast(cut.read_bytes(), "Phi") is None
    with pytest.raises(sensor.FrameFileError, match="cut.exr"):
        read_phi(cut)


def test_a_negative_attribute_size_is_refused_not_walked_forever(tmp_path):
    """A damaged header whose attribute size is negative once sent the header walk back to the same
    attribute, forever: the fast reader now leaves the file to OpenEXR, which refuses it, naming it."""
    import struct
    write_frame(tmp_path / "a.exr", np.ones((2, 3), np.float32), time_s=0.0, attrs={"aa": 5})
    d = bytearray((tmp_path / "a.exr").read_bytes())
    at = d.find(b"aa\0int\0") + 7
    struct.pack_into("<i", d, at, -(7 + 4))  # back to the start of the same attribute
    (tmp_path / "b.exr").write_bytes(bytes(d))
    code = ("import sys; from sensor.io.frames import _exr_header; "
            f"print(_exr_header(open({str(tmp_path / 'b.exr')!r}, 'rb').read(), 'Phi'))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=str(ROOT), timeout=30,
                       env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    assert r.returncode == 0 and r.stdout.strip() == "None", r.stderr
    with pytest.raises(sensor.FrameFileError, match="b.exr"):
        read_phi(tmp_path / "b.exr")


def test_frames_read_phi_checks_like_read(tmp_path):
    _frames(tmp_path / "fr", n=3)
    write_frame(tmp_path / "fr" / "frame_000001.exr", np.full((8, 16), -1.0, np.float32), time_s=1e-3)
    seq = sensor.read_frames(tmp_path / "fr")
    with pytest.raises(sensor.FrameFileError, match="Phi"):
        seq.read_phi(1)
    write_frame(tmp_path / "fr" / "frame_000002.exr", np.ones((8, 16), np.float32), time_s=0.5)
    with pytest.raises(sensor.FrameFileError, match="time_s"):
        seq.read_phi(2)


def test_frames_fast_and_openexr_reads_give_the_same_spikes(tmp_path):
    prof = sensor.SensorProfile.load("vidar-default").window(0, 0, 8, 16)
    prof_path = prof.save(tmp_path / "cam.npz")
    phi = _frames(tmp_path / "raw", n=8, seed=4)
    _frames(tmp_path / "zip", n=8, seed=4, compression=OpenEXR.ZIP_COMPRESSION)
    for name in ("raw", "zip"):
        assert main(["simulate", str(tmp_path / name), "--out", str(tmp_path / f"{name}.npz"), "--profile",
                     str(prof_path), "--seed", "3", "--quiet", "--chunk", "3"]) == 0
    a, b = sensor.read_spikes(tmp_path / "raw.npz"), sensor.read_spikes(tmp_path / "zip.npz")
    np.testing.assert_array_equal(a, b)
    ref = sensor.simulate(sensor.photoelectron_rate(phi, prof), prof, "elssim", seed=3, t_s=np.arange(8) * 1e-3)
    np.testing.assert_array_equal(a, ref)
    assert a.sum() > 0


def test_photoelectron_rate_single_pass_is_the_float64_formula():
    from sensor.units import photoelectron_rate
    rng = np.random.default_rng(5)
    args = (20e-6, 0.5, 50e-6)
    scale = 20e-6 ** 2 * 0.5 * 50e-6
    for phi in (rng.uniform(0, 1e18, (6, 5)).astype(np.float32), rng.uniform(0, 1e18, 7), [3e15, 4e16],
                np.arange(4, dtype=np.int64)):
        want = (np.asarray(phi, np.float64) * scale).astype(np.float32)
        got = photoelectron_rate(phi, *args)
        assert got.dtype == np.float32 and got.shape == want.shape
        np.testing.assert_array_equal(got, want)
    x = rng.uniform(0, 1e18, (3, 4)).astype(np.float32)
    want = (x.astype(np.float64) * scale).astype(np.float32)
    assert photoelectron_rate(x, *args, out=x) is x
    np.testing.assert_array_equal(x, want)
    s = photoelectron_rate(2e16, *args)
    assert isinstance(s, np.float32) and s == np.float32(2e16 * scale)


@pytest.mark.parametrize("shape", [(0, 4), (1, 1), (3, 5), (7, 9), (2, 8), (5, 12500)])
def test_count_bits_any_shape_and_layout(shape):
    b = np.random.default_rng(6).integers(0, 256, shape, dtype=np.uint8)
    for v in (b, b[:, ::2], b[1:, 1:], b.T):
        assert count_bits(v) == int(np.unpackbits(np.ascontiguousarray(v)).sum())


@pytest.mark.parametrize("compiled", [True, False])
@pytest.mark.parametrize("shape", [(1, 1, 1), (3, 5, 7), (2, 8, 16), (4, 250, 50), (0, 3, 2)])
def test_flip_rows_counted_is_the_reversed_copy_and_the_bit_count(monkeypatch, shape, compiled):
    """The .dat writer's fused pass: rows reversed per frame and every set bit counted (the 8-byte words
    and the tail bytes: sizes here are and are not multiples of 8), compiled and with numpy alone."""
    from sensor.io import fastio
    if compiled and not fastio.HAVE_NUMBA:
        pytest.skip("numba is not installed")
    monkeypatch.setattr(fastio, "HAVE_NUMBA", compiled)
    bits = np.random.default_rng(11).integers(0, 256, shape, dtype=np.uint8)
    dst = np.full(shape, 7, np.uint8)
    n = fastio.flip_rows_counted(bits, dst)
    assert n == int(np.unpackbits(bits).sum())
    np.testing.assert_array_equal(dst, bits[:, ::-1, :])
    with pytest.raises(ValueError, match="bits must be C-contiguous"):
        fastio.flip_rows_counted(np.asfortranarray(np.zeros((2, 3, 4), np.uint8)), np.zeros((2, 3, 4), np.uint8))
    with pytest.raises(ValueError, match="dst must be"):
        fastio.flip_rows_counted(np.zeros((2, 3, 4), np.uint8), np.zeros((2, 4, 3), np.uint8))


@pytest.mark.parametrize("numba_loaded", [True, False])
@pytest.mark.parametrize("width", [24, 12])
def test_dat_writer_bytes_and_count_match_the_numpy_layout(tmp_path, monkeypatch, width, numba_loaded):
    """Blocks written to a .dat are :func:`packed_to_dat`'s bytes, back to back, and every spike is counted:
    through the staging buffer (W % 8 == 0; the compiled pass when numba is loaded, numpy when not) and
    the general way (W % 8 != 0)."""
    from sensor.io.spikefile import pack_frames, packed_to_dat
    if numba_loaded:
        pytest.importorskip("numba")  # loaded here, so the writer takes the compiled pass
    else:
        monkeypatch.delitem(sys.modules, "numba", raising=False)
    rng = np.random.default_rng(12)
    blocks = [pack_frames(rng.random((n, 6, width)) < 0.2) for n in (4, 1, 7)]
    with SpikeWriter(tmp_path / "s.dat", interval_s=50e-6, model="elssim", profile_id="p", seed=1) as w:
        for b in blocks:
            w.write_packed(b, (6, width))
    assert w.n_intervals == 12 and w.n_spikes == sum(int(np.unpackbits(b).sum()) for b in blocks)
    want = b"".join(packed_to_dat(b, 6, width).tobytes() for b in blocks)
    assert (tmp_path / "s.dat").read_bytes() == want


@pytest.mark.parametrize("suffix", [".dat", ".npz"])
def test_background_writer_writes_the_same_file(tmp_path, suffix):
    rng = np.random.default_rng(7)
    blocks = [np.packbits(rng.random((n, 8 * 16)) < 0.1, axis=1, bitorder="little") for n in (5, 3, 9, 1)]
    for bg in (False, True):
        with SpikeWriter(tmp_path / f"{bg}{suffix}", interval_s=50e-6, model="elssim", profile_id="p", seed=1,
                         background=bg) as w:
            for b in blocks:
                w.write_packed(b, (8, 16))
        assert (w.n_intervals, w.n_spikes) == (18, sum(count_bits(b) for b in blocks))
    if suffix == ".dat":
        assert (tmp_path / "True.dat").read_bytes() == (tmp_path / "False.dat").read_bytes()
    else:
        np.testing.assert_array_equal(sensor.read_spikes(tmp_path / "True.npz"),
                                      sensor.read_spikes(tmp_path / "False.npz"))


def test_background_writer_error_reaches_the_caller_and_leaves_nothing(tmp_path):
    out = tmp_path / "s.dat"
    with pytest.raises(sensor.SpikeFileError, match="frame shape changed"):
        with SpikeWriter(out, interval_s=50e-6, model="elssim", profile_id="p", seed=1, background=True) as w:
            w.write_packed(np.zeros((2, 16), np.uint8), (8, 16))
            w.write_packed(np.zeros((2, 8), np.uint8), (8, 8))  # wrong shape: fails in the writer thread
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_checked_owned_feed_and_warm_up_change_no_spike():
    prof = sensor.SensorProfile.synthetic(8, 16, threshold_e=40, dark_rate=0.02, prnu_sigma=0.05, seed=1)
    rate = np.random.default_rng(8).uniform(0, 4, (90, 8, 16)).astype(np.float32)
    t = np.arange(90) * 1e-3
    ref = sensor.simulate(rate, prof, "elssim", seed=5, t_s=t, chunk=7)
    sim = sensor.SpikeSimulator(prof, "elssim", 5)
    sim.warm_up()
    parts = []
    for i in range(0, 90, 7):
        chunk = rate[i:i + 7].copy()
        parts += list(sim.iter_feed_packed(chunk, t[i:i + 7], checked=True, owned=True))
        if i == 0:  # 6 ms < one block: all of it is kept, and being handed over, without a copy
            assert np.shares_memory(sim.schedule._chunks[0], chunk)
    parts.append(sim.finish_packed())
    np.testing.assert_array_equal(unpack_frames(np.concatenate(parts), (8, 16)), ref)
    bad = rate[:3].copy()
    bad[1, 2, 3] = np.nan
    with pytest.raises(sensor.InputError, match=r"\[1, 2, 3\]"):
        list(sensor.SpikeSimulator(prof, "elssim", 5).iter_feed_packed(bad, t[:3]))  # checked=False: still checked


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_npy_rows_are_map_views_released_after_use(tmp_path, dtype):
    a = np.random.default_rng(9).uniform(0, 9, (6, 4, 3)).astype(dtype)
    np.save(tmp_path / "r.npy", a)
    src = RateSource(tmp_path / "r.npy")
    rows = src._npy_rows(1, 4)
    assert rows.dtype == np.float32
    assert rows.flags.writeable == (dtype is np.float64)  # float32: a view of the read-only map; else a copy
    src._release(0, 6)  # pages dropped from the process: the rows still read the file's values
    np.testing.assert_array_equal(rows, a[1:4].astype(np.float32))
    got = [r for r, _, _ in RateSource(tmp_path / "r.npy").chunks(None, [(0, 4), (4, 6)])]
    np.testing.assert_array_equal(np.concatenate(got), a.astype(np.float32))


def test_read_plan_covers_two_blocks_of_keyframes_within_a_memory_cap():
    from types import SimpleNamespace as NS

    from sensor.io.reader import plan_reads
    sim = NS(block=1000, interval_s=50e-6)  # 50 ms per block: 50 keyframes at 1 kHz
    kf = NS(per_interval=False, n=2001, t_s=np.arange(2001) * 1e-3, shape=(250, 400))
    bounds, ahead = plan_reads(kf, sim, 32)
    assert bounds[:2] == [(0, 32), (32, 64)] and ahead == 4  # ceil(2 * 50 / 32)
    assert plan_reads(kf, sim, 100)[1] == 1
    assert plan_reads(kf, sim, 32, max_bytes=3 * 32 * 4 * 250 * 400)[1] == 3
    bounds, ahead = plan_reads(kf, sim)  # default: one read per block, sharing the boundary keyframe
    assert bounds[:3] == [(0, 51), (50, 101), (100, 151)] and bounds[-1][1] == 2001 and ahead == 2
    big = NS(per_interval=False, n=2001, t_s=np.arange(2001) * 1e-4, shape=(250, 400))  # 500 rows per block
    assert plan_reads(big, sim)[0][:2] == [(0, 32), (32, 64)]  # 200 MB per block: fixed chunks instead
    bounds, ahead = plan_reads(NS(per_interval=True, n=5000, shape=(250, 400)), sim, 1)
    assert bounds == [(0, 1000), (1000, 2000), (2000, 3000), (3000, 4000), (4000, 5000)] and ahead == 1
    # a simulator that starts each block ahead overlaps the reads itself: no third block of rows held
    mapped = NS(per_interval=True, n=5000, shape=(250, 400), rate=np.zeros(0))
    assert plan_reads(mapped, NS(block=1000, looks_ahead=True), 1) == (bounds, 0)
    assert plan_reads(mapped, NS(block=1000, looks_ahead=False), 1)[1] == 1  # the reference: reads overlap it
    assert plan_reads(NS(per_interval=True, n=5000, shape=(250, 400), rate=None), NS(block=1000, looks_ahead=True),
                      1)[1] == 1  # a deflated member is decoded by the reader thread


@pytest.mark.parametrize("depth", [0, 1, 3])
def test_read_ahead_depth_gives_the_same_chunks(tmp_path, depth):
    p = sensor.SensorProfile.load("vidar-default").window(0, 0, 8, 16)
    phi = _frames(tmp_path / "fr", n=10)
    got = list(RateSource(tmp_path / "fr").chunks(p, [(0, 3), (3, 6), (6, 9), (9, 10)], prefetch=depth))
    assert [r.shape[0] for r, _, _ in got] == [3, 3, 3, 1]
    np.testing.assert_array_equal(np.concatenate([r for r, _, _ in got]), sensor.photoelectron_rate(phi, p))
    np.testing.assert_array_equal(np.concatenate([t for _, t, _ in got]), np.arange(10) * 1e-3)
    # overlapping ranges: the repeated rows come first, copied from the previous chunk
    got = list(RateSource(tmp_path / "fr").chunks(p, [(0, 4), (2, 7), (6, 10)], prefetch=depth))
    assert [(r.shape[0], ov) for r, _, ov in got] == [(4, 0), (5, 2), (4, 1)]
    want = sensor.photoelectron_rate(phi, p)
    for (r, t, _), (i, j) in zip(got, [(0, 4), (2, 7), (6, 10)]):
        np.testing.assert_array_equal(r, want[i:j])
        np.testing.assert_array_equal(t, np.arange(i, j) * 1e-3)
