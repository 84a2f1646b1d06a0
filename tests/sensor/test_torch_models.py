"""The torch implementation (:mod:`sensor.models.torch_models`) is the same model as the reference and fast ones.

Every statistical test runs on each device: ``cpu`` always, ``cuda`` where a CUDA device works (those are
marked ``cuda`` and run by ``benchmarks/gpu_check.sh``). Fixed seeds; tolerances are standard errors times
``Z`` = 3.9 (P ~ 1e-4 per check) or a Bonferroni z, and each SE is derived next to its check:

* two-sample rates (torch vs reference or fast): binomial SE of the difference, conservative for read-outs
  whose counts are sub-binomial (renewal ISIs with CV^2 <= 1 - p; see ``test_fast.py``);
* ISI laws: two-sample KS at alpha = 1e-4 (conservative for discrete laws), on independent samples where the
  read-out ISIs are correlated (crossing reset: one ISI per pixel);
* closed-form oracles of :mod:`sensor.analysis.theory` (renewal ISI moments, 1 - exp(-mu), the crossing phase
  chain, blind-time renewal rates) with the variance they give;
* time-varying input: a chi-square test of homogeneity of the counts per time bin.

Plus: ``ideal`` is bitwise the reference with one rate per interval, a seed reproduces its spikes on a device,
the spikes do not depend on the chunking nor on torch's CPU thread count, the state goes across blocks, bad
device names fail in one line, ``auto`` is ``fast`` without CUDA, ``import sensor`` does not load torch, and the
CLI records the implementation and device.
"""

import os
import subprocess
import sys

import numpy as np
import pytest
from scipy import stats

import sensor
from sensor.analysis import theory
from sensor.models.effects import count_threshold
from sensor.units import INTERVAL_S

from ..conftest import Z
from .crossing_checks import (check_hot_pixel_current_fires_at_every_whole_threshold,
                              check_prnu_gain_sets_the_photoelectrons_needed, nth_isis)

torch = pytest.importorskip("torch")
from sensor.models import torch_models  # noqa: E402
from sensor.models.registry import get_model, resolve_implementation  # noqa: E402
from sensor.models.step import block_generator  # noqa: E402

HAVE_CUDA = torch_models.cuda_works()
DEVICES = ["cpu", pytest.param("cuda", marks=[pytest.mark.cuda,
                                               pytest.mark.skipif(not HAVE_CUDA, reason="no working CUDA device")])]
#: the statistical tests also run the CUDA path's dense draws on the CPU ("cpu-dense"): in the default run for the
#: every-effect and reproducibility tests, with --runslow for every oracle
STAT_DEVICES = DEVICES + [pytest.param("cpu-dense", marks=pytest.mark.slow)]
DENSE_DEVICES = DEVICES + ["cpu-dense"]
ALPHA = 1e-4


def prof(h, w, theta, **kw):
    kw.setdefault("refractory_s", 0.0)
    return sensor.SensorProfile.synthetic(h, w, threshold_e=theta, **kw)


def run(rate, p, device, model="elssim", seed=0, t_s=None, impl="torch", chunk=None):
    """sensor.simulate with ``impl``; ``device`` "cpu-dense": torch on the CPU with the dense draws of new Gamma
    targets (the path CUDA takes, :attr:`torch_models._TorchModel.dense_rounds`)."""
    dense = device == "cpu-dense"
    cls = torch_models._TorchModel
    try:
        cls.dense_rounds = True if dense else None
        return sensor.simulate(rate, p, model, seed=seed, t_s=t_s, implementation=impl,
                               device=("cpu" if dense else device) if impl == "torch" else None, chunk=chunk)
    finally:
        cls.dense_rounds = None


def rates_agree(a, b, what=""):
    p = (a.sum() + b.sum()) / (a.size + b.size)
    se = np.sqrt(p * (1 - p) * (1 / a.size + 1 / b.size))
    assert abs(a.mean() - b.mean()) <= Z * se + 1e-15, f"{what}: torch {a.mean():.6g} vs {b.mean():.6g}, SE {se:.3g}"


