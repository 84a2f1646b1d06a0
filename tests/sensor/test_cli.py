"""The sensor-stage CLI: simulate, calibrate, info; clear errors without tracebacks."""

import json

import numpy as np
import pytest

import sensor
from render2spike.cli import main


def test_help_lists_commands(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    out = capsys.readouterr().out
    for cmd in ("simulate", "calibrate", "info"):
        assert cmd in out


def test_simulate_from_npz_keyframes_matches_python_api(tmp_path, capsys):
    prof = sensor.SensorProfile.synthetic(8, 16, threshold_e=50, dark_rate=0.01, prnu_sigma=0.05, seed=2)
    prof_path = prof.save(tmp_path / "cam.npz")
    rate = np.random.default_rng(0).uniform(0, 20, (6, 8, 16)).astype(np.float32)
    t = np.linspace(0, 0.02, 6)
    np.savez(tmp_path / "rate.npz", rate_e=rate, t_s=t)
    rc = main(["simulate", str(tmp_path / "rate.npz"), "--out", str(tmp_path / "s.npz"), "--profile", str(prof_path),
               "--seed", "9", "--quiet", "--chunk", "2"])
    assert rc == 0
    spikes, meta = sensor.read_spikes_with_meta(tmp_path / "s.npz")
    np.testing.assert_array_equal(spikes, sensor.simulate(rate, prof, "elssim", seed=9, t_s=t))
    assert meta["seed"] == 9 and meta["model"] == "elssim" and meta["profile_id"] == prof.name


def test_simulate_frames_folder_to_dat_uses_profile_window(tmp_path, capsys):
    prof = sensor.SensorProfile.load("vidar-default")
    phi = np.full((3, 8, 16), 1.2e17, np.float32)  # e-/(s m^2)
    sensor.write_frames(tmp_path / "frames", phi, [0.0, 0.005, 0.01])
    rc = main(["simulate", str(tmp_path / "frames"), "--out", str(tmp_path / "s.dat"), "--model", "ideal"])
    assert rc == 0
    assert "centred 8x16 window" in capsys.readouterr().out
    s = sensor.read_dat(tmp_path / "s.dat", 8, 16)
    assert s.shape == (200, 8, 16)
    # ideal model (no PRNU, no dark): rate_e = 1.2e17 * (20e-6)^2 * 1.0 * 50e-6 = 2400 e-/interval, theta = 16,000 e-
    # -> a spike every ceil(16000 / 2400) = 7 intervals -> 200 // 7 = 28 spikes in every pixel
    assert (prof.threshold_e, prof.fill_factor) == (16000.0, 1.0)
    np.testing.assert_array_equal(s.sum(axis=0), 28)


def test_bad_input_is_one_clear_line(tmp_path, capsys):
    (tmp_path / "x.npz").write_bytes(b"garbage")
    rc = main(["simulate", str(tmp_path / "x.npz"), "--out", str(tmp_path / "o.npz")])
    err = capsys.readouterr().err
    assert rc == 2 and "x.npz" in err and "Traceback" not in err
    np.savez(tmp_path / "y.npz", other=np.zeros(3))
    assert main(["simulate", str(tmp_path / "y.npz"), "--out", str(tmp_path / "o.npz")]) == 2
    assert "rate_e" in capsys.readouterr().err
    assert not (tmp_path / "o.npz").exists()


def test_calibrate_cli_writes_profile_and_report(tmp_path, capsys):
    true = sensor.SensorProfile.synthetic(8, 16, threshold_e=50, dark_rate=0.005, prnu_sigma=0.05,
                                          hot_pixel_fraction=0.02, hot_mu=0.1, seed=1)
    base = true.replace(dark_rate=np.zeros((8, 16)), prnu_gain=np.ones((8, 16)),
                        hot_mask=np.zeros((8, 16), bool), hot_mu=np.zeros((8, 16)), hot_sigma=np.zeros((8, 16)))
    base_path = base.save(tmp_path / "base.npz")
    darks, flats = [], []
    for i in range(3):
        p = tmp_path / f"dark{i}.dat"
        sensor.write_dat(p, sensor.simulate(np.zeros((3000, 8, 16), np.float32), true, seed=i))
        darks.append(str(p))
    for i, lv in enumerate((2.0, 5.0)):
        p = tmp_path / f"flat{i}.dat"
        sensor.write_dat(p, sensor.simulate(np.full((3000, 8, 16), lv, np.float32), true, seed=10 + i))
        flats.append(str(p))
    rc = main(["calibrate", "--dark", *darks, "--flat", *flats, "--base", str(base_path),
               "--flat-lux", "1", "2.5", "--out", str(tmp_path / "mycam.npz")])
    assert rc == 0
    out = capsys.readouterr().out
    assert "threshold" in out and "sensitivity" in out and "reset" in out
    est = sensor.SensorProfile.load(tmp_path / "mycam.npz")
    assert est.hot_mask.sum() == true.hot_mask.sum()
    assert (tmp_path / "mycam_report.png").stat().st_size > 10_000
    rep = json.loads((tmp_path / "mycam_report.json").read_text())
    assert rep["n_dark_recordings"] == 3 and rep["hot_pixels"] == int(true.hot_mask.sum())
    for key in ("threshold_e", "threshold_se", "reset", "sensitivity_e_per_lux", "sensitivity_se", "hot_mu_sigma",
                "level_information_share", "level_reason", "prnu_se_median"):
        assert key in rep, key
    assert len(rep["hot_mu_sigma"]) == rep["hot_pixels"]
    assert main(["calibrate", "--dark", *darks, "--flat", *flats, "--base", str(base_path), "--flat-lux", "1",
                 "--out", str(tmp_path / "bad.npz")]) == 2
    assert "--flat-lux" in capsys.readouterr().err


def test_info_on_a_bad_npz_is_one_clear_line(tmp_path, capsys):
    (tmp_path / "bad.npz").write_bytes(b"not a zip archive")
    assert main(["info", str(tmp_path / "bad.npz")]) == 2
    err = capsys.readouterr().err
    assert "bad.npz" in err and "Traceback" not in err


def test_info_on_profile_and_spikes(tmp_path, capsys):
    assert main(["info", "vidar-default", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["threshold_e"] == 16000.0 and info["resolution"] == "250 x 400" and info["dark"] == "current"
    sensor.write_dat(tmp_path / "a.dat", np.ones((4, 2, 8), bool))
    assert main(["info", str(tmp_path / "a.dat"), "--height", "2", "--width", "8", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["intervals"] == 4


def test_console_script_entry_point_runs(cli):
    # in-process (``python -m render2spike`` itself runs in test_cli_blas.py)
    r = cli("simulate", "--help")
    assert r.returncode == 0 and "photoelectrons per interval" in r.stdout
