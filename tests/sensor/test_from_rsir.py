"""``calibrate --from-rsir``: RSIR maps (Nd, Nl, D_light) -> profile -> the same maps; bad maps refused."""

import numpy as np
import pytest

import sensor
from render2spike.cli import main
from sensor.calibration.rsir import (PLUS_ONE, REFERENCE_LUX, RSIR_KEYS, import_rsir, load_rsir_maps, rsir_maps,
                                     rsir_profile)

H, W = 20, 30


def synth_maps(seed=0, h=H, w=W):
    """RSIR-like maps: Nd log-normal around 7.66 lux with one 382-lux pixel, gain sd 5.6 %, q median ~1700."""
    rng = np.random.default_rng(seed)
    nd = 7.66 * np.exp(rng.normal(0.0, 0.5, (h, w)))
    nd[0, 1] = 382.0
    q = 1696.0 / rng.normal(1.0, 0.056, (h, w))  # RSIR's q = D_light (335 + Nd) [lux intervals]
    return {"Nd": nd.astype(np.float32), "Nl": (q[0, 0] / q).astype(np.float32),
            "D_light": (q / (REFERENCE_LUX + nd)).astype(np.float32)}


@pytest.fixture(scope="module")
def base():
    return sensor.SensorProfile.load("vidar-default")


@pytest.mark.parametrize("plus_one", PLUS_ONE)
def test_round_trip_through_the_saved_profile(tmp_path, base, plus_one):
    maps = synth_maps()
    np.savez(tmp_path / "maps.npz", **maps)
    imp = import_rsir(load_rsir_maps(tmp_path / "maps.npz"), base, plus_one=plus_one)
    prof = sensor.SensorProfile.load(rsir_profile(imp, base, "rsir-test").save(tmp_path / "p.npz"))
    back = rsir_maps(prof, base)
    for k in RSIR_KEYS:  # float32 maps in, float32 maps stored: equal to a few float32 ulps
        np.testing.assert_allclose(back[k], maps[k], rtol=2e-6, err_msg=k)
    assert np.median(prof.prnu_gain) == pytest.approx(1.0, abs=1e-3)
    np.testing.assert_allclose(imp.dark_current_e, imp.sensitivity_e_per_lux * maps["Nd"], rtol=1e-6)
    assert prof.reset == base.reset and prof.fill_factor == base.fill_factor
    np.testing.assert_array_equal(prof.qe.values, base.qe.values)
    if plus_one == "dead-time":  # the "+1" is a one-interval blind time; the gain is RSIR's Nl
        np.testing.assert_allclose(prof.refractory_fraction, 1.0, rtol=1e-6)
        np.testing.assert_allclose(prof.prnu_gain / prof.prnu_gain[0, 0], maps["Nl"], rtol=2e-6)
    else:
        np.testing.assert_array_equal(prof.refractory_s, base.refractory_s[:H, :W])
    for fieldname in ("threshold_e", "prnu_gain", "dark_current_e", "refractory_s", "hot_mask/hot_mu/hot_sigma", "qe"):
        assert fieldname in prof.provenance


def test_threshold_is_s_times_the_median_light_per_firing(base):
    maps = synth_maps(1)
    imp = import_rsir({k: v.astype(float) for k, v in maps.items()}, base)
    q = maps["D_light"].astype(float) * (REFERENCE_LUX + maps["Nd"])
    assert imp.threshold_e == pytest.approx(imp.sensitivity_e_per_lux * np.median(q), rel=1e-6)  # f = 1 - 3e-8 (float32 s)
    # s from the project's photometry: about 130 e-/(interval lux) for vidar-default's 20 um, fill factor 1.0
    assert 100 < imp.sensitivity_e_per_lux < 160


def test_cli_in_process(tmp_path, capsys):
    maps = synth_maps(2)
    np.savez(tmp_path / "maps.npz", **maps)
    out = tmp_path / "cam.npz"
    assert main(["calibrate", "--from-rsir", str(tmp_path / "maps.npz"), "--out", str(out)]) == 0
    assert "threshold" in capsys.readouterr().out
    prof = sensor.SensorProfile.load(out)
    assert prof.name == "rsir-maps" and prof.shape == (H, W)
    back = rsir_maps(prof)  # the profile's own photometry (copied from the base)
    for k in RSIR_KEYS:
        np.testing.assert_allclose(back[k], maps[k], rtol=2e-6, err_msg=k)
    # an existing output is refused without --overwrite
    assert main(["calibrate", "--from-rsir", str(tmp_path / "maps.npz"), "--out", str(out)]) == 2
    assert "exists" in capsys.readouterr().err


def _bad(maps, case):
    m = dict(maps)
    if case == "missing key":
        del m["Nl"]
        return m, "Nl", "missing"
    if case == "not 2-D":
        m["D_light"] = m["D_light"].reshape(-1)
        return m, "D_light", "2-D"
    if case == "shapes differ":
        m["Nl"] = m["Nl"][:, :-1]
        return m, "Nl", "share one shape"
    if case == "negative":
        m["Nd"] = m["Nd"].copy()
        m["Nd"][3, 4] = -1.0
        return m, "Nd", "out of range"
    if case == "NaN":
        m["D_light"] = m["D_light"].copy()
        m["D_light"][2, 2] = np.nan
        return m, "D_light", "not finite"
    if case == "Nl inconsistent":
        m["Nl"] = m["Nl"] * np.linspace(0.9, 1.1, m["Nl"].size, dtype=np.float32).reshape(m["Nl"].shape)
        return m, "Nl", "do not come from one RSIR calibration"
    raise AssertionError(case)