def isis(s, skip_first=True):
    flat = s.reshape(s.shape[0], -1)
    out = [np.diff(np.flatnonzero(flat[:, j]))[1 if skip_first else 0:] for j in range(flat.shape[1])]
    return np.concatenate(out)


def ks_agree(a, b, what=""):
    res = stats.ks_2samp(a, b)
    assert res.pvalue > ALPHA, f"{what}: KS D = {res.statistic:.4g}, p = {res.pvalue:.3g} (n = {a.size}, {b.size})"


# ----------------------------------------------------------------------------------- interval reset
@pytest.mark.parametrize("device", STAT_DEVICES)
def test_interval_constant_light_agrees_with_reference_and_renewal_oracle(device):
    lam, k, f = 1.7, 20, 0.08
    H, W, T = 30, 40, 2500
    p = prof(H, W, float(k), refractory_s=f * INTERVAL_S)
    rate = np.full((T, H, W), lam, np.float32)
    ts, rs = run(rate, p, device, seed=11), run(rate, p, device, seed=11, impl="reference")
    rates_agree(ts, rs, "shot noise")
    a = isis(ts)
    ks_agree(a, isis(rs), "shot-noise ISI")
    m, v = theory.isi_moments(lam, k, 0.0, f)  # renewal: the ISIs of a pixel are iid
    assert abs(a.mean() - m) < Z * np.sqrt(v / a.size), (a.mean(), m)
    # count variance per pixel: renewal CLT Var(N_T) ~ T v / m^3; its sample estimate over 1200 pixels
    c = ts.sum(axis=0).ravel()
    var_pred = T * v / m ** 3
    se_var = var_pred * np.sqrt(2.0 / (c.size - 1))  # chi-square SE of a normal-sample variance
    assert abs(c.var(ddof=1) - var_pred) < Z * se_var + 2.0, (c.var(ddof=1), var_pred)


@pytest.mark.parametrize("device", STAT_DEVICES)
def test_interval_dark_events_and_dark_current_match_their_oracles(device):
    H, W, T, mu = 20, 25, 6000, 0.05
    s = run(np.zeros((T, H, W), np.float32), prof(H, W, 100.0, dark_rate=mu, refractory_s=0.3 * INTERVAL_S),
            device, seed=12)
    pd = -np.expm1(-mu)  # a dark event in an interval: exactly Bernoulli per interval
    se = np.sqrt(pd * (1 - pd) / s.size)
    assert abs(s.mean() - pd) < Z * se, (s.mean(), pd)
    assert abs(mu - pd) > 2 * Z * se  # the first-order p = mu fails the same check
    # dark current: d electrons per interval with their shot noise, k = theta / g of them fire, the excess is
    # discarded at the reset: the renewal ISI law of light of rate d (f = 0), and the fast kernel's
    pc = prof(H, W, 10.0, dark="current", dark_current_e=0.8)
    tc = run(np.zeros((2000, H, W), np.float32), pc, device, seed=13)
    rc = run(np.zeros((2000, H, W), np.float32), pc, device, seed=13, impl="fast")
    rates_agree(tc, rc, "dark current")
    ks_agree(isis(tc), isis(rc), "dark-current ISI")
    m, v = theory.isi_moments(0.8, 10, 0.0, 0.0)
    a = isis(tc)
    assert abs(a.mean() - m) < Z * np.sqrt(v / a.size), (a.mean(), m)


@pytest.mark.parametrize("device", STAT_DEVICES)
def test_interval_refractory_under_high_light(device):
    lam, k, f = 6.0, 12, 0.6  # ISI ~ 2 intervals: every other interval is a refractory one
    H, W, T = 25, 30, 1500
    s = run(np.full((T, H, W), lam, np.float32), prof(H, W, float(k), refractory_s=f * INTERVAL_S), device, seed=13)
    a = isis(s)
    m, v = theory.isi_moments(lam, k, 0.0, f)
    m0, _ = theory.isi_moments(lam, k, 0.0, 0.0)
    assert abs(a.mean() - m) < Z * np.sqrt(v / a.size), (a.mean(), m)
    assert m - m0 > 10 * Z * np.sqrt(v / a.size)  # the refractory effect is far beyond the noise


