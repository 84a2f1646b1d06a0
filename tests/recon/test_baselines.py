"""The strong classic baseline (tfp-dt-denoised): smoothing, the width table, tuning, the evaluate method."""

import json

import numpy as np
import pytest

from recon.baselines import (SIGMA_GRID, gaussian_denoise, load_sigma_table, mean_count, sigma_for_count,
                             smooth_rate, tfp_dt_denoised, tune_sigmas)
from recon.classic import tfp_deadtime
from recon.datasets import Sample, uniform_profile
from recon.evaluate import METHOD_NAMES, apply_method, parse_methods
from sensor import InputError, SensorProfile, UnknownMethodError, simulate


def test_shipped_sigma_table_is_valid_and_monotone_in_light():
    t = load_sigma_table()
    counts, sigmas = np.asarray(t["counts"]), np.asarray(t["sigmas"])
    assert np.all(np.diff(counts) > 0) and set(sigmas) <= set(SIGMA_GRID)
    assert t["split"] == "train"  # chosen on training items only
    # dim scenes get a wider filter than bright ones (below ~1 lux nothing helps: the widths there are noise)
    assert max(sigmas[: len(sigmas) // 2]) > sigma_for_count(counts[-1])


def test_sigma_for_count_interpolates_in_log_count_and_clamps():
    table = {"counts": [1.0, 100.0], "sigmas": [4.0, 0.0]}
    assert sigma_for_count(10.0, table) == pytest.approx(2.0)  # halfway in log count
    assert sigma_for_count(0.01, table) == 4.0 and sigma_for_count(1e4, table) == 0.0


def test_sigma_table_errors(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        load_sigma_table(tmp_path / "none.json")
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"format": "x"}))
    with pytest.raises(InputError, match="counts"):
        load_sigma_table(bad)


def test_smooth_rate_keeps_hot_pixels_out_and_each_pixels_dark_level():
    prof = SensorProfile.synthetic(16, 16, threshold_e=100.0, dark_rate=0.01, dark_rate_spread=0.5,
                                   hot_pixel_fraction=0.02, seed=3)
    from sensor.models.effects import dark_event_probability
    p = dark_event_probability(prof.dark_rate)
    rate = p + 0.05  # uniform excess over each pixel's own dark level
    rate = np.where(prof.hot_mask, 0.9, rate)  # hot pixels fire far more
    out = smooth_rate(rate, prof, 2.0)
    # the excess stays exactly uniform (hot pixels left out) and each pixel keeps its own dark level
    np.testing.assert_allclose(out - p, 0.05, atol=1e-5)
    np.testing.assert_array_equal(smooth_rate(rate, prof, 0.0), rate)
    np.testing.assert_array_equal(gaussian_denoise(rate, 0), rate.astype(np.float32))


def _flat_sample(lam, seed, size=32, T=320):
    prof = uniform_profile(size, size)
    rate = np.full((T + 64, size, size), lam, np.float32)
    # random spike phases, as a camera that has been running (recon.datasets' start='phase'): the warm-up brings
    # each pixel to a uniform random charge; from zero charge the nearly periodic pixels would all fire in step
    u = np.random.default_rng(100 + seed).uniform(0.0, 1.0, (size, size))
    rate[:64] = (u * prof.threshold_e / 64).astype(np.float32)
    spikes = simulate(rate, prof, "elssim", seed=seed)[64:]
    target = np.full((1, size, size), lam / prof.threshold_e, np.float32)
    return Sample(windows=np.zeros((10, size, size), np.float32), target=target, maps=np.zeros((2, size, size)),
                  spikes=spikes, center=T // 2, profile=prof, meta={"window": T // 10})


def test_denoised_baseline_beats_tfp_dt_on_a_noisy_flat_scene_and_tuning_picks_a_wide_filter():
    """Few spikes per pixel on a flat scene: any smoothing lowers the error; the tuner must not pick sigma 0."""
    lam = 0.02 * uniform_profile(1, 1).threshold_e  # 0.02 threshold per interval: ~6 light spikes per pixel in 320
    samples = [_flat_sample(lam, seed) for seed in (1, 2)]
    best, scores = tune_sigmas(samples, (0.0, 1.0, 4.0))
    assert best == 4.0 and scores[4.0] > scores[1.0] > scores[0.0]
    s = samples[0]
    truth = s.target[0] * s.profile.threshold_e
    err_dt = np.mean((tfp_deadtime(s.spikes, s.profile, 320, s.center) - truth) ** 2)
    err_dn = np.mean((tfp_dt_denoised(s.spikes, s.profile, 320, s.center, sigma=4.0) - truth) ** 2)
    assert err_dn < 0.2 * err_dt
    assert mean_count(s.spikes, 320, s.center) == pytest.approx(s.spikes[s.center - 160:s.center + 160].mean() * 320)


def test_evaluate_method_names_and_application():
    ms = parse_methods("tfp-dt-denoised,tfp-dt-denoised:1.5")
    assert [m.kind for m in ms] == ["tfp-dt-denoised"] * 2 and ms[1].arg == "1.5"
    assert "tfp-dt-denoised" in METHOD_NAMES and "rsir:CKPT" in METHOD_NAMES
    with pytest.raises(InputError, match="width"):
        parse_methods("tfp-dt-denoised:wide")
    with pytest.raises(UnknownMethodError, match="tfp-dt-denoised"):
        parse_methods("nlm")
    s = _flat_sample(40.0, 5, size=16)
    fixed = apply_method(ms[1], s)
    np.testing.assert_allclose(fixed, tfp_dt_denoised(s.spikes, s.profile, 320, s.center, sigma=1.5)
                               / s.profile.threshold_e)
    assert apply_method(ms[0], s).shape == (16, 16)
