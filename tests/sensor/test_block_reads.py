"""Block-aligned reads and fused read passes of `render2spike simulate`: the keyframes of each simulator
block arrive as one array (no join), Phi is scaled and checked in one pass, rates are checked in one
pass -- and none of it changes a value or a spike."""


import numpy as np
import pytest

import sensor
from render2spike.cli import main
from sensor.io.reader import RateSource, plan_reads
from sensor.io.fastio import count_bad, scale_checked
from sensor.rates import RateSchedule, block_keyframe_rows
from sensor.units import photoelectron_rate, photoelectron_scale

OpenEXR = pytest.importorskip("OpenEXR")


# ------------------------------------------------------------------------------------------ fused passes
def test_scale_checked_is_photoelectron_rate_bit_for_bit_and_counts_bad_values():
    rng = np.random.default_rng(3)
    base = rng.uniform(0, 3e16, (40, 61)).astype(np.float32)
    src = base[:, ::2]  # strided, as a channel sliced out of a file's bytes
    scale = photoelectron_scale(20e-6, 0.5, 50e-6)
    out = np.empty(src.shape, np.float32)
    assert scale_checked(src, scale, out) == 0
    np.testing.assert_array_equal(out, photoelectron_rate(src, 20e-6, 0.5, 50e-6))
    bad = src.copy()
    bad[1, 2], bad[3, 4], bad[5, 6], bad[7, 8] = np.nan, np.inf, -1.0, -0.0  # -0.0 is >= 0: allowed
    assert scale_checked(bad, scale, out) == 3


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_count_bad_counts_non_finite_and_negative(dtype):
    a = np.random.default_rng(1).uniform(0, 9, (5, 7, 3)).astype(dtype)
    assert count_bad(a) == 0 and count_bad(a[:, ::2]) == 0 and count_bad(a[:0]) == 0
    a[0, 0, 0], a[2, 3, 1], a[4, 6, 2] = np.nan, -np.inf, -1e-30
    assert count_bad(a) == 3
    assert count_bad(a[:, ::2]) == int((~np.isfinite(a[:, ::2]) | (a[:, ::2] < 0)).sum())


def test_read_scaled_equals_the_rate_of_read_phi_and_keeps_its_errors(tmp_path):
    p = sensor.SensorProfile.load("vidar-default")
    scale = photoelectron_scale(p.pixel_pitch_m, p.fill_factor, p.interval_s)
    phi = np.random.default_rng(2).uniform(1e14, 2e16, (3, 9, 13)).astype(np.float32)
    sensor.write_frames(tmp_path / "fr", phi, [0.0, 1e-3, 2e-3])
    seq = sensor.read_frames(tmp_path / "fr")
    out = np.empty((9, 13), np.float32)
    for i in range(3):
        np.testing.assert_array_equal(seq.read_scaled(i, scale, out), sensor.photoelectron_rate(seq.read_phi(i), p))
    # a compressed file takes the general path: same values
    fr = sensor.read_frame(seq.path(1))
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
                       "time_s": np.array(fr.time_s, np.float64)}, {"Phi": fr.phi, "E": fr.illuminance_lux}) as f:
        f.write(str(seq.path(1)))
    np.testing.assert_array_equal(seq.read_scaled(1, scale, out), sensor.photoelectron_rate(phi[1], p))
    # a bad pixel is named, as read_phi names it
    bad = phi[2].copy()
    bad[4, 5] = np.nan
    sensor.write_frame(seq.path(2), bad, time_s=2e-3)
    with pytest.raises(sensor.FrameFileError, match=r"\(row, col\) = \(4, 5\)"):
        seq.read_scaled(2, scale, out)
    sensor.write_frame(seq.path(2), phi[2], time_s=2.5e-3)  # header time disagrees with frames.json
    with pytest.raises(sensor.FrameFileError, match="time_s"):
        seq.read_scaled(2, scale, out)