@pytest.mark.parametrize("device", STAT_DEVICES)
def test_interval_prnu_count_ratio_per_gain(device):
    lam, theta, T, H, W = 2.5, 20.0, 2000, 30, 40
    p = prof(H, W, theta, prnu_sigma=0.15, seed=4)
    rate = np.full((T, H, W), lam, np.float32)
    ts, fs = run(rate, p, device, seed=14), run(rate, p, device, seed=14, impl="fast")
    k = count_threshold(theta, p.prnu_gain)
    ks_, counts = np.unique(k.ravel(), return_counts=True)
    assert (counts >= 60).sum() >= 3
    for kk in ks_[counts >= 60]:  # pixels pooled by their count threshold: same rate as the fast kernel, and
        sel = k == kk            # the renewal oracle's 1 / E[ISI]
        rates_agree(ts[:, sel], fs[:, sel], f"k={kk}")
        m, v = theory.isi_moments(lam, kk, 0.0, 0.0)
        n = ts[:, sel].sum(axis=0)  # counts per pixel: Var ~ T v / m^3 (renewal), +-1 from the start-up
        assert abs(n.mean() - T / m) < Z * np.sqrt(T * v / m ** 3 / n.size) + 1.0, (kk, n.mean(), T / m)
    # the count ratio between the low- and high-gain halves follows the thresholds
    lo, hi = k <= np.median(k), k > np.median(k)
    r_obs = ts[:, hi].mean() / ts[:, lo].mean()
    r_fast = fs[:, hi].mean() / fs[:, lo].mean()
    se = r_obs * np.sqrt(1 / ts[:, hi].sum() + 1 / ts[:, lo].sum() + 1 / fs[:, hi].sum() + 1 / fs[:, lo].sum())
    assert abs(r_obs - r_fast) < Z * se and r_obs < 1.0 - 4 * Z * se, (r_obs, r_fast, se)


@pytest.mark.parametrize("device", STAT_DEVICES)
def test_interval_hot_pixels_agree_with_reference(device):
    H, W, T = 20, 20, 3000
    p = prof(H, W, 200.0, dark_rate=0.002, hot_pixel_fraction=0.1, hot_mu=0.05, hot_mu_spread=0.5, hot_sigma=0.03,
             refractory_s=0.1 * INTERVAL_S, seed=6)
    hot = p.hot_mask
    rate = np.full((T, H, W), 1.5, np.float32)
    ts, rs = run(rate, p, device, seed=15), run(rate, p, device, seed=15, impl="reference")
    rates_agree(ts[:, hot], rs[:, hot], "hot pixels")
    rates_agree(ts[:, ~hot], rs[:, ~hot], "normal pixels")
    zb = stats.norm.isf(1e-3 / (2 * hot.sum()))  # per hot pixel, Bonferroni over the 40 of them
    for i, j in zip(*np.nonzero(hot)):
        a, b = ts[:, i, j], rs[:, i, j]
        pp = (a.sum() + b.sum()) / (2 * T)
        assert abs(a.mean() - b.mean()) <= zb * np.sqrt(2 * pp * (1 - pp) / T) + 1e-12
    ks_agree(isis(ts[:, hot][:, :, None]), isis(rs[:, hot][:, :, None]), "hot ISI")


