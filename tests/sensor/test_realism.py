"""Realism report: statistics on hand-built trains, the stationarity tests, a matched model, and the CLI."""

from pathlib import Path

import numpy as np
import pytest

import sensor
from sensor.analysis.realism import (DISTANCE_MEANING, parse_models, realism, spike_statistics, stationary_pixels,
                            write_report)

UHSR = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "real" / "uhsr.npz"


def _by(rows, stat, source="real"):
    return {r["bin"]: r for r in rows if r["statistic"] == stat and r["source"] == source}


def _train(times, T):
    x = np.zeros(T, bool)
    x[np.asarray(times)] = True
    return x


def test_statistics_of_hand_built_trains():
    # 20 pixels with ISIs alternating 2, 4 (mean 3): CV = 1/3, lag-1 = -(n-1)/n over the n ISIs of a pixel;
    # 20 pixels firing every 5 intervals: CV 0, Fano 0 in windows of 10 (two spikes in every window)
    T = 120
    alt = np.cumsum([1] + [2, 4] * 19)
    alt = alt[alt < T]
    s = np.zeros((T, 2, 20), bool)
    s[:, 0, :] = _train(alt, T)[:, None]
    s[:, 1, :] = _train(np.arange(0, T, 5), T)[:, None]
    rows = spike_statistics(s, isi_edges=(2.0, 4.0, 10.0), fano_windows=(10,), min_pixels=5)
    n = alt.size - 1
    cv, lag = _by(rows, "isi_cv"), _by(rows, "isi_lag1")
    # alternating pixels: T / spikes = 120 / 40 = 3 -> bin 2-4; periodic: 120 / 24 = 5 -> bin 4-10
    d = np.diff(alt) / np.diff(alt).mean() - 1
    assert cv["2-4"]["value"] == pytest.approx(np.sqrt((d ** 2).sum() / (n - 1)))
    assert lag["2-4"]["value"] == pytest.approx((d[:-1] * d[1:]).sum() / (d ** 2).sum())
    assert lag["2-4"]["value"] == pytest.approx(-(n - 1) / n, rel=0.05)
    assert cv["4-10"]["value"] == 0.0 and _by(rows, "fano_w10")["4-10"]["value"] == 0.0
    assert _by(rows, "isi_cv")["2-4"]["n_pixels"] == 20
    hist = _by(rows, "rate_hist")
    assert sum(r["value"] for r in hist.values()) == pytest.approx(1.0)
    out = _by(rows, "outliers")
    assert out["hot_fraction"]["value"] == 0 and out["dark_fraction"]["value"] == 0


def test_hot_and_dark_pixels_are_local_outliers():
    rng = np.random.default_rng(0)
    s = rng.random((400, 12, 16)) < 0.1  # ~40 spikes per pixel
    s[:, 3, 5] = True  # hot: 400 spikes
    s[:, 7, 9] = False  # dark: none
    out = _by(spike_statistics(s), "outliers")
    assert out["hot_fraction"]["value"] == pytest.approx(1 / 192)
    assert out["dark_fraction"]["value"] == pytest.approx(1 / 192)


def test_stationarity_tests_catch_a_rate_step_and_a_drift():
    T = 400
    s = np.zeros((T, 9, 30), bool)
    s[:, :, :10] = _train(np.arange(3, T, 10), T)[:, None, None]  # constant: every 10 intervals
    step = np.r_[np.arange(0, 200, 10), np.arange(200, T, 4)]  # rate x2.5 half way (neighbourhood count test)
    s[:, :, 10:20] = _train(step, T)[:, None, None]
    drift = np.cumsum(np.linspace(8, 16, 30)).astype(int)  # slowly lengthening ISIs (trend test)
    s[:, :, 20:] = _train(drift[drift < T], T)[:, None, None]
    keep, info = stationary_pixels(s, dilate=False)
    assert keep[:, :9].all() and not keep[:, 11:19].any() and not keep[:, 21:].any()
    assert info["fail_counts"] > 0 and info["fail_isi_trend"] > 0
    keep_d, _ = stationary_pixels(s, dilate=True)
    from scipy.ndimage import binary_dilation
    np.testing.assert_array_equal(keep_d, ~binary_dilation(~keep, np.ones((3, 3), bool)))  # neighbours left out
    assert keep_d[:, :7].all()