# ------------------------------------------------------------------------------------------ block rows
KEYFRAME_TIMES = {
    "1 kHz": np.arange(301) * 1e-3,
    "300 Hz": np.arange(0, 0.3001, 1 / 300),
    "irregular": np.cumsum(np.random.default_rng(4).uniform(1e-4, 4e-3, 200)),
    "sparse": np.array([0.0, 0.11, 0.31]),
    "per interval": np.arange(2400) * 50e-6,
    "off grid": 0.0123 + np.arange(120) * 0.8e-3,
    # keyframes on (or a round-off away from) block boundaries: the schedule runs a block as soon as the
    # keyframes fed cover it within its tolerance, and the plan must follow it (a review found these)
    "10 Hz": np.arange(11) / 10,
    "10 Hz from 0.3 s": 0.3 + np.arange(11) / 10,
    "0.15 s apart": 0.01 + np.arange(5) * 0.15,
    "a hair before a block end": np.array([0.0, 0.1 - 1e-12, 0.2]),
}


@pytest.mark.parametrize("name", KEYFRAME_TIMES)
def test_block_rows_cover_every_keyframe_and_only_overlap_at_block_boundaries(name):
    t = KEYFRAME_TIMES[name]
    rows = block_keyframe_rows(t, 1000)
    assert rows[0][0] == 0 and rows[-1][1] == t.size
    for (i0, j0), (i1, j1) in zip(rows, rows[1:]):
        assert i0 <= i1 <= j0 < j1 and j0 - i1 <= 2  # advancing; one or two shared keyframes at most


@pytest.mark.parametrize("name", KEYFRAME_TIMES)
def test_block_aligned_chunks_give_the_same_spikes_and_are_never_joined(name):
    t = KEYFRAME_TIMES[name]
    prof = sensor.SensorProfile.synthetic(6, 10, threshold_e=40, dark_rate=0.02, prnu_sigma=0.05, seed=1)
    rate = np.random.default_rng(5).uniform(0, 8, (t.size, 6, 10)).astype(np.float32)
    whole = sensor.simulate(rate, prof, "elssim", seed=7, t_s=t)
    sim = sensor.SpikeSimulator(prof, "elssim", 7)
    got, end = [], 0
    for i, j in block_keyframe_rows(t, sim.block):
        ov = end - i if end else 0
        got += list(sim.iter_feed_packed(rate[i:j].copy(), t[i:j], owned=True, overlap=ov))
        end = j
    got.append(sim.finish_packed())
    spikes = sensor.io.spikefile.unpack_frames(np.concatenate(got), prof.shape)
    np.testing.assert_array_equal(spikes, whole)
    assert all(b is None for b in sim.schedule._scratch_pair)  # no block's keyframes were ever joined from two chunks


def test_overlap_must_repeat_the_last_keyframes_and_leaves_the_stream_intact_when_refused():
    s = RateSchedule()
    s.add(np.ones((3, 2, 2), np.float32), [0.0, 1e-3, 2e-3])
    with pytest.raises(sensor.InputError, match="overlap=1"):
        s.add(np.ones((2, 2, 2), np.float32), [2.5e-3, 3e-3], overlap=1)
    with pytest.raises(sensor.InputError, match="frame shape"):
        s.add(np.ones((2, 3, 3), np.float32), [2e-3, 3e-3], overlap=1)
    assert s._n == 3 and s._t.tolist() == [0.0, 1e-3, 2e-3]
    s.add(np.full((2, 2, 2), 2, np.float32), [2e-3, 3e-3], overlap=1)  # replaces the repeated row
    assert s._n == 4 and s._t.tolist() == [0.0, 1e-3, 2e-3, 3e-3] and float(s._gather(2, 3)[0, 0, 0]) == 2
    p = RateSchedule(per_interval=True)
    with pytest.raises(sensor.InputError, match="overlap"):
        p.add(np.ones((2, 2, 2), np.float32), overlap=1)