@pytest.mark.parametrize("device", STAT_DEVICES)
def test_interval_time_varying_keyframes_agree_bin_by_bin(device):
    rng = np.random.default_rng(10)
    H, W, K = 20, 30, 121  # keyframes every 20 intervals -> 2400 intervals, over three torch blocks
    t = np.arange(K) * 1e-3
    curve = np.clip(3 + 2.5 * np.sin(np.arange(K) / 6.0) + rng.normal(0, 0.7, K), 0, None)
    r = (curve[:, None, None] * np.ones((1, H, W))).astype(np.float32)
    p = prof(H, W, 10.0, dark_rate=0.002, prnu_sigma=0.05, refractory_s=0.2 * INTERVAL_S, seed=7)
    ts, fs = run(r, p, device, seed=17, t_s=t), run(r, p, device, seed=17, t_s=t, impl="fast")
    assert ts.shape == fs.shape == (2400, H, W)
    bins = 48
    ct, cf = ts.reshape(bins, -1).sum(1), fs.reshape(bins, -1).sum(1)
    _, pv, _, _ = stats.chi2_contingency(np.stack([ct, cf]))
    assert pv > ALPHA, pv
    lam = sensor.interval_rates(r[:, :1, :1], t)[:, 0, 0].reshape(bins, -1).mean(1)
    assert np.corrcoef(lam, ct)[0, 1] > 0.9  # the rate follows the light


# ----------------------------------------------------------------------------------- crossing reset
def crossing(h, w, theta, **kw):
    return prof(h, w, theta, reset="crossing", **kw)


@pytest.mark.parametrize("device", STAT_DEVICES)
def test_crossing_constant_light_matches_the_phase_chain_and_fast_isi(device):
    k, lam = 20, 9.0
    H, W, T = 20, 20, 1500
    p = crossing(H, W, float(k))
    rate = np.full((T, H, W), lam, np.float32)
    ts = run(rate, p, device, seed=3)
    expected = theory.crossing_readout_probability(np.full(T, lam), k).sum()  # exact, start-up included
    _, var = theory.crossing_window_count_moments(lam, k, T)  # stationary Var of one pixel's count over T
    counts = ts.sum(axis=0).ravel()
    assert abs(counts.mean() - expected) < Z * np.sqrt(var / counts.size), (counts.mean(), expected)
    # count variance over 100-interval windows: the phase chain's (sub-Poisson), per-pixel estimates averaged
    mean_w, var_w = theory.crossing_window_count_moments(lam, k, 100)
    c = ts[100:].reshape(14, 100, -1).sum(axis=1)
    per_pix = ((c - mean_w) ** 2).mean(axis=0)
    assert abs(per_pix.mean() - var_w) < Z * per_pix.std(ddof=1) / np.sqrt(per_pix.size), (per_pix.mean(), var_w)
    # the read-out ISI law against the fast kernel's: one ISI per pixel (independent), over 1600 pixels
    fs = run(np.full((400, 40, 40), lam, np.float32), crossing(40, 40, float(k)), device, seed=4, impl="fast")
    ts2 = run(np.full((400, 40, 40), lam, np.float32), crossing(40, 40, float(k)), device, seed=4)
    ks_agree(nth_isis(ts2, 5), nth_isis(fs, 5), "crossing ISI")


@pytest.mark.parametrize("device", STAT_DEVICES)
def test_crossing_dark_only_is_a_poisson_process_and_is_lost_while_blind(device):
    H, W, T = 20, 20, 8000
    p = crossing(H, W, 1000.0, dark_rate=0.05, dark_rate_spread=0.8, seed=3)
    s = run(np.zeros((T, H, W), np.float32), p, device, seed=10)
    p_true = -np.expm1(-p.dark_rate.astype(np.float64))  # f = 0: Poisson events, read out per interval
    se = np.sqrt(p_true * (1 - p_true) / T)
    zb = stats.norm.isf(1e-3 / (2 * H * W))
    assert np.max(np.abs(s.mean(axis=0) - p_true) / se) < zb
    mu, f = 0.2, 0.6
    s = run(np.zeros((6000, H, W), np.float32), crossing(H, W, 1000.0, dark_rate=mu, refractory_s=f * INTERVAL_S),
            device, seed=11)
    _, r = theory.crossing_rates(0.0, 1000, f, mu)  # E[min(X, 1)] / E[X], X = f + Exp(mu)
    se = np.sqrt(r * (1 - r) / s.size)  # negatively dependent indicators: binomial SE is conservative
    assert abs(s.mean() - r) < Z * se + 1.0 / (6000 * 5.6), (s.mean(), r)
    assert abs(-np.expm1(-mu) - r) > 4 * Z * se  # without the blind loss the rate would be 1 - exp(-mu)


