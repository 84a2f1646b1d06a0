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


def test_tables_without_windows_load_as_window_320(tmp_path):
    """The version-1 table format (no windows) still loads: window 320 everywhere, widths interpolated as before."""
    from recon.baselines import COUNT_WINDOW, DEFAULT_WINDOW, window_sigma_for_count
    shipped = load_sigma_table()
    assert len(shipped["windows"]) == len(shipped["counts"]) and shipped["count_window"] == COUNT_WINDOW
    old = tmp_path / "v1.json"
    old.write_text(json.dumps({"format": "render2spike-denoise-sigma", "version": 1, "counts": [1.0, 100.0],
                               "sigmas": [4.0, 0.0]}))
    t = load_sigma_table(old)
    assert t["windows"] == [DEFAULT_WINDOW] * 2 == [320, 320] and t["count_window"] == 320
    assert window_sigma_for_count(10.0, t) == (320, pytest.approx(2.0))
    bad = tmp_path / "bad_windows.json"
    bad.write_text(json.dumps({"format": "render2spike-denoise-sigma", "counts": [1.0, 2.0], "sigmas": [1.0, 0.0],
                               "windows": [320]}))
    with pytest.raises(InputError, match="windows"):
        load_sigma_table(bad)


def test_window_sigma_for_count_nearest_window_and_width_within_it():
    from recon.baselines import window_sigma_for_count
    t = {"counts": [1.0, 10.0, 100.0, 1000.0], "windows": [320, 320, 32, 16], "sigmas": [4.0, 2.0, 1.0, 0.0]}
    assert window_sigma_for_count(0.1, t) == (320, 4.0)
    assert window_sigma_for_count(np.sqrt(10.0), t) == (320, pytest.approx(3.0))  # between the two 320 levels
    assert window_sigma_for_count(20.0, t) == (320, 2.0)  # nearer 10 than 100 in log count; clamped within 320
    assert window_sigma_for_count(60.0, t) == (32, 1.0)
    assert window_sigma_for_count(1e5, t) == (16, 0.0)


def test_tuned_window_is_used_and_capped_and_the_fixed_form_keeps_the_full_window():
    from recon.baselines import light_count
    s = _flat_sample(40.0, 7, size=16)
    key = light_count(s.spikes, 320, s.center)
    assert key == pytest.approx(mean_count(s.spikes, 320, s.center))  # over 320 intervals: the old key
    t = {"counts": [key / 10, key * 10], "windows": [64, 64], "sigmas": [1.0, 1.0], "count_window": 320}
    np.testing.assert_array_equal(tfp_dt_denoised(s.spikes, s.profile, 320, s.center, table=t),
                                  tfp_dt_denoised(s.spikes, s.profile, 64, s.center, sigma=1.0))
    # offered fewer intervals than the table's window: capped (and the key measured over what is offered)
    np.testing.assert_array_equal(tfp_dt_denoised(s.spikes, s.profile, 40, s.center, table=t),
                                  tfp_dt_denoised(s.spikes, s.profile, 40, s.center, sigma=1.0))
    # evaluate's tfp-dt-denoised:S: the fixed width over the whole M = 320 window
    m = parse_methods("tfp-dt-denoised:1")[0]
    np.testing.assert_allclose(apply_method(m, s) * s.profile.threshold_e,
                               tfp_dt_denoised(s.spikes, s.profile, 320, s.center, sigma=1.0), rtol=1e-6)


