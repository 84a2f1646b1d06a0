"""Spike-file layouts: hand-built files of every layout, corrupt files, and `render2spike convert`.

Each file is built here from the layout's published rules (not with the reader's
code) from one asymmetric pattern: H != W, a different spike count per row, per
column and per interval, so a transposed, flipped or time-reversed axis fails.
"""

import json
import zipfile

import numpy as np
import pytest

import sensor
from sensor.io.spikefile import LAYOUTS, detect_layout, read_spikes_with_meta

T, H, W = 11, 3, 8  # T not a multiple of 8 (RSIR's last plane is partial); H*W = 24 (whole .dat bytes)


def _pattern():
    s = np.zeros((T, H, W), bool)
    for t in range(T):
        for r in range(H):
            for c in range(W):
                # a time ramp (later intervals fire more) that differs by row and column
                s[t, r, c] = (t * (r + 1) + 3 * c) % (W + r) < 1 + t // 3
    s[0, 0, W - 1] = True  # one lone mark in the top-right corner of the first interval
    s[T - 1, H - 1, 0] = False
    return s


def test_pattern_is_asymmetric():
    s = _pattern()
    for axis_flip in (s[::-1], s[:, ::-1], s[:, :, ::-1]):
        assert not np.array_equal(axis_flip, s)
    assert len(set(s.sum(axis=(1, 2)).tolist())) > 3  # the ramp: counts per interval differ