@pytest.mark.parametrize("device", STAT_DEVICES)
def test_crossing_dark_current_agrees_with_fast_and_renewal(device):
    # dark == "current": d electrons per interval count with the light; no light: firings every Gamma(k, d)
    H, W, T, d, k = 20, 20, 3000, 2.0, 8
    p = crossing(H, W, float(k), dark="current", dark_current_e=d, refractory_s=0.1 * INTERVAL_S)
    rate = np.zeros((T, H, W), np.float32)
    ts, fs = run(rate, p, device, seed=21), run(rate, p, device, seed=21, impl="fast")
    rates_agree(ts, fs, "dark current")
    _, r = theory.crossing_rates(d, k, 0.1)
    ex, var_x = theory.crossing_inter_firing_mean(d, k, 0.1), k / d ** 2
    se = np.sqrt(T * var_x / ex ** 3 / (H * W)) / T  # renewal CLT of the count
    assert abs(ts.mean() - r) < Z * se + 2.0 / T, (ts.mean(), r)


@pytest.mark.parametrize("device", STAT_DEVICES)
def test_crossing_refractory_blind_time_lowers_the_rate_as_renewal_theory_says(device):
    lam, k, T, H, W = 6.0, 12, 3000, 20, 20
    for f in (0.0, 0.5):
        s = run(np.full((T, H, W), lam, np.float32), crossing(H, W, float(k), refractory_s=f * INTERVAL_S), device,
                seed=12)
        _, r = theory.crossing_rates(lam, k, f)
        ex, var_x = theory.crossing_inter_firing_mean(lam, k, f), k / lam ** 2
        se = np.sqrt(T * var_x / ex ** 3 / (H * W)) / T  # renewal CLT; start-up bias < 2 firings per pixel
        assert abs(s.mean() - r) < Z * se + 2.0 / T, (f, s.mean(), r)
    assert theory.crossing_rates(lam, k, 0.5)[1] < theory.crossing_rates(lam, k, 0.0)[1] - 10 * (Z * se + 2.0 / T)


@pytest.mark.parametrize("device", STAT_DEVICES)
def test_crossing_prnu_gain_sets_the_photoelectrons_needed(device):
    check_prnu_gain_sets_the_photoelectrons_needed(lambda r, p, seed: run(r, p, device, seed=seed), crossing)


@pytest.mark.parametrize("device", STAT_DEVICES)
def test_crossing_hot_pixel_current_fires_at_every_whole_threshold(device):
    check_hot_pixel_current_fires_at_every_whole_threshold(lambda r, p, seed: run(r, p, device, seed=seed),
                                                           crossing)


@pytest.mark.parametrize("device", DENSE_DEVICES)
def test_crossing_every_effect_agrees_with_reference_and_fast(device):
    p = sensor.SensorProfile.synthetic(30, 30, threshold_e=200.0, dark_rate=0.01, dark_rate_spread=0.37,
                                       prnu_sigma=0.058, hot_pixel_fraction=0.03, hot_mu=0.05, hot_sigma=0.02,
                                       refractory_s=0.1 * INTERVAL_S, seed=17, reset="crossing")
    rng = np.random.default_rng(18)
    t = np.arange(0, 61) * 1e-3  # 1200 intervals, keyframes every 20, light crossing a torch block boundary
    r = (np.clip(40 + 25 * np.sin(np.arange(61) / 5.0), 0, None)[:, None, None]
         * rng.uniform(0.5, 1.5, (1, 30, 30))).astype(np.float32)
    ts = run(r, p, device, seed=19, t_s=t)
    hot = p.hot_mask
    for impl in ("reference", "fast"):
        other = run(r, p, device, seed=19, t_s=t, impl=impl)
        rates_agree(ts[:, ~hot], other[:, ~hot], f"normal pixels vs {impl}")
        rates_agree(ts[:, hot], other[:, hot], f"hot pixels vs {impl}")
        for a, b in ((0, 400), (400, 800), (800, 1200)):
            rates_agree(ts[a:b], other[a:b], f"intervals {a}:{b} vs {impl}")
        ks_agree(nth_isis(ts[:, ~hot], 5), nth_isis(other[:, ~hot], 5), f"5th ISI vs {impl}")


