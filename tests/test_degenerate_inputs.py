"""Degenerate recordings, out-of-range options, a full disk and a read-only folder, through the CLI.

Each refusal: exit code 2, one line without a traceback naming the file and/or the option, and nothing
created, changed or removed under the test folder (:func:`tests.test_bad_inputs.expect_refused`).
"""

import errno
import json
import os

import numpy as np
import pytest

import sensor
from tests.test_bad_inputs import expect_refused, snapshot

H, W = 8, 16


@pytest.fixture(scope="module")
def cal(tmp_path_factory):
    """Dark and flat .dat recordings of a small synthetic sensor (interval reset), its base profile, and
    degenerate recordings: all-zero, all-one, mostly saturated, empty."""
    d = tmp_path_factory.mktemp("cal")
    true = sensor.SensorProfile.synthetic(H, W, threshold_e=50, dark_rate=0.005, prnu_sigma=0.05,
                                          hot_pixel_fraction=0.02, hot_mu=0.1, seed=1)
    base = true.replace(dark_rate=np.zeros((H, W)), prnu_gain=np.ones((H, W)), hot_mask=np.zeros((H, W), bool),
                        hot_mu=np.zeros((H, W)), hot_sigma=np.zeros((H, W)))
    base.save(d / "base.npz")
    for i in range(2):
        sensor.write_dat(d / f"dark{i}.dat", sensor.simulate(np.zeros((2000, H, W), np.float32), true, seed=i))
    for i, lv in enumerate((2.0, 5.0)):
        sensor.write_dat(d / f"flat{i}.dat", sensor.simulate(np.full((2000, H, W), lv, np.float32), true,
                                                             seed=10 + i))
    sensor.write_dat(d / "zeros.dat", np.zeros((2000, H, W), bool))
    sensor.write_dat(d / "ones.dat", np.ones((2000, H, W), bool))
    sensor.write_dat(d / "sat.dat", np.random.default_rng(3).random((2000, H, W)) < 0.95)
    (d / "empty.dat").write_bytes(b"")
    (d / "flatcopy.dat").write_bytes((d / "flat0.dat").read_bytes())
    return d


def calibrate_args(d, dark=("dark0.dat", "dark1.dat"), flat=("flat0.dat", "flat1.dat"), extra=(), out="cam.npz"):
    return ["calibrate", "--base", d / "base.npz", "--height", H, "--width", W, "--dark", *[d / f for f in dark],
            "--flat", *[d / f for f in flat], *extra, "--out", d / out]


# ------------------------------------------------------------------------------------------ calibrate
@pytest.mark.parametrize("lux, bad", [(("-1", "2"), "-1"), (("1", "nan"), "nan"), (("0", "2"), "0"),
                                      (("1", "inf"), "inf")])
def test_calibrate_refuses_a_flat_lux_that_is_not_a_positive_number(cal, capsys, lux, bad):
    err = expect_refused(calibrate_args(cal, extra=["--flat-lux", *lux]), cal, capsys, "--flat-lux", bad)
    assert "above 0" in err


@pytest.mark.parametrize("dark, flat, names", [
    (("dark0.dat",), ("flat0.dat", "flat0.dat"), ("flat0.dat", "--flat", "given twice")),
    (("dark0.dat",), ("flat0.dat", "flatcopy.dat"), ("flatcopy.dat", "--flat", "same spikes", "flat0.dat")),
    (("dark0.dat", "dark0.dat"), ("flat0.dat", "flat1.dat"), ("dark0.dat", "--dark", "given twice")),
    (("flat0.dat",), ("flat0.dat", "flat1.dat"), ("flat0.dat", "given twice")),
])
def test_calibrate_refuses_a_recording_given_twice(cal, capsys, dark, flat, names):
    expect_refused(calibrate_args(cal, dark=dark, flat=flat), cal, capsys, *names)


@pytest.mark.parametrize("dark, flat, names", [
    (("ones.dat",), ("flat0.dat", "flat1.dat"), ("ones.dat", "--dark", "saturated")),
    (("zeros.dat",), ("flat0.dat", "flat1.dat"), ("zeros.dat", "--dark", "no spike")),
    (("dark0.dat",), ("flat0.dat", "ones.dat"), ("ones.dat", "--flat", "saturated")),
    (("dark0.dat",), ("flat0.dat", "zeros.dat"), ("zeros.dat", "--flat", "no spike")),
    (("empty.dat",), ("flat0.dat", "flat1.dat"), ("empty.dat", "dark")),
])
def test_calibrate_refuses_degenerate_recordings_naming_the_right_option(cal, capsys, dark, flat, names):
    err = expect_refused(calibrate_args(cal, dark=dark, flat=flat), cal, capsys, *names)
    if "--dark" in names:
        assert "--flat" not in err  # the dark recording is at fault, not the flats