def _flash_sample(seed, size=16, T=320, level=0.3):
    """Bright for the 16 intervals around the centre, dim before and after: only a short window sees the centre."""
    prof = uniform_profile(size, size)
    th = prof.threshold_e
    rate = np.full((T + 64, size, size), 0.2 * level * th, np.float32)
    c = 64 + T // 2
    rate[c - 8:c + 8] = level * th
    u = np.random.default_rng(200 + seed).uniform(0.0, 1.0, (size, size))
    rate[:64] = (u * th / 64).astype(np.float32)
    spikes = simulate(rate, prof, "elssim", seed=seed)[64:]
    return Sample(windows=np.zeros((10, size, size), np.float32),
                  target=np.full((1, size, size), level, np.float32), maps=np.zeros((2, size, size)),
                  spikes=spikes, center=T // 2, profile=prof, meta={"window": T // 10})


def test_tune_window_sigma_picks_short_windows_for_change_and_long_ones_for_dim_still_scenes():
    from recon.baselines import tune_window_sigma
    (w, _), scores = tune_window_sigma([_flash_sample(s) for s in (1, 2)], (16, 64, 320), (0.0, 1.0))
    assert w == 16 and scores[(16, 0.0)] > scores[(320, 0.0)] + 6.0  # the long windows average the dim part in
    lam = 0.02 * uniform_profile(1, 1).threshold_e
    (w, sig), _ = tune_window_sigma([_flat_sample(lam, s) for s in (1, 2)], (16, 64, 320), (0.0, 4.0))
    assert (w, sig) == (320, 4.0)  # a dim still scene: the longest window and the wide filter
    # windows longer than the samples' span are not tried
    (w, _), scores = tune_window_sigma([_flat_sample(lam, 1, T=200)], (16, 640), (0.0,))
    assert {k[0] for k in scores} == {16}


def test_tune_command_writes_a_window_table(tmp_path):
    from recon.baselines import load_sigma_table as load
    from recon.baselines import main
    from recon.synth import make_davis_like
    root = make_davis_like(tmp_path / "davis", ["tr-a", "te-a"], n_frames=3, size=(8, 8), seed=4)
    split = tmp_path / "split.json"
    split.write_text(json.dumps({"train": ["tr-a"], "test": ["te-a"]}))
    out = tmp_path / "table.json"
    spec = f"davis:{root}:split_file={split}:res=8x8:warmup=8:frame_stride=2"
    assert main(["tune", "--data", spec, "--lux", "5,500", "--items", "1", "--windows", "32,320",
                 "--out", str(out)]) == 0
    t = load(out)
    assert t["version"] == 2 and t["split"] == "train" and set(t["windows"]) <= {32, 320}
    assert t["counts"] == sorted(t["counts"]) and len(t["levels"]) == 2
    assert set(t["levels"][0]["psnr_by_window_sigma"]) == {"32", "320"}


def _moving_sample(seed, size=32, T=320, step_intervals=16):
    """Bright vertical bars drifting one pixel every ``step_intervals`` intervals on a dim background."""
    prof = uniform_profile(size, size)
    th = prof.threshold_e
    t = np.arange(T + 64)[:, None, None]
    x = np.arange(size)[None, None, :]
    bars = ((x + t // step_intervals) % 16) < 6
    rate = np.where(bars, 0.3 * th, 0.05 * th) * np.ones((1, size, 1))
    rate = rate.astype(np.float32)
    u = np.random.default_rng(300 + seed).uniform(0.0, 1.0, (size, size))
    rate[:64] = (u * th / 64).astype(np.float32)
    spikes = simulate(rate, prof, "elssim", seed=seed)[64:]
    target = (rate[64 + T // 2] / th)[None]
    return Sample(windows=np.zeros((10, size, size), np.float32), target=target, maps=np.zeros((2, size, size)),
                  spikes=spikes, center=T // 2, profile=prof, meta={"window": T // 10})


def test_motion_score_separates_still_from_moving_scenes_and_picks_the_motion_group():
    from recon.baselines import light_count, motion_group, motion_score, window_sigma_for_item
    lam = 0.2 * uniform_profile(1, 1).threshold_e
    still, moving = _flat_sample(lam, 3), _moving_sample(3)
    m_still, m_moving = (motion_score(s.spikes, 320, s.center) for s in (still, moving))
    # still: z^2 of a nested Bernoulli difference averages 1 at most (integrate-and-fire spikes are more regular)
    assert m_still < 1.0 and m_moving > 2.0 and m_moving > 10 * m_still
    assert motion_score(moving.spikes, 320, moving.center, sigma=0.0) > 2.0  # per pixel too, at this contrast
    assert motion_score(still.spikes, 32, still.center) == 0.0  # no window shorter than the offered one
    keys = [light_count(s.spikes, 320, s.center) for s in (still, moving)]
    lo, hi = min(keys) / 10, max(keys) * 10
    t = {"counts": [lo, hi], "windows": [128, 128], "sigmas": [0.5, 0.5], "count_window": 320,
         "groups": [{"counts": [lo, hi], "windows": [320, 320], "sigmas": [1.0, 1.0], "motions": [0.5, 0.5]},
                    {"counts": [lo, hi], "windows": [32, 32], "sigmas": [0.0, 0.0], "motions": [30.0, 30.0]}]}
    assert motion_group(keys[0], m_still, t) is t["groups"][0] and motion_group(keys[1], m_moving, t) is t["groups"][1]
    alike = {**t, "groups": [t["groups"][0], {**t["groups"][1], "motions": [0.6, 0.6]}]}
    assert motion_group(keys[1], m_moving, alike) is alike["groups"][0]  # scores alike: the first group
    assert window_sigma_for_item(still.spikes, 320, still.center, t) == (320, 1.0)
    assert window_sigma_for_item(moving.spikes, 320, moving.center, t) == (32, 0.0)
    assert window_sigma_for_item(moving.spikes, 320, moving.center, t, motion=False) == (128, 0.5)  # pooled pair
    np.testing.assert_array_equal(tfp_dt_denoised(moving.spikes, moving.profile, 320, moving.center, table=t),
                                  tfp_dt_denoised(moving.spikes, moving.profile, 32, moving.center, sigma=0.0))
    # and the short window is the better choice there: the moving bars blur out over 320 intervals
    th = moving.profile.threshold_e
    short = tfp_dt_denoised(moving.spikes, moving.profile, 32, moving.center, sigma=0.0) / th
    long = tfp_dt_denoised(moving.spikes, moving.profile, 320, moving.center, sigma=0.0) / th
    from recon.metrics import psnr_ssim
    assert psnr_ssim(short, moving.target[0])[0] > psnr_ssim(long, moving.target[0])[0] + 3.0


def test_grouped_tuning_writes_a_motion_table(tmp_path):
    from recon.baselines import load_sigma_table as load
    from recon.baselines import main
    from recon.synth import make_davis_like
    root = make_davis_like(tmp_path / "davis", ["tr-a", "tr-b", "te-a"], n_frames=3, size=(8, 8), seed=4)
    split = tmp_path / "split.json"
    split.write_text(json.dumps({"train": ["tr-a", "tr-b"], "test": ["te-a"]}))
    out = tmp_path / "table.json"
    spec = f"davis:{root}:split_file={split}:res=8x8:warmup=8:frame_stride=2"
    assert main(["tune", "--group", spec, "--group", f"{spec};{spec}", "--lux", "5,500", "--items", "1",
                 "--windows", "32,320", "--out", str(out)]) == 0
    t = load(out)
    assert t["version"] == 3 and len(t["groups"]) == 2 and len(t["counts"]) == 2
    for g in t["groups"]:
        assert len(g["counts"]) == len(g["motions"]) == 2 and set(g["windows"]) <= {32, 320}
    assert len(t["groups"][1]["data"]) == 2 and t["groups"][1]["levels"][0]["items"] == 2
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({**json.loads(out.read_text()), "groups": [{"counts": [1.0], "windows": [32]}]}))
    with pytest.raises(InputError, match="group 0"):
        load(bad)
    with pytest.raises(SystemExit):
        main(["tune", "--lux", "5", "--out", str(out)])