def test_cli_default_block_reads_equal_fixed_chunks_and_the_python_api(tmp_path):
    prof = sensor.SensorProfile.synthetic(8, 16, threshold_e=50, dark_rate=0.01, prnu_sigma=0.05, seed=2)
    prof_path = prof.save(tmp_path / "cam.npz")
    t = np.arange(0, 0.1201, 1e-3)  # 121 keyframes: three blocks, the last partial
    phi = np.random.default_rng(8).uniform(1e15, 2e16, (t.size, 8, 16)).astype(np.float32)
    sensor.write_frames(tmp_path / "fr", phi, t)
    outs = []
    for extra in ([], ["--chunk", "7"]):
        out = tmp_path / f"s{len(extra)}.npz"
        assert main(["simulate", str(tmp_path / "fr"), "--out", str(out), "--profile", str(prof_path), "--seed",
                     "3", "--quiet", *extra]) == 0
        outs.append(sensor.read_spikes(out))
    np.testing.assert_array_equal(outs[0], outs[1])
    want = sensor.simulate(photoelectron_rate(phi, prof.pixel_pitch_m, prof.fill_factor, prof.interval_s), prof,
                           "elssim", seed=3, t_s=t)
    np.testing.assert_array_equal(outs[0], want)
    src = RateSource(tmp_path / "fr")
    sim = sensor.SpikeSimulator(prof, "elssim", 3)
    assert plan_reads(src, sim)[0] == [(0, 51), (50, 101), (100, 121)]
    assert main(["simulate", str(tmp_path / "fr"), "--out", str(tmp_path / "x.npz"), "--chunk", "0"]) == 2


def test_chunk_pool_reuses_only_arrays_nobody_holds():
    from sensor.io.reader import ChunkPool as _ChunkPool
    pool = _ChunkPool(keep=3)
    a = pool.take((2, 3))
    a_id = id(a)
    view = a[1:]
    del a
    b = pool.take((2, 3))
    assert id(b) != a_id  # still referenced through the view's base
    del view
    c = pool.take((2, 3))
    assert id(c) == a_id  # now free: recycled
    assert pool.take((4, 3)).shape == (4, 3)  # another shape: a new array


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("compressed", [False, True])
def test_npz_keyframes_read_block_by_block_give_the_python_api_spikes(tmp_path, dtype, compressed):
    prof = sensor.SensorProfile.synthetic(5, 8, threshold_e=30, dark_rate=0.02, prnu_sigma=0.05, seed=4)
    prof_path = prof.save(tmp_path / "cam.npz")
    t = 0.004 + np.arange(0, 0.1101, 0.7e-3)  # keyframes off the block grid: two rows shared per boundary
    rate = np.random.default_rng(6).uniform(0, 6, (t.size, 5, 8)).astype(dtype)
    (np.savez_compressed if compressed else np.savez)(tmp_path / "r.npz", rate_e=rate, t_s=t)
    assert main(["simulate", str(tmp_path / "r.npz"), "--out", str(tmp_path / "s.npz"), "--profile", str(prof_path),
                 "--seed", "2", "--quiet"]) == 0
    want = sensor.simulate(rate.astype(np.float32), prof, "elssim", seed=2, t_s=t)
    np.testing.assert_array_equal(sensor.read_spikes(tmp_path / "s.npz"), want)
    src = RateSource(tmp_path / "r.npz")  # stored: memory-mapped like an .npy; deflated: decoded from the stream
    assert (src.rate is not None) == (not compressed) and (src._member is not None) == compressed
    src.close()