def test_calibrate_warns_about_a_saturated_flat_and_keeps_it_out_of_the_reset_decision(cal, cli):
    r = cli(*calibrate_args(cal, flat=("flat0.dat", "flat1.dat", "sat.dat"), out="sat.npz"))
    assert r.returncode == 0, r.stderr
    assert "render2spike: warning: flat recording 2" in r.stderr and "sat.dat" in r.stderr and "saturated" in r.stderr
    rep = json.loads((cal / "sat_report.json").read_text())
    assert len(rep["warnings"]) == 1 and "sat.dat" in rep["warnings"][0]
    assert rep["level_used"][2] is False and rep["reset_levels"][2]["z"] is None  # no say in the reset
    ref = cli(*calibrate_args(cal, out="ref.npz"))
    assert ref.returncode == 0 and "warning" not in ref.stderr
    rep0 = json.loads((cal / "ref_report.json").read_text())
    assert rep["reset"] == rep0["reset"] and rep["reset_z"] == rep0["reset_z"]


def test_calibrate_api_refuses_identical_arrays_as_two_levels():
    from sensor.calibration.estimate import calibrate
    prof = sensor.SensorProfile.synthetic(4, 8, threshold_e=10)
    d = np.zeros((50, 4, 8), bool)
    d[::7, 0, 0] = True
    f = np.random.default_rng(0).random((50, 4, 8)) < 0.2
    with pytest.raises(sensor.CalibrationError, match="same spikes as flat recording 0"):
        calibrate([d], [f, f.copy()], base=prof)


def test_calibrate_refuses_a_zero_height(cal, capsys):
    args = calibrate_args(cal)
    args[args.index("--height") + 1] = 0
    expect_refused(args, cal, capsys, "--height", "positive")


# ------------------------------------------------------------------------------------------ realism
@pytest.mark.parametrize("name, what", [("zeros.dat", "no spike"), ("ones.dat", "every pixel in every interval"),
                                        ("empty.dat", "0 intervals")])
def test_realism_refuses_a_recording_with_nothing_to_compare(cal, capsys, name, what):
    err = expect_refused(["realism", cal / name, "--height", H, "--width", W, "--profile", cal / "base.npz",
                          "--out", cal / "rep", "--quiet"], cal, capsys, name, what)
    assert "D =" not in err


# ------------------------------------------------------------------------------------------ .dat sizes
@pytest.mark.parametrize("flag, value", [("--height", "0"), ("--width", "0"), ("--height", "-8")])
def test_dat_frame_size_must_be_positive(cal, capsys, flag, value):
    other = "--width" if flag == "--height" else "--height"
    expect_refused(["convert", cal / "dark0.dat", cal / "x.npz", flag, value, other, 16], cal, capsys, flag,
                   "dark0.dat")
    expect_refused(["info", cal / "dark0.dat", flag, value], cal, capsys, flag)


def test_library_refuses_a_zero_frame_height(cal):
    with pytest.raises(sensor.SpikeFileError, match="height"):
        sensor.read_spikes(cal / "dark0.dat", height=0, width=16)
    from sensor.io.dat import dat_frame_count
    with pytest.raises(sensor.SpikeFileError, match="width"):
        dat_frame_count(cal / "dark0.dat", 8, 0)


def test_an_empty_recording_converts_and_reconstruct_refuses_it(cal, tmp_path, cli, capsys):
    r = cli("convert", cal / "empty.dat", tmp_path / "e.npz", "--height", H, "--width", W)
    assert r.returncode == 0 and "0 intervals" in r.stdout  # a faithful copy of nothing, no "cannot reshape"
    assert sensor.read_spikes(tmp_path / "e.npz").shape == (0, H, W)
    expect_refused(["reconstruct", cal / "empty.dat", "--height", H, "--width", W, "--out", cal / "rec"], cal, capsys,
                   "empty.dat", "empty recording")


# ------------------------------------------------------------------------------------------ full disk, read-only
def _enospc(*a, **k):
    raise OSError(errno.ENOSPC, "No space left on device")


@pytest.mark.parametrize("suffix", [".dat", ".npz", ".h5"])
def test_convert_on_a_full_disk_is_one_line_naming_the_file(cal, tmp_path, cli, monkeypatch, suffix):
    out = tmp_path / f"out{suffix}"
    src = cal / "dark0.dat"
    monkeypatch.setattr(os, "write", _enospc)  # every atomic write goes through os.write
    r = cli("convert", src, out, "--height", H, "--width", W)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert "disk full" in lines[0] and str(out) in lines[0]
    assert list(tmp_path.iterdir()) == []  # no partial file, no temp file