def _dat_bytes(s, width_pad=0):
    """SpikeCV rule written out: rows bottom-up, pixel p = r*W + c -> byte p // 8, bit p % 8 (LSB first)."""
    out = bytearray()
    for frame in s:
        frame = np.pad(frame, ((0, 0), (0, width_pad)))
        hh, ww = frame.shape
        buf = bytearray(hh * ww // 8)
        for r_img in range(hh):
            r_st = hh - 1 - r_img
            for c in range(ww):
                if frame[r_img, c]:
                    p = r_st * ww + c
                    buf[p // 8] |= 1 << (p % 8)
        out += buf
    return bytes(out)


def _rsir_seq(s):
    """RSIR's dump rule: interval i is bit (i & 7) of plane i // 8."""
    seq = np.zeros(((s.shape[0] + 7) // 8,) + s.shape[1:], np.uint8)
    for i in range(s.shape[0]):
        seq[i // 8] |= (s[i].astype(np.uint8) << (i & 7))
    return seq


def _write_each_layout(tmp_path, s):
    files = {}
    files["dat"] = tmp_path / "a.dat"
    files["dat"].write_bytes(_dat_bytes(s))
    np.savez(tmp_path / "zoo.npz", spk=s.astype(np.uint8), label=np.zeros((H, W)))
    files["spikezoo"] = tmp_path / "zoo.npz"
    np.savez(tmp_path / "sim.npz", s.transpose(1, 2, 0).astype(np.int16))  # SpikingSIM: arr_0 (H, W, T)
    files["spikingsim"] = tmp_path / "sim.npz"
    np.savez(tmp_path / "rsir.npz", seq=_rsir_seq(s), tag=np.zeros((H, W), np.uint8), length=np.array(T))
    files["rsir"] = tmp_path / "rsir.npz"
    files["container"] = sensor.write_spikes(tmp_path / "c.npz", s, interval_s=5e-5, model="m", profile_id="p",
                                             seed=1)
    files["h5"] = sensor.write_h5(tmp_path / "h.h5", s)
    return files


def test_every_layout_reads_the_hand_built_pattern(tmp_path):
    s = _pattern()
    files = _write_each_layout(tmp_path, s)
    assert set(files) | {"vidar-raw"} == set(LAYOUTS)
    for layout, path in files.items():
        kw = {"height": H, "width": W} if layout == "dat" else {}
        got = sensor.read_spikes(path, **kw)
        assert got.dtype == bool and got.shape == (T, H, W), layout
        np.testing.assert_array_equal(got, s, err_msg=layout)
        if layout != "dat":
            assert detect_layout(path) == layout
        np.testing.assert_array_equal(sensor.read_spikes(path, layout=layout, **kw), s, err_msg=layout)


def test_rsir_bytes_by_hand(tmp_path):
    # 1 x 2 pixels, 9 intervals: pixel 0 fires at t = 0 and 8, pixel 1 at t = 3
    # plane 0 = [bit0, bit3] = [1, 8]; plane 1 = [bit0 (t=8), 0] = [1, 0]
    seq = np.array([[[1, 8]], [[1, 0]]], np.uint8)
    np.savez(tmp_path / "r.npz", seq=seq, length=np.array(9))
    s = sensor.read_spikes(tmp_path / "r.npz")
    assert s.shape == (9, 1, 2)
    assert np.flatnonzero(s[:, 0, 0]).tolist() == [0, 8] and np.flatnonzero(s[:, 0, 1]).tolist() == [3]


def test_vidar_raw_416_is_detected_and_cropped(tmp_path):
    rng = np.random.default_rng(5)
    raw = rng.random((2, 250, 416)) < 0.2
    p = sensor.write_dat(tmp_path / "raw.dat", raw)  # 2 x 13000 bytes: not a whole number of 12500-byte frames
    assert detect_layout(p) == "vidar-raw"
    np.testing.assert_array_equal(sensor.read_spikes(p), raw[:, :, :400])
    p2 = sensor.write_dat(tmp_path / "std.dat", raw[:, :, :400])
    assert detect_layout(p2) == "dat"
    np.testing.assert_array_equal(sensor.read_spikes(p2), raw[:, :, :400])


def test_any_height_and_width_for_dat(tmp_path):
    s = _pattern()[:, :, :]
    p = tmp_path / "x.dat"
    p.write_bytes(_dat_bytes(s))
    np.testing.assert_array_equal(sensor.read_spikes(p, height=H, width=W), s)
    # the old keyword arguments keep working
    np.testing.assert_array_equal(sensor.read_spikes(p, height=H, width=W, drop_columns=2), s[:, :, :W - 2])


# ------------------------------------------------------------------ one error path
def _err(path, **kw):
    with pytest.raises(sensor.SpikeFileError) as e:
        sensor.read_spikes(path, **kw)
    assert str(path.name) in str(e.value)
    return str(e.value)


def test_ambiguous_files_ask_for_layout(tmp_path):
    np.savez(tmp_path / "two.npz", spk=np.zeros((2, 2, 4), np.uint8), arr_0=np.zeros((2, 4, 2), np.uint8))
    assert "layout=" in _err(tmp_path / "two.npz")
    both = tmp_path / "both.dat"  # 325000 bytes = 26 frames of 250x400 = 25 raw frames of 250x416
    both.write_bytes(bytes(325000))
    msg = _err(both)
    assert "ambiguous" in msg and "layout=" in msg
    assert sensor.read_spikes(both, layout="vidar-raw").shape == (25, 250, 400)
    assert sensor.read_spikes(both, layout="dat").shape == (26, 250, 400)
    np.savez(tmp_path / "other.npz", foo=np.zeros(3))
    assert "no known spike layout" in _err(tmp_path / "other.npz")
    with pytest.raises(sensor.UnknownMethodError, match="rsir"):
        sensor.read_spikes(tmp_path / "other.npz", layout="nope")


def test_corrupt_truncated_and_inconsistent_files(tmp_path):
    s = _pattern()
    files = _write_each_layout(tmp_path, s)
    # truncated archives and HDF5: BadZipFile / EOFError / OSError inside -> one SpikeFileError
    for layout in ("container", "spikezoo", "rsir", "spikingsim", "h5"):
        p = files[layout]
        data = p.read_bytes()
        for cut in (len(data) // 2, len(data) - 30):
            q = tmp_path / f"cut-{cut}-{p.name}"
            q.write_bytes(data[:cut])
            _err(q, layout=layout)
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"PK\x03\x04 not really a zip")
    assert "corrupt" in _err(garbage)
    # a container whose height*width disagrees with its packed data (was silently zero-padded)
    meta = json.loads(bytes(np.load(files["container"])["meta_json"]).decode())
    meta["height"], meta["width"] = 2, 8
    np.savez(tmp_path / "bad.npz", packed=np.load(files["container"])["packed"],
             meta_json=np.frombuffer(json.dumps(meta).encode(), np.uint8))
    msg = _err(tmp_path / "bad.npz")
    assert "packed" in msg and "2 x 8" in msg
    meta["height"], meta["width"], meta["n_intervals"] = H, W, T + 1
    np.savez(tmp_path / "badn.npz", packed=np.load(files["container"])["packed"],
             meta_json=np.frombuffer(json.dumps(meta).encode(), np.uint8))
    assert "n_intervals" in _err(tmp_path / "badn.npz")
    # container without meta_json: KeyError inside -> named key
    np.savez(tmp_path / "nometa.npz", packed=np.zeros((1, 3), np.uint8))
    assert "meta_json" in _err(tmp_path / "nometa.npz", layout="container")
    # RSIR whose length disagrees with its planes; Spike-Zoo with counts instead of spikes
    np.savez(tmp_path / "r.npz", seq=_rsir_seq(s), length=np.array(T + 8))
    assert "length" in _err(tmp_path / "r.npz")
    np.savez(tmp_path / "z.npz", spk=np.full((2, 2, 4), 3, np.uint8))
    assert "other than 0 and 1" in _err(tmp_path / "z.npz")
    np.savez(tmp_path / "z2.npz", spk=np.zeros((2, 8), np.uint8))
    assert "(T, H, W)" in _err(tmp_path / "z2.npz")
    # a damaged member inside an intact zip directory
    zpath = tmp_path / "member.npz"
    with zipfile.ZipFile(zpath, "w") as zf:
        zf.writestr("spk.npy", b"\x93NUMPY\x01\x00v\x00{'descr': '|u1', 'fortran_order': False, 'shape': (9, 9, 9), }")
    _err(zpath)
    assert "does not exist" in _err(tmp_path / "missing.npz")


# ------------------------------------------------------------------------ convert
def test_convert_round_trips_through_every_output(tmp_path):
    from render2spike.commands.convert import convert
    s = _pattern()
    files = _write_each_layout(tmp_path, s)
    for layout, path in files.items():
        kw = {"height": H, "width": W} if layout == "dat" else {}
        for suffix in (".dat", ".npz", ".h5"):
            out = tmp_path / f"out-{layout}{suffix}"
            info = convert(path, out, **kw)
            assert info["layout"] == layout
            back, meta = read_spikes_with_meta(out, **({"height": H, "width": W} if suffix == ".dat" else {}))
            np.testing.assert_array_equal(back, s, err_msg=f"{layout} -> {suffix}")
            if suffix != ".dat":
                assert meta["input_layout"] == layout and meta["interval_s"] == 5e-5
    out = tmp_path / "u8.h5"
    convert(files["spikezoo"], out, h5_encoding="uint8")
    import h5py
    with h5py.File(out) as f:
        assert f["spikes"].dtype == np.uint8 and f["spikes"].shape == (T, H, W)
        assert f["spikes"].attrs["encoding"] == "uint8"
    np.testing.assert_array_equal(sensor.read_spikes(out), s)
    with h5py.File(tmp_path / "other.h5", "w") as f:  # another tool's HDF5: 0/1 (T, H, W), no attributes
        f["spikes"] = s.astype(np.uint8)
    np.testing.assert_array_equal(sensor.read_spikes(tmp_path / "other.h5"), s)
    with h5py.File(tmp_path / "nospikes.h5", "w") as f:
        f["frames"] = s.astype(np.uint8)
    with pytest.raises(sensor.SpikeFileError, match="no dataset 'spikes'"):
        sensor.read_spikes(tmp_path / "nospikes.h5")


def test_convert_cli_refuses_to_overwrite_and_reports_one_line(tmp_path, capsys):
    from render2spike.cli import main
    s = _pattern()
    files = _write_each_layout(tmp_path, s)
    out = tmp_path / "o.dat"
    assert main(["convert", str(files["rsir"]), str(out)]) == 0
    before = out.read_bytes()
    assert main(["convert", str(files["spikezoo"]), str(out)]) == 2
    err = capsys.readouterr().err
    assert "o.dat" in err and "--overwrite" in err and len(err.strip().splitlines()) == 1
    assert out.read_bytes() == before
    assert main(["convert", str(files["spikezoo"]), str(out), "--overwrite"]) == 0
    assert main(["convert", str(out), str(out), "--overwrite", "--height", "3", "--width", "8"]) == 2
    assert "is the INPUT" in capsys.readouterr().err
    # a 3 x 5 frame cannot be a .dat
    np.savez(tmp_path / "odd.npz", spk=np.zeros((2, 3, 5), np.uint8))
    assert main(["convert", str(tmp_path / "odd.npz"), str(tmp_path / "odd.dat")]) == 2
    assert "multiple of 8" in capsys.readouterr().err and not (tmp_path / "odd.dat").exists()
    trunc = tmp_path / "t.npz"
    trunc.write_bytes(files["spikezoo"].read_bytes()[:100])
    assert main(["convert", str(trunc), str(tmp_path / "t.h5")]) == 2
    assert "t.npz" in capsys.readouterr().err and not (tmp_path / "t.h5").exists()


def test_info_describes_third_party_layouts_and_h5(tmp_path):
    from render2spike.commands.info import describe
    s = _pattern()
    files = _write_each_layout(tmp_path, s)
    for layout in ("spikezoo", "rsir", "spikingsim"):
        d = describe(files[layout])
        assert d["kind"] == f"spike file, layout '{layout}'" and (d["intervals"], d["height"], d["width"]) == (T, H, W)
        assert d["mean_spike_rate_per_interval"] == pytest.approx(s.mean())
    d = describe(files["h5"])
    assert d["kind"] == "HDF5 spike file" and d["n_intervals"] == T