@pytest.mark.parametrize("case", ["missing key", "not 2-D", "shapes differ", "negative", "NaN", "Nl inconsistent"])
def test_bad_maps_one_clear_error_and_nothing_written(tmp_path, capsys, case):
    maps, key, words = _bad(synth_maps(3), case)
    np.savez(tmp_path / "maps.npz", **maps)
    out = tmp_path / "cam.npz"
    assert main(["calibrate", "--from-rsir", str(tmp_path / "maps.npz"), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "maps.npz" in err and f"field '{key}'" in err and words in err, err
    assert not out.exists() and list(tmp_path.iterdir()) == [tmp_path / "maps.npz"]


def test_not_an_npz_and_mixed_options_refused(tmp_path, capsys):
    (tmp_path / "maps.npz").write_bytes(b"not a zip")
    assert main(["calibrate", "--from-rsir", str(tmp_path / "maps.npz"), "--out", str(tmp_path / "o.npz")]) == 2
    assert "not a readable .npz" in capsys.readouterr().err
    np.save(tmp_path / "one.npy", np.zeros((2, 2)))
    assert main(["calibrate", "--from-rsir", str(tmp_path / "one.npy"), "--out", str(tmp_path / "o.npz")]) == 2
    assert "single array" in capsys.readouterr().err
    np.savez(tmp_path / "good.npz", **synth_maps())
    assert main(["calibrate", "--from-rsir", str(tmp_path / "good.npz"), "--dark", str(tmp_path / "good.npz"),
                 "--out", str(tmp_path / "o.npz")]) == 2
    assert "field '--dark'" in capsys.readouterr().err
    assert main(["calibrate", "--out", str(tmp_path / "o.npz")]) == 2
    assert "--from-rsir" in capsys.readouterr().err
    for flag in (["--dark-mode", "events"], ["--hot-threshold", "0.1"]):  # options of calibration from recordings
        assert main(["calibrate", "--from-rsir", str(tmp_path / "good.npz"), *flag, "--out",
                     str(tmp_path / "o.npz")]) == 2
        assert f"field '{flag[0]}'" in capsys.readouterr().err
    assert not (tmp_path / "o.npz").exists()


def test_maps_that_leave_no_light_per_firing_are_refused(tmp_path, capsys):
    """With the one-interval blind time a D_light of ~0 leaves theta / (g s) ~ 0: one error naming D_light."""
    maps = synth_maps(3)
    maps["D_light"] = np.full_like(maps["D_light"], 1e-12)
    maps["Nl"] = (1.0 / (maps["D_light"] * (335.0 + maps["Nd"]))).astype(np.float32)
    maps["Nl"] = maps["Nl"] / maps["Nl"][0, 0]
    np.savez(tmp_path / "maps.npz", **maps)
    out = tmp_path / "cam.npz"
    assert main(["calibrate", "--from-rsir", str(tmp_path / "maps.npz"), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "field 'D_light'" in err and "no light per firing" in err and not out.exists()


def _mean_isi(spikes):
    """Per-pixel mean read-out ISI from the first to the last spike (the read-out indices telescope) and count."""
    s = np.asarray(spikes)
    T = s.shape[0]
    n = s.sum(0)
    first, last = s.argmax(0), T - 1 - s[::-1].argmax(0)
    return (last - first) / (n - 1), n


def test_simulated_mean_isi_at_335_lux_is_one_plus_d_light(base):
    """The crossing ``elssim`` pixel of the imported profile fires at RSIR's rate at 335 lux.

    The profile holds the dark current as charge (``dark = current``): the simulator adds ``dark_current_e`` to
    the light. Then mean ISI = f + theta / (g (s 335 + d)) = 1 + D_light exactly in
    both ``--plus-one`` choices. Over 4000 intervals the per-pixel mean is precise to ~1e-4 (relative); the
    PRNU spread it must follow is 5.6 %.
    """
    maps = synth_maps(4)
    T = 4000
    for plus_one in PLUS_ONE:
        imp = import_rsir({k: v.astype(float) for k, v in maps.items()}, base, plus_one=plus_one)
        prof = rsir_profile(imp, base)
        assert prof.dark == "current"
        rate = np.full((H, W), imp.sensitivity_e_per_lux * REFERENCE_LUX, np.float32)
        spikes = sensor.simulate(np.stack([rate, rate]), prof, "elssim", seed=5,
                                 t_s=np.array([0.0, T * prof.interval_s]))
        mean, n = _mean_isi(spikes)
        target = 1.0 + maps["D_light"].astype(float)
        rel = mean / target - 1.0
        # sd of the estimate: the two ends' read-out phases (sqrt(1/6) interval over n - 1 ISIs) and shot noise,
        # sd(X) <= mean / sqrt(k) per firing (Gamma(k) photoelectrons), over n - 1 firings
        k = imp.threshold_e / imp.prnu_gain
        sd = np.sqrt(1.0 / 6.0 / (n - 1) ** 2 + target ** 2 / k / (n - 1)) / target
        z = rel / sd
        assert np.all(np.abs(z) < 5.0), (plus_one, np.abs(z).max())
        assert abs(z.mean()) * np.sqrt(z.size) < 4.0, (plus_one, z.mean())