def test_a_read_only_folder_is_one_line_naming_the_file(cal, tmp_path, cli, monkeypatch):
    """Permission refused (EACCES) and a read-only file system (EROFS): the file named, not its temp name."""
    import sensor.io.fileio as fileio
    out = tmp_path / "x.dat"
    for code, words in ((errno.EACCES, "permission denied"), (errno.EROFS, "read-only file system")):
        real_open = os.open

        def refuse(path, flags, *a, _code=code, **k):
            if str(path).startswith(str(tmp_path)) and flags & os.O_CREAT:
                raise OSError(_code, os.strerror(_code), str(path))
            return real_open(path, flags, *a, **k)
        monkeypatch.setattr(fileio.os, "open", refuse)
        r = cli("convert", cal / "dark0.dat", out, "--height", H, "--width", W)
        monkeypatch.undo()
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1, r.stderr
        assert words in lines[0] and f"{out}:" in lines[0] and ".part-" not in lines[0], lines[0]
        assert list(tmp_path.iterdir()) == []


def test_final_name_maps_temp_names_back():
    from sensor.io.fileio import final_name
    assert final_name("/a/.x.part-12-0.dat").as_posix() == "/a/x.dat"
    assert final_name("/a/.cam.part-9-ab_3q8z1k.npz").as_posix() == "/a/cam.npz"
    assert final_name("/a/.noext.part-9-3").as_posix() == "/a/noext"
    assert final_name("/a/plain.dat").as_posix() == "/a/plain.dat"


# ------------------------------------------------------------------------------------------ numeric options
@pytest.mark.parametrize("args, names", [
    (["reconstruct", "{d}/dark0.dat", "--height", "8", "--width", "16", "--window", "0"], ["--window"]),
    (["reconstruct", "{d}/dark0.dat", "--height", "8", "--width", "16", "--every", "0"], ["--every"]),
    (["reconstruct", "{d}/dark0.dat", "--height", "8", "--width", "16", "--every", "-5"], ["--every", "-5"]),
    (["reconstruct", "{d}/dark0.dat", "--height", "8", "--width", "16", "--method", "tfp-dt-denoised",
      "--sigma", "-1"], ["--sigma"]),
    (["train", "--data", "rendered:{d}/nowhere", "--steps", "-1"], ["--steps"]),
    (["train", "--data", "rendered:{d}/nowhere", "--lr", "nan"], ["--lr"]),
    (["train", "--data", "rendered:{d}/nowhere", "--batch-size", "0"], ["--batch-size"]),
    (["train", "--data", "rendered:{d}/nowhere:window=0"], ["--data", "window"]),
    (["train", "--data", "davis:{d}/nowhere:lux=50-5"], ["--data", "lux", "50-5"]),
    (["train", "--data", "davis:{d}/nowhere:lux=-3"], ["--data", "lux"]),
    (["evaluate", "--data", "davis:{d}/nowhere:windows=0"], ["--data", "windows"]),
    (["evaluate", "--data", "davis:{d}/nowhere:intervals=5"], ["--data", "intervals", "320"]),
    (["evaluate", "--data", "davis:{d}/nowhere", "--examples", "-1"], ["--examples"]),
    (["realism", "{d}/dark0.dat", "--height", "8", "--width", "16", "--segments", "0"], ["--segments"]),
    (["calibrate", "--dark", "{d}/dark0.dat", "--flat", "{d}/flat0.dat", "{d}/flat1.dat", "--base", "{d}/base.npz",
      "--height", "8", "--width", "16", "--hot-threshold", "nan"], ["--hot-threshold"]),
])
def test_out_of_range_options_are_refused_before_anything_is_written(cal, capsys, args, names):
    args = [a.format(d=cal) for a in args] + ["--out", str(cal / "out")]
    expect_refused(args, cal, capsys, *names)


@pytest.mark.parametrize("value", ["-1", "0", "nan"])
def test_convert_refuses_an_interval_that_is_not_a_positive_time(cal, capsys, value):
    expect_refused(["convert", cal / "dark0.dat", cal / "x.npz", "--height", H, "--width", W, "--interval-s", value],
                   cal, capsys, "--interval-s")


def test_run_refuses_a_clip_shorter_than_one_interval(tmp_path, capsys):
    expect_refused(["run", "rotating_disk", "--out", tmp_path / "o", "--duration", "1e-5"], tmp_path, capsys,
                   "duration_s", "shorter than one read-out interval")
    assert snapshot(tmp_path) == {}


def test_calibrate_with_pixels_dark_at_a_flat_level_finishes():
    """A dim, short flat where some pixels never fire carries no information there: it is weighted 0, and the
    fit does not try to sum ~1 / x terms of their (zero) light."""
    import time

    from sensor.calibration.estimate import calibrate
    prof = sensor.SensorProfile.synthetic(4, 8, threshold_e=10)
    rng = np.random.default_rng(1)
    d = rng.random((400, 4, 8)) < 0.005
    d[0] = True  # every pixel has a dark event
    flats = []
    for p in (0.05, 0.1):
        f = rng.random((400, 4, 8)) < p
        f[:, :2] = False  # two rows never fire
        flats.append(f)
    t0 = time.perf_counter()
    _, rep = calibrate([d], flats, base=prof, reset="interval")
    assert time.perf_counter() - t0 < 60
    assert np.isfinite(rep.numbers["prnu_std"])