@pytest.mark.parametrize("reset", ["interval", "crossing"])
def test_the_report_finds_the_model_and_reset_that_made_a_recording(z, reset):
    # "real" = elssim with one reset on a light ramp. Each bin's |z| is |N(0,1)| (mean 0.80, sd 0.60) when the
    # model is right, and D averages >= 1 bin per statistic, so a matched model stays below 0.8 + z * 0.6 (the
    # single-bin bound, the loosest); the other reset must miss the lag-1 correlation by more than that
    other = {"interval": "crossing", "crossing": "interval"}[reset]
    prof = sensor.SensorProfile.synthetic(24, 40, threshold_e=400.0, dark_rate=0.002, prnu_sigma=0.03, seed=1)
    lam = np.broadcast_to(np.linspace(8.0, 120.0, 40, dtype=np.float32)[None, None, :], (600, 24, 40))
    rec = sensor.simulate(lam, prof.replace(reset=reset), "elssim", seed=11)
    res = realism(rec, prof, [f"elssim:{reset}", f"elssim:{other}", "ideal"], seed=5, curve_intervals=4000)
    bound = 0.8 + z * 0.6
    matched = res.distances[f"elssim:{reset}"]
    assert matched["D"] < bound, matched
    assert {"isi_cv", "isi_lag1", "fano", "rate_hist", "outliers"} <= set(matched["per_statistic"])
    assert res.distances[f"elssim:{other}"]["per_statistic"]["isi_lag1"] > bound, res.distances
    assert res.distances["ideal"]["D"] > bound
    assert res.distances["ideal"]["statistics_undefined"] == ["isi_lag1"]  # all ISIs of an ideal pixel are equal
    how = res.notes["models"]
    assert how["elssim:interval"]["light_estimate"].startswith("exact renewal")
    assert how["elssim:crossing"]["light_estimate"].startswith("rate-light curve")
    assert res.notes["models"][f"elssim:{reset}"]["reset"] == reset


def test_parse_models_lists_valid_choices():
    assert [m.label for m in parse_models("elssim:crossing, isi")] == ["elssim:crossing", "isi"]
    with pytest.raises(sensor.UnknownMethodError, match="ideal"):
        parse_models("nonsense")
    with pytest.raises(sensor.UnknownMethodError, match="crossing"):
        parse_models("elssim:sometimes")


def test_report_files(tmp_path):
    rng = np.random.default_rng(3)
    rec = rng.random((160, 16, 24)) < 0.08
    prof = sensor.SensorProfile.synthetic(16, 24, threshold_e=200.0, dark_rate=0.001, seed=2)
    res = realism(rec, prof, ["isi"], seed=0, curve_intervals=2000)
    paths = write_report(res, tmp_path / "r", recording="rand.npz")
    import csv
    import json
    rows = list(csv.DictReader(open(paths["csv"])))
    assert {r["source"] for r in rows} == {"real", "isi"}
    assert {"isi_cv", "isi_lag1", "rate_hist", "outliers"} <= {r["statistic"] for r in rows}
    summary = json.loads(paths["json"].read_text())
    assert summary["distance_meaning"] == DISTANCE_MEANING and "isi" in summary["distances"]
    assert "Motion" in paths["md"].read_text() and paths["png"].stat().st_size > 10_000


def test_realism_cli_on_a_small_synthetic_recording(tmp_path, capsys):
    from render2spike.cli import main
    prof = sensor.SensorProfile.synthetic(20, 24, threshold_e=300.0, dark_rate=0.002, seed=4)
    prof.save(tmp_path / "prof.npz")
    lam = np.broadcast_to(np.linspace(5.0, 60.0, 24, dtype=np.float32)[None, None, :], (300, 20, 24))
    rec = sensor.simulate(lam, prof, "elssim", seed=2)
    np.savez(tmp_path / "rec.npz", spk=rec.astype(np.uint8))  # Spike-Zoo layout
    out = tmp_path / "rep"
    args = ["realism", str(tmp_path / "rec.npz"), "--out", str(out), "--profile", str(tmp_path / "prof.npz"),
            "--models", "elssim:interval,isi", "--seed", "1"]
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "stationarity:" in text and "D =" in text
    assert {p.name for p in out.iterdir()} == {"realism.csv", "realism.png", "realism.json", "realism.md"}
    assert main(args) == 2 and "--overwrite" in capsys.readouterr().err
    assert main(args[:-4] + ["--models", "elssim:whenever", "--overwrite"]) == 2
    assert "valid choices" in capsys.readouterr().err
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"PK\x03\x04")
    assert main(["realism", str(bad), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "bad.npz" in err and len(err.strip().splitlines()) == 1 and not (tmp_path / "x").exists()


@pytest.mark.skipif(not UHSR.exists(), reason="real recording ../shared/data/real/uhsr.npz not present")
def test_realism_cli_runs_on_the_real_recording(tmp_path, capsys):
    from render2spike.cli import main
    out = tmp_path / "uhsr"
    assert main(["realism", str(UHSR), "--out", str(out), "--crop", "64,80", "--models", "elssim:interval,isi"]) == 0
    text = capsys.readouterr().out
    assert "layout 'spikezoo'" in text and "200 intervals of 250 x 250" in text
    import json
    d = json.loads((out / "realism.json").read_text())["distances"]
    assert set(d) == {"elssim:interval", "isi"} and all(np.isfinite(v["D"]) for v in d.values())


def test_streamed_warmup_equals_the_tail_of_one_long_simulation():
    from sensor.analysis.light import simulate_after_warmup as _simulate_after_warmup
    p = sensor.SensorProfile.synthetic(8, 16, threshold_e=100.0, dark_rate=0.01, seed=0)
    lam = np.linspace(1, 50, 128, dtype=np.float32).reshape(8, 16)
    for T, warm, chunk in ((300, 1000, 97), (5, 3, 2)):
        whole = sensor.simulate(np.broadcast_to(lam[None], (warm + T, 8, 16)), p, "elssim", seed=3)
        np.testing.assert_array_equal(_simulate_after_warmup(lam, T, warm, p, "elssim", 3, chunk=chunk), whole[warm:])