@pytest.mark.parametrize("device", STAT_DEVICES)
def test_crossing_keyframed_input_follows_the_exact_phase_chain(device):
    H, W, k, K = 30, 40, 15, 31  # keyframes every 20 intervals -> 600 intervals
    t = np.arange(K) * 1e-3
    rng = np.random.default_rng(15)
    curve = np.clip(6 + 5 * np.sin(np.arange(K) / 3.0) + rng.normal(0, 1, K), 0, None)
    r = (curve[:, None, None] * np.ones((1, H, W))).astype(np.float32)
    s = run(r, crossing(H, W, float(k)), device, seed=16, t_s=t)
    lam_m = sensor.interval_rates(r[:, :1, :1], t)[:, 0, 0].astype(np.float64)
    pm = theory.crossing_readout_probability(lam_m, k)  # exact for time-varying light (f = 0, no dark)
    bins = 30
    obs = s.reshape(bins, -1, H * W).sum(axis=1)
    exp_ = pm.reshape(bins, -1).sum(axis=1)
    se = obs.std(axis=1, ddof=1) / np.sqrt(H * W)  # pixels independent: SE of the pixel mean per bin
    zs = np.abs(obs.mean(axis=1) - exp_) / se
    assert zs.max() < stats.norm.isf(1e-3 / (2 * bins)), zs.max()


# ------------------------------------------------------------------------------------------- ideal
@pytest.mark.parametrize("device", DEVICES)
def test_ideal_is_bitwise_the_reference_per_interval_across_blocks(device):
    p = prof(20, 30, 37.5)
    lam = np.random.default_rng(9).uniform(0, 9, (2300, 20, 30)).astype(np.float32)  # three torch blocks
    t = run(lam, p, device, "ideal")
    np.testing.assert_array_equal(t, run(lam, p, device, "ideal", impl="reference"))
    assert t.any() and t[1000:].any()


@pytest.mark.parametrize("device", DEVICES)
def test_ideal_with_keyframes_differs_only_at_round_off_ties(device):
    p = prof(20, 30, 37.5)
    rng = np.random.default_rng(9)
    ts_ = np.arange(0, 101) * 1e-3
    r = rng.uniform(0, 9, (101, 20, 30)).astype(np.float32)
    t, ref = run(r, p, device, "ideal", t_s=ts_), run(r, p, device, "ideal", t_s=ts_, impl="reference")
    # lambda_m in float64 from the pieces vs the reference's float32 matrix product: they may disagree only
    # after a threshold decision within float32 round-off (|V - theta| <= 3 eps32 V), as for the fast kernel
    from sensor.rates import hat_interval_weights
    T, P = t.shape[0], 600
    lam64 = hat_interval_weights(ts_, ts_[0] + np.arange(T + 1) * INTERVAL_S, INTERVAL_S) @ r.reshape(101, P).astype(
        np.float64)
    eps32 = float(np.finfo(np.float32).eps)
    V = np.zeros(P)
    fragile_first = np.full(P, np.inf)
    for m in range(T):
        V += lam64[m]
        fragile = np.abs(V - 37.5) <= 3 * eps32 * V
        fragile_first[fragile & np.isinf(fragile_first)] = m
        V[V >= 37.5] = 0.0
    mism = (t != ref).reshape(T, P)
    bad = mism.any(axis=0)
    assert np.all(fragile_first[bad] <= mism.argmax(axis=0)[bad] + 1), "a disagreement without a round-off tie"
    assert np.abs(t.sum(0).astype(int) - ref.sum(0).astype(int)).max() <= 1


# ------------------------------------------------------------------------------- reproducibility
def _mixed_profile(reset):
    return sensor.SensorProfile.synthetic(12, 16, threshold_e=30, dark_rate=0.01, prnu_sigma=0.1,
                                          hot_pixel_fraction=0.05, refractory_s=0.3 * INTERVAL_S, seed=7, reset=reset)