@pytest.mark.parametrize("damage", ["table", "scanline y", "scanline size"])
def test_read_scaled_checks_the_layout_of_every_frame_not_only_the_first(tmp_path, damage):
    """Frames after the first reuse the first one's parsed header; each frame's offset table and scanline
    heads are still checked, so a damaged frame is never sliced at the wrong place."""
    import struct
    p = sensor.SensorProfile.load("vidar-default")
    scale = photoelectron_scale(p.pixel_pitch_m, p.fill_factor, p.interval_s)
    phi = np.random.default_rng(3).uniform(1e14, 2e16, (2, 6, 5)).astype(np.float32)
    sensor.write_frames(tmp_path / "fr", phi, [0.0, 1e-3])
    seq = sensor.read_frames(tmp_path / "fr")
    out = np.empty((6, 5), np.float32)
    seq.read_scaled(0, scale, out)
    assert seq._hdr is not None  # the layout is remembered
    data = bytearray(seq.path(1).read_bytes())
    pos, H = seq._hdr[4], 6
    first = pos + 8 * H
    if damage == "table":
        struct.pack_into("<Q", data, pos + 8 * 2, 7)
    elif damage == "scanline y":
        struct.pack_into("<i", data, first + 3 * (8 + 2 * 5 * 4), 99)
    else:
        struct.pack_into("<i", data, first + 4, 12)
    seq.path(1).write_bytes(bytes(data))
    from sensor.io.fastio import exr_scale_checked
    from sensor.io.frames import _exr_header, _exr_views
    hdr = _exr_header(data, "Phi")
    table, heads, src = _exr_views(data, hdr)
    assert exr_scale_checked(table, heads, src, first, 8 + hdr[4], hdr[3], hdr[4], scale, out) == -1  # refused
    intact = bytearray(sensor.io.frames.Path(seq.path(0)).read_bytes())
    table, heads, src = _exr_views(intact, hdr)
    assert exr_scale_checked(table, heads, src, first, 8 + hdr[4], hdr[3], hdr[4], scale, out) == 0
    try:
        got = seq.read_scaled(1, scale, out).copy()
    except sensor.FrameFileError:
        return  # refused, naming the file: fine
    # or read by OpenEXR's own reader (which may repair an offset table): then with the true values
    np.testing.assert_array_equal(got, sensor.photoelectron_rate(phi[1], p))


@pytest.mark.parametrize("compressed", [False, True])
def test_a_bad_rate_in_an_npz_is_named_by_its_absolute_index(tmp_path, capsys, compressed):
    prof = sensor.SensorProfile.synthetic(4, 8, threshold_e=30, seed=1)
    t = np.arange(0, 0.1201, 1e-3)
    rate = np.ones((t.size, 4, 8), np.float32)
    rate[97, 2, 3] = np.nan  # in the second block's read
    (np.savez_compressed if compressed else np.savez)(tmp_path / "r.npz", rate_e=rate, t_s=t)
    assert main(["simulate", str(tmp_path / "r.npz"), "--out", str(tmp_path / "s.npz"), "--profile",
                 str(prof.save(tmp_path / "cam.npz")), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "r.npz" in err and "[97, 2, 3]" in err and "Traceback" not in err
    assert not (tmp_path / "s.npz").exists()


@pytest.mark.parametrize("per_interval", [False, True])
def test_a_damaged_stored_npz_is_refused_by_its_crc(tmp_path, capsys, per_interval):
    """A stored member is memory-mapped, not read through the zip stream, but its CRC-32 is still checked."""
    import zipfile
    prof = sensor.SensorProfile.synthetic(4, 8, threshold_e=30, seed=1)
    t = np.arange(0, 0.1201, 1e-3)
    rate = np.random.default_rng(2).uniform(0, 5, (t.size, 4, 8)).astype(np.float32)
    np.savez(tmp_path / "r.npz", **({"rate_e": rate} if per_interval else {"rate_e": rate, "t_s": t}))
    args = ["--out", str(tmp_path / "s.npz"), "--profile", str(prof.save(tmp_path / "cam.npz")), "--quiet"]
    assert main(["simulate", str(tmp_path / "r.npz"), *args]) == 0  # intact: accepted
    (tmp_path / "s.npz").unlink()
    data = bytearray((tmp_path / "r.npz").read_bytes())
    with zipfile.ZipFile(tmp_path / "r.npz") as zf:
        info = zf.getinfo("rate_e.npy")
    n_name, n_extra = np.frombuffer(bytes(data[info.header_offset + 26:info.header_offset + 30]), "<u2")
    at = info.header_offset + 30 + int(n_name) + int(n_extra) + info.file_size - 100  # in the last keyframe
    data[at] ^= 0x01  # one bit of one rate, still a finite positive float32
    (tmp_path / "r.npz").write_bytes(bytes(data))
    assert main(["simulate", str(tmp_path / "r.npz"), *args]) == 2
    err = capsys.readouterr().err
    assert "r.npz" in err and "CRC-32" in err and "damaged" in err
    assert not (tmp_path / "s.npz").exists()