@pytest.mark.parametrize("device", DENSE_DEVICES)
@pytest.mark.parametrize("reset", ["interval", "crossing"])
def test_seed_reproduces_the_spikes_for_any_chunking(device, reset):
    p = _mixed_profile(reset)
    rng = np.random.default_rng(0)
    lam = rng.uniform(0, 12, (1300, 12, 16)).astype(np.float32)  # two torch blocks: the state crosses one
    whole = run(lam, p, device, seed=3)
    np.testing.assert_array_equal(run(lam, p, device, seed=3), whole)
    for chunk in (7, 999):
        np.testing.assert_array_equal(run(lam, p, device, seed=3, chunk=chunk), whole)
    assert (run(lam, p, device, seed=4) != whole).any()
    t = np.cumsum(rng.uniform(0.3e-3, 2e-3, 40))
    r = rng.uniform(0, 8, (40, 12, 16)).astype(np.float32)
    np.testing.assert_array_equal(run(r, p, device, seed=5, t_s=t), run(r, p, device, seed=5, t_s=t, chunk=3))


@pytest.mark.parametrize("device", ["cpu", "cpu-dense"])
@pytest.mark.parametrize("reset", ["interval", "crossing"])
def test_cpu_spikes_do_not_depend_on_torch_threads(reset, device):
    p = _mixed_profile(reset)
    lam = np.random.default_rng(1).uniform(0, 12, (300, 12, 16)).astype(np.float32)
    n = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = run(lam, p, device, seed=8)
        torch.set_num_threads(max(2, n))
        two = run(lam, p, device, seed=8)
    finally:
        torch.set_num_threads(n)
    np.testing.assert_array_equal(one, two)


def test_state_stays_on_the_device_and_blocks_carry_it():
    p = _mixed_profile("crossing")
    model = get_model("elssim", p, "torch", device="cpu")
    assert model.implementation == "torch" and model.device_name == "cpu"
    state = model.init_state()
    lam = np.full((2, 12, 16), 50.0, np.float32)
    from sensor.rates import Segments
    bits = model.run_segments(Segments.per_interval(lam, 0), state, block_generator(1, "elssim", 0, "torch"))
    assert bits.dtype == np.uint8 and bits.shape == (2, 24) and state["m"] == 2
    assert all(state[k].device.type == "cpu" and isinstance(state[k], torch.Tensor) for k in ("rem", "blind"))
    with pytest.raises(ValueError, match="starts at interval 0 but the state is at 2"):
        model.run_segments(Segments.per_interval(lam, 0), state, block_generator(1, "elssim", 0, "torch"))


def test_torch_stream_key_is_its_own_and_the_others_are_unchanged():
    draw = {impl: block_generator(5, "elssim", 3, impl).random() for impl in ("reference", "fast", "torch")}
    assert len(set(draw.values())) == 3
    for impl, key in (("reference", 0), ("fast", 1)):  # the existing streams keep their spawn keys
        ss = np.random.SeedSequence(5, spawn_key=(1, key, 3))
        assert draw[impl] == np.random.Generator(np.random.PCG64(ss)).random()


# ------------------------------------------------------------------------------- selection, errors
def test_bad_device_names_fail_in_one_line(monkeypatch):
    p = prof(4, 8, 10.0)
    with pytest.raises(sensor.InputError, match=r"field 'device': unknown spike device 'tpu'") as e:
        sensor.SpikeSimulator(p, implementation="torch", device="tpu")
    assert "\n" not in str(e.value)
    monkeypatch.setenv(torch_models.DEVICE_ENV, "gpu0")
    with pytest.raises(sensor.InputError, match=r"RENDER2SPIKE_SPIKE_DEVICE.*unknown spike device 'gpu0'"):
        sensor.SpikeSimulator(p)  # auto reads the variable too
    monkeypatch.setenv(torch_models.DEVICE_ENV, "cpu")
    assert sensor.SpikeSimulator(p, implementation="torch").device == "cpu"
    assert sensor.SpikeSimulator(p).implementation == resolve_implementation("elssim", p, "fast")  # auto + cpu
    if not HAVE_CUDA:
        with pytest.raises(sensor.InputError, match="no CUDA device works here"):
            sensor.SpikeSimulator(p, implementation="torch", device="cuda")


@pytest.mark.skipif(HAVE_CUDA, reason="a CUDA device works here: auto is torch")
def test_auto_is_fast_without_cuda_and_metadata_says_so(monkeypatch):
    monkeypatch.delenv(torch_models.DEVICE_ENV, raising=False)
    p = prof(4, 8, 10.0)
    sim = sensor.SpikeSimulator(p)
    assert sim.implementation == resolve_implementation("elssim", p, "fast") and sim.describe()["device"] == "cpu"
    t = sensor.SpikeSimulator(p, implementation="torch")
    assert t.describe()["implementation"] == "torch" and t.describe()["device"] == "cpu"
    assert sensor.SpikeSimulator(p, "isi", implementation="torch").implementation in ("fast", "reference")


@pytest.mark.cuda
@pytest.mark.skipif(not HAVE_CUDA, reason="no working CUDA device")
def test_auto_is_torch_on_cuda(monkeypatch):
    monkeypatch.delenv(torch_models.DEVICE_ENV, raising=False)
    sim = sensor.SpikeSimulator(prof(4, 8, 10.0))
    assert sim.implementation == "torch" and sim.device.startswith("cuda")
    assert sim.state["v"].device.type == "cuda"


def test_import_sensor_loads_no_torch():
    code = ("import sys, numpy as np, sensor; p = sensor.SensorProfile.synthetic(2, 8, threshold_e=5.0); "
            "sensor.simulate(np.ones((3, 2, 8), np.float32), p, implementation='reference'); "
            "print('torch' in sys.modules); sensor.simulate(np.ones((3, 2, 8), np.float32), p); "
            "print('torch' in sys.modules)")
    env = {k: v for k, v in os.environ.items() if k != torch_models.DEVICE_ENV}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.split()
    assert lines[0] == "False"
    if not torch_models._nvidia_driver_present():  # auto asks torch only where an NVIDIA driver is loaded
        assert lines[1] == "False"


def test_simulate_cli_implementation_option_and_metadata(tmp_path, cli, monkeypatch):
    monkeypatch.delenv(torch_models.DEVICE_ENV, raising=False)
    from sensor.io.spikefile import read_spikes_with_meta
    p = prof(6, 8, 10.0, dark_rate=0.01, seed=2)
    p.save(tmp_path / "p.npz")
    rate = np.full((50, 6, 8), 2.0, np.float32)
    np.save(tmp_path / "rate.npy", rate)
    base = ["simulate", tmp_path / "rate.npy", "--profile", tmp_path / "p.npz", "--quiet", "--seed", "3"]
    res = cli(*base, "--out", tmp_path / "t.npz", "--implementation", "torch", "--device", "cpu")
    assert res.returncode == 0, res.stderr
    spikes, meta = read_spikes_with_meta(tmp_path / "t.npz")
    assert meta["implementation"] == "torch" and meta["simulator"]["device"] == "cpu"
    np.testing.assert_array_equal(spikes, sensor.simulate(rate, p, seed=3, implementation="torch", device="cpu"))
    res = cli(*base, "--out", tmp_path / "r.npz", "--reference")
    assert res.returncode == 0, res.stderr
    assert read_spikes_with_meta(tmp_path / "r.npz")[1]["implementation"] == "reference"
    res = cli(*base, "--out", tmp_path / "x.npz", "--reference", "--implementation", "torch")
    assert res.returncode != 0 and "--reference" in res.stderr and "Traceback" not in res.stderr
    res = cli(*base, "--out", tmp_path / "y.npz", "--implementation", "torch", "--device", "tpu")
    assert res.returncode != 0 and "unknown spike device 'tpu'" in res.stderr and "Traceback" not in res.stderr
