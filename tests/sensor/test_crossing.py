"""The crossing reset (``profile.reset == "crossing"``): profile field and oracles from closed forms.

Every stochastic test has a fixed seed; tolerances are standard errors of the
quantity tested (derived next to each) times ``Z`` = 3.9, or a Bonferroni z. The
oracles come from :mod:`sensor.analysis.theory` (section "The crossing reset"): the
renewal law of the continuous-time firings and the exact phase chain of the
read-out (f = 0, no dark). They run on both implementations.
"""

import io
import json

import numpy as np
import pytest
from scipy import stats

import sensor
from sensor.analysis import theory
from sensor.profile import PROFILE_VERSION, RESETS

from ..conftest import Z
from .crossing_checks import (check_hot_pixel_current_fires_at_every_whole_threshold,
                              check_prnu_gain_sets_the_photoelectrons_needed, nth_isis)

IMPLS = ["reference", "fast"]
#: for the reference implementation's longest runs: slow tests (the fast one checks the same oracle by default,
#: and the fast-vs-reference tests below keep the reference in the default run)
IMPLS_SLOW_REFERENCE = [pytest.param("reference", marks=pytest.mark.slow), "fast"]


def _sim(impl):
    """``sim(rate, profile, seed)`` of :mod:`tests.sensor.crossing_checks` on implementation ``impl``."""
    return lambda r, p, seed: sensor.simulate(r, p, "elssim", seed=seed, implementation=impl)


def crossing_profile(h, w, theta, **kw):
    kw.setdefault("refractory_s", 0.0)
    return sensor.SensorProfile.synthetic(h, w, threshold_e=theta, reset="crossing", **kw)


def lag1(s):
    """Pooled lag-1 correlation of consecutive read-out ISIs of a bool (T, H, W) stream, and the pair count."""
    flat = s.reshape(s.shape[0], -1)
    x, y = [], []
    for j in range(flat.shape[1]):
        d = np.diff(np.flatnonzero(flat[:, j]))
        x.append(d[:-1])
        y.append(d[1:])
    x, y = np.concatenate(x), np.concatenate(y)
    return float(np.corrcoef(x, y)[0, 1]), x.size


# ------------------------------------------------------------------------------------------- profile field
def test_reset_field_validated_saved_loaded_and_shown(tmp_path):
    assert RESETS == ("interval", "crossing")
    p = crossing_profile(4, 8, 50.0, dark_rate=0.01, seed=1)
    assert p.reset == "crossing"
    assert sensor.SensorProfile.synthetic(4, 8, threshold_e=50.0).reset == "interval"
    with pytest.raises(sensor.ProfileError, match="reset.*interval, crossing"):
        p.replace(reset="midway")
    q = p.replace(reset="interval")
    assert q.reset == "interval" and p.reset == "crossing"
    assert p.window(0, 0, 2, 2).reset == "crossing"
    path = p.save(tmp_path / "c.npz")
    back = sensor.SensorProfile.load(path)
    assert back.reset == "crossing"
    assert back.summary()["reset"] == "crossing" and back.to_meta()["reset"] == "crossing"
    assert PROFILE_VERSION >= 2 and back.to_meta()["version"] == PROFILE_VERSION


def test_a_profile_file_without_reset_is_refused(tmp_path):
    p = crossing_profile(3, 5, 40.0)
    path = p.save(tmp_path / "v2.npz")
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(bytes(arrays["meta_json"]).decode())
    del meta["reset"]
    arrays["meta_json"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    bad = tmp_path / "no-reset.npz"
    bad.write_bytes(buf.getvalue())
    with pytest.raises(sensor.ProfileError, match="reset"):
        sensor.SensorProfile.load(bad)


def test_info_command_shows_the_reset(tmp_path, capsys):
    from render2spike.cli import main
    path = crossing_profile(3, 5, 40.0).save(tmp_path / "c.npz")
    assert main(["info", str(path), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["reset"] == "crossing"


def test_elssim_follows_the_profile_reset():
    from sensor.models.registry import get_model
    from sensor.models.step import ELSSimCrossingStep, ELSSimStep
    p = crossing_profile(2, 8, 20.0)
    assert isinstance(get_model("elssim", p, "reference"), ELSSimCrossingStep)
    assert isinstance(get_model("elssim", p.replace(reset="interval"), "reference"), ELSSimStep)
    from sensor.models import fast
    if fast.HAVE_NUMBA:
        assert isinstance(get_model("elssim", p, "fast"), fast.ELSSimCrossingFast)
        assert isinstance(get_model("elssim", p.replace(reset="interval"), "fast"), fast.ELSSimFast)
    # the other models have one pixel each and ignore the reset
    lam = np.full((50, 2, 8), 3.0, np.float32)
    np.testing.assert_array_equal(sensor.simulate(lam, p, "isi", seed=1),
                                  sensor.simulate(lam, p.replace(reset="interval"), "isi", seed=1))


def test_simulate_cli_reset_option_overrides_the_profile(tmp_path):
    from render2spike.cli import main
    prof = crossing_profile(4, 8, 20.0)
    prof_path = prof.save(tmp_path / "cam.npz")
    rate = np.full((300, 4, 8), 9.0, np.float32)
    np.save(tmp_path / "rate.npy", rate)
    for reset in RESETS:
        out = tmp_path / f"{reset}.npz"
        assert main(["simulate", str(tmp_path / "rate.npy"), "--out", str(out), "--profile", str(prof_path),
                     "--reset", reset, "--quiet", "--seed", "2"]) == 0
        from sensor.io.spikefile import read_spikes_with_meta
        spikes, meta = read_spikes_with_meta(out)
        np.testing.assert_array_equal(spikes, sensor.simulate(rate, prof.replace(reset=reset), seed=2))
        assert meta["simulator"]["reset"] == reset


# ---------------------------------------------------------------------------------- rate and start-up
@pytest.mark.parametrize("impl", IMPLS)
def test_readout_rate_is_smooth_in_light_and_matches_the_phase_chain(impl, slow_scale):
    # lam = 0.45 theta: the interval reset gives ~1/3 (staircase), the crossing reset 0.45 (smooth)
    k, lam = 20, 9.0
    H, W, T = 20, 20, 1500 * slow_scale
    prof = crossing_profile(H, W, float(k))
    s = sensor.simulate(np.full((T, H, W), lam, np.float32), prof, "elssim", seed=3, implementation=impl)
    expected = theory.crossing_readout_probability(np.full(T, lam), k).sum()  # exact, start-up included
    _, var = theory.crossing_window_count_moments(lam, k, T)  # stationary Var of one pixel's count over T
    counts = s.sum(axis=0).ravel()
    assert abs(counts.mean() - expected) < Z * np.sqrt(var / counts.size), (counts.mean(), expected)
    # teeth: the interval reset's rate (about 1/ceil(k/lam)) is far outside the band
    assert abs(T / 3 - expected) > 10 * Z * np.sqrt(var / counts.size)


def lag1_cov(s, mean):
    """Lag-1 autocovariance of read-out ISIs about the known ``mean``, pooled over pixels, and its standard error.

    Per pixel j: c_j = sum of (N_i - mean)(N_{i+1} - mean) over its consecutive ISI pairs, n_j = pair count.
    The pooled estimate is sum c / sum n (a ratio of sums over independent pixels); its SE by the delta method
    (CLT over pixels) is sd(c_j - R n_j) / (sqrt(P) mean(n_j)).
    """
    flat = s.reshape(s.shape[0], -1)
    c, n = [], []
    for j in range(flat.shape[1]):
        d = np.diff(np.flatnonzero(flat[:, j])) - mean
        c.append(np.sum(d[:-1] * d[1:]))
        n.append(max(d.size - 1, 0))
    c, n = np.asarray(c), np.asarray(n, np.float64)
    R = c.sum() / n.sum()
    return R, np.std(c - R * n, ddof=1) / (np.sqrt(c.size) * n.mean())


@pytest.mark.parametrize("impl", IMPLS)
def test_readout_lag1_isi_correlation_matches_the_phase_chain(impl, slow_scale):
    k, lam = 200, 200 / 3.4  # near-regular firings (continuous CV 1/sqrt(k)): the read-out makes the ISIs alternate
    H, W, T = 16, 16 * slow_scale, 1000
    prof = crossing_profile(H, W, float(k))
    s = sensor.simulate(np.full((T, H, W), lam, np.float32), prof, "elssim", seed=4, implementation=impl)
    mean, var, rho = theory.crossing_readout_isi_stats(lam, k)
    cov, se = lag1_cov(s[20:], mean)  # skip the start-up (the phase is uniform after a few ISIs)
    assert rho < -0.4
    assert abs(cov - rho * var) < Z * se, (cov / var, rho, se / var)
    # teeth: the interval reset's read-out is a renewal process (zero lag-1 correlation): far outside the band
    assert abs(rho * var) > 10 * Z * se


def discrete_ks(sample, pmf_support, pmf):
    """Exact KS statistic of a sample against a discrete law on ``pmf_support`` and its (conservative) p-value."""
    cdf = np.cumsum(pmf)
    ecdf = np.searchsorted(np.sort(sample), pmf_support, side="right") / sample.size
    D = np.max(np.abs(ecdf - cdf))
    return D, stats.kstwo.sf(D, sample.size)


# ---------------------------------------------------------------------------------------- Fano factor
@pytest.mark.parametrize("impl", IMPLS)
def test_window_count_fano_factor_matches_the_phase_chain(impl, slow_scale):
    k, lam = 30, 30 / 2.6
    H, W, T, skip = 20, 20 * slow_scale, 1100, 100
    prof = crossing_profile(H, W, float(k))
    s = sensor.simulate(np.full((T, H, W), lam, np.float32), prof, "elssim", seed=6, implementation=impl)
    s = s[skip:].reshape(T - skip, -1)
    for win in (4, 50):
        mean, var = theory.crossing_window_count_moments(lam, k, win)
        c = s[: (T - skip) // win * win].reshape(-1, win, s.shape[1]).sum(axis=1)  # (windows, pixels)
        # per pixel: mean squared deviation from the known mean; pixels are independent, so the CLT over pixels
        # gives the SE of their average from its sample standard deviation
        per_pix = ((c - mean) ** 2).mean(axis=0)
        se = per_pix.std(ddof=1) / np.sqrt(per_pix.size)
        assert abs(per_pix.mean() - var) < Z * se, (win, per_pix.mean(), var, se)
        pm = c.mean(axis=0)  # per-pixel mean count: independent over pixels
        assert abs(pm.mean() - mean) < Z * pm.std(ddof=1) / np.sqrt(pm.size), (win, pm.mean(), mean)
    # the long-window Fano factor is far below the Poisson 1 and the interval reset's value differs
    m50, v50 = theory.crossing_window_count_moments(lam, k, 50)
    assert v50 / m50 < 0.2


# ------------------------------------------------------------------------------------------ ISI laws
def firing_times(model, lam, T, seed):
    """Exact continuous firing times [intervals] of a reference crossing model (``record_crossings``) run for
    ``T`` intervals of constant light ``lam`` [e-/interval]: (pixel index, time) arrays, sorted by pixel, then
    time."""
    model.record_crossings = True
    st = model.init_state()
    H, W = model.profile.shape
    model.run_block(np.full((T, H, W), lam, np.float32), st, np.random.default_rng(seed))
    pix = np.concatenate([p for p, _ in st["crossings"]])
    tim = np.concatenate([t for _, t in st["crossings"]])
    order = np.lexsort((tim, pix))
    return pix[order], tim[order]


def inter_firing_times(model, lam, T, seed):
    """Exact continuous-time gaps [intervals] between consecutive firings of each pixel of a reference
    crossing model (``record_crossings``) run for ``T`` intervals of constant light ``lam`` [e-/interval]."""
    pix, tim = firing_times(model, lam, T, seed)
    return np.diff(tim)[pix[1:] == pix[:-1]]


def test_continuous_time_isi_law_is_blind_time_plus_gamma_or_dark():
    # the reference records its exact firing times: inter-firing times are f + min(Gamma(k, lam), Exp(mu)), iid
    from sensor.models.step import ELSSimCrossingStep
    k, lam, f, mu = 12, 4.0, 0.3, 0.05
    H, W, T = 12, 12, 600
    prof = crossing_profile(H, W, float(k), refractory_s=f * sensor.INTERVAL_S, dark_rate=mu)
    x = inter_firing_times(ELSSimCrossingStep(prof), lam, T, seed=8)
    assert x.min() >= f - 1e-9
    res = stats.kstest(x, lambda v: 1.0 - theory.crossing_firing_survival(v, lam, k, f, mu))
    assert res.pvalue > 1e-4, res
    # teeth: the same law without the blind time is rejected
    assert stats.kstest(x, lambda v: 1.0 - theory.crossing_firing_survival(v, lam, k, 0.0, mu)).pvalue < 1e-6


@pytest.mark.parametrize("impl", IMPLS)
def test_readout_isi_law_matches_the_phase_chain(impl, slow_scale):
    k, lam = 40, 40 / 3.3
    H, W, T, j = 30, 30 * slow_scale, 60, 6
    prof = crossing_profile(H, W, float(k))
    s = sensor.simulate(np.full((T, H, W), lam, np.float32), prof, "elssim", seed=9, implementation=impl)
    x = nth_isis(s, j)  # one ISI per pixel: independent draws of the exact law of the j-th ISI
    assert x.size == H * W
    support = np.arange(1, 30)
    D, p = discrete_ks(x, support, theory.crossing_readout_isi_pmf(support, lam, k, after_spikes=j))
    assert p > 1e-4, (D, p)
    # teeth: the interval reset's ISI law at the same light (renewal, reset to zero) is rejected
    wrong = theory.isi_pmf(support, lam, k)
    assert discrete_ks(x, support, wrong)[1] < 1e-6


# --------------------------------------------------------------------------------------- dark only
@pytest.mark.parametrize("impl", IMPLS_SLOW_REFERENCE)
def test_dark_only_is_a_poisson_process_read_out(impl, slow_scale):
    H, W, T = 20, 20, 8000 * slow_scale
    prof = crossing_profile(H, W, 1000.0, dark_rate=0.05, dark_rate_spread=0.8, seed=3)
    s = sensor.simulate(np.zeros((T, H, W), np.float32), prof, "elssim", seed=10, implementation=impl)
    # f = 0: independent Poisson increments, an interval reads 1 with probability 1 - exp(-mu), independently
    p_true = -np.expm1(-prof.dark_rate.astype(np.float64))
    se = np.sqrt(p_true * (1 - p_true) / T)
    zb = stats.norm.isf(1e-3 / (2 * H * W))
    assert np.max(np.abs(s.mean(axis=0) - p_true) / se) < zb
    assert np.abs(s.mean() - prof.dark_rate.mean()) > Z * np.sqrt((p_true * (1 - p_true)).mean() / s.size)


@pytest.mark.parametrize("impl", IMPLS_SLOW_REFERENCE)
def test_dark_events_are_lost_while_blind(impl):
    mu, f = 0.2, 0.6
    H, W, T = 20, 20, 6000
    prof = crossing_profile(H, W, 1000.0, dark_rate=mu, refractory_s=f * sensor.INTERVAL_S)
    s = sensor.simulate(np.zeros((T, H, W), np.float32), prof, "elssim", seed=11, implementation=impl)
    _, r = theory.crossing_rates(0.0, 1000, f, mu)  # E[min(X, 1)] / E[X], X = f + Exp(mu)
    # after a firing the pixel is blind for f, so the read-out indicators of nearby intervals are negatively
    # dependent and the count variance is at most the binomial one; start-up: the stream starts un-blind (< 1
    # firing's worth of bias per pixel, over E[X] ~ 5.6 intervals)
    se = np.sqrt(r * (1 - r) / s.size)
    assert abs(s.mean() - r) < Z * se + 1.0 / (T * 5.6), (s.mean(), r)
    assert abs(-np.expm1(-mu) - r) > 4 * Z * se  # without the blind loss the rate would be 1 - exp(-mu)


# --------------------------------------------------------------------------------- refractory, PRNU
@pytest.mark.parametrize("impl", IMPLS_SLOW_REFERENCE)
def test_refractory_blind_time_lowers_the_rate_as_renewal_theory_says(impl):
    lam, k, T, H, W = 6.0, 12, 3000, 20, 20
    for f in (0.0, 0.5):
        prof = crossing_profile(H, W, float(k), refractory_s=f * sensor.INTERVAL_S)
        s = sensor.simulate(np.full((T, H, W), lam, np.float32), prof, "elssim", seed=12, implementation=impl)
        _, r = theory.crossing_rates(lam, k, f)
        ex = theory.crossing_inter_firing_mean(lam, k, f)
        var_x = k / lam ** 2  # Var(f + Gamma(k, lam))
        # renewal CLT: Var(N_T) ~ T Var(X) / E[X]^3 per pixel (two firings in one interval have P < 1e-4 here);
        # start-up: the stream starts un-blind, |E N_T - T / E X| <= 1 + E[X^2] / E[X]^2 / 2 < 2 per pixel
        se = np.sqrt(T * var_x / ex ** 3 / (H * W)) / T
        assert abs(s.mean() - r) < Z * se + 2.0 / T, (f, s.mean(), r)
    assert theory.crossing_rates(lam, k, 0.5)[1] < theory.crossing_rates(lam, k, 0.0)[1] - 10 * (Z * se + 2.0 / T)


@pytest.mark.parametrize("impl", IMPLS)
def test_prnu_gain_sets_the_photoelectrons_needed(impl):
    check_prnu_gain_sets_the_photoelectrons_needed(_sim(impl), crossing_profile)


# -------------------------------------------------------------------------------------------- hot pixels
@pytest.mark.parametrize("impl", IMPLS_SLOW_REFERENCE)
def test_hot_pixel_current_fires_at_every_whole_threshold(impl):
    check_hot_pixel_current_fires_at_every_whole_threshold(_sim(impl), crossing_profile)


# -------------------------------------------------------------------------------- time-varying input
@pytest.mark.parametrize("impl", IMPLS)
def test_keyframed_input_follows_the_exact_phase_chain(impl, slow_scale):
    H, W, k = 30, 40 * slow_scale, 15
    K = 31  # keyframes every 20 intervals -> 600 intervals
    t = np.arange(K) * 1e-3
    rng = np.random.default_rng(15)
    curve = np.clip(6 + 5 * np.sin(np.arange(K) / 3.0) + rng.normal(0, 1, K), 0, None)
    r = (curve[:, None, None] * np.ones((1, H, W))).astype(np.float32)
    prof = crossing_profile(H, W, float(k))
    s = sensor.simulate(r, prof, "elssim", seed=16, t_s=t, implementation=impl)
    lam_m = sensor.interval_rates(r[:, :1, :1], t)[:, 0, 0].astype(np.float64)
    p = theory.crossing_readout_probability(lam_m, k)  # exact for any time-varying light (f = 0, no dark)
    bins = 30
    obs = s.reshape(bins, -1, H * W).sum(axis=1)  # (bins, pixels): counts per pixel per bin
    exp_ = p.reshape(bins, -1).sum(axis=1)
    # pixels are independent: per bin, the SE of the pixel-mean count from its sample sd; Bonferroni over bins
    se = obs.std(axis=1, ddof=1) / np.sqrt(H * W)
    zb = stats.norm.isf(1e-3 / (2 * bins))
    zs = np.abs(obs.mean(axis=1) - exp_) / se
    assert zs.max() < zb, zs.max()
    assert np.corrcoef(exp_, curve[:-1].reshape(bins, -1).mean(1))[0, 1] > 0.9


# ---------------------------------------------------------------------------------- chunk invariance
@pytest.mark.parametrize("impl", IMPLS_SLOW_REFERENCE)
def test_chunked_equals_whole_bitwise(impl):
    prof = sensor.SensorProfile.synthetic(12, 16, threshold_e=30, dark_rate=0.01, prnu_sigma=0.1,
                                          hot_pixel_fraction=0.05, refractory_s=0.3 * sensor.INTERVAL_S, seed=7,
                                          reset="crossing")
    rng = np.random.default_rng(0)
    T = 1300 if impl == "fast" else 600
    lam = rng.uniform(0, 12, (T, 12, 16)).astype(np.float32)
    whole = sensor.simulate(lam, prof, seed=3, implementation=impl)
    for chunk in (1, 7, 256, 999):
        np.testing.assert_array_equal(sensor.simulate(lam, prof, seed=3, implementation=impl, chunk=chunk), whole)
    t = np.cumsum(rng.uniform(0.3e-3, 2e-3, 40))
    r = rng.uniform(0, 8, (40, 12, 16)).astype(np.float32)
    a = sensor.simulate(r, prof, seed=5, t_s=t, implementation=impl)
    np.testing.assert_array_equal(a, sensor.simulate(r, prof, seed=5, t_s=t, implementation=impl, chunk=3))
    assert (a != sensor.simulate(r, prof, seed=6, t_s=t, implementation=impl)).any()


# ----------------------------------------------------------------------------- fast vs reference
def _both(rate, prof, seed, t_s=None):
    return (sensor.simulate(rate, prof, seed=seed, t_s=t_s, implementation="fast"),
            sensor.simulate(rate, prof, seed=seed, t_s=t_s, implementation="reference"))


def _rates_agree(a, b, what):
    # read-out indicators of one pixel are sub-binomial here (regular firings, CV^2 <= 1 - p): binomial SE is
    # conservative (see test_fast.py)
    p = (a.sum() + b.sum()) / (a.size + b.size)
    se = np.sqrt(p * (1 - p) * (1 / a.size + 1 / b.size))
    assert abs(a.mean() - b.mean()) <= Z * se + 1e-15, (what, a.mean(), b.mean(), se)


def test_fast_agrees_with_reference_vidar_like_with_every_effect():
    prof = sensor.SensorProfile.synthetic(30, 30, threshold_e=200.0, dark_rate=0.01, dark_rate_spread=0.37,
                                          prnu_sigma=0.058, hot_pixel_fraction=0.03, hot_mu=0.05, hot_sigma=0.02,
                                          refractory_s=0.1 * sensor.INTERVAL_S, seed=17, reset="crossing")
    rng = np.random.default_rng(18)
    t = np.arange(0, 61) * 1e-3  # 1200 intervals, keyframes every 20, light crossing fast-block boundaries
    r = (np.clip(40 + 25 * np.sin(np.arange(61) / 5.0), 0, None)[:, None, None]
         * rng.uniform(0.5, 1.5, (1, 30, 30))).astype(np.float32)
    fs, rs = _both(r, prof, 19, t_s=t)
    hot = prof.hot_mask
    _rates_agree(fs[:, ~hot], rs[:, ~hot], "normal pixels")
    _rates_agree(fs[:, hot], rs[:, hot], "hot pixels")
    for a, b in ((0, 400), (400, 800), (800, 1200)):
        _rates_agree(fs[a:b], rs[a:b], f"intervals {a}:{b}")
    # one ISI per pixel (the 5th): independent samples, two-sample KS
    assert stats.ks_2samp(nth_isis(fs[:, ~hot], 5), nth_isis(rs[:, ~hot], 5)).pvalue > 1e-4


@pytest.mark.parametrize("k,lam,f,mu", [(200, 200 / 3.4, 0.0, 0.0), (25, 9.0, 0.4, 0.02)])
def test_fast_agrees_with_reference_lag1_and_isi(k, lam, f, mu):
    H, W, T = 20, 20, 800
    prof = crossing_profile(H, W, float(k), refractory_s=f * sensor.INTERVAL_S, dark_rate=mu)
    fs, rs = _both(np.full((T, H, W), lam, np.float32), prof, 20)
    _rates_agree(fs, rs, "rate")
    m = 0.5 * (np.diff(np.flatnonzero(fs[:, 0, 0])).mean() + np.diff(np.flatnonzero(rs[:, 0, 0])).mean())
    cf, sf = lag1_cov(fs[20:], m)
    cr, sr = lag1_cov(rs[20:], m)
    assert abs(cf - cr) < Z * np.hypot(sf, sr), (cf, cr)
    assert stats.ks_2samp(nth_isis(fs, 4), nth_isis(rs, 4)).pvalue > 1e-4


@pytest.mark.slow
def test_negative_hot_current_is_clipped_like_the_reference():
    H, W, T = 10, 10, 3000
    prof = crossing_profile(H, W, 100.0, refractory_s=0.2 * sensor.INTERVAL_S, dark_rate=0.002)
    mask = np.ones((H, W), bool)
    prof = prof.replace(hot_mask=mask, hot_mu=np.full((H, W), 0.01), hot_sigma=np.full((H, W), 0.1))
    fs, rs = _both(np.full((T, H, W), 0.5, np.float32), prof, 21)
    _rates_agree(fs, rs, "clipped hot current")
    assert stats.ks_2samp(nth_isis(fs, 3), nth_isis(rs, 3)).pvalue > 1e-4


@pytest.mark.slow
def test_fast_agrees_with_reference_at_vidar_threshold():
    prof = sensor.SensorProfile.synthetic(20, 25, threshold_e=2000.0, dark_rate=0.0047, dark_rate_spread=0.37,
                                          prnu_sigma=0.058, hot_pixel_fraction=0.02, refractory_s=0.2e-6,
                                          seed=1, reset="crossing")
    for lam in (90.0, 450.0, 900.0):
        fs, rs = _both(np.full((3000, 20, 25), lam, np.float32), prof, int(lam))
        _rates_agree(fs, rs, f"lam {lam}")
        assert stats.ks_2samp(nth_isis(fs, 5), nth_isis(rs, 5)).pvalue > 1e-4


# ------------------------------------------------------------------------------ vidar-default evidence
def test_vidar_default_uses_the_crossing_reset_and_says_why():
    p = sensor.SensorProfile.load("vidar-default")
    assert p.reset == "crossing"
    assert "crossing" in p.provenance["reset"] and "uhsr" in p.provenance["reset"]


def test_excess_lag1_is_zero_for_a_renewal_stream_and_negative_for_the_crossing_reset():
    from sensor.calibration.vidar import lag1_isi_correlation_by_mean_isi
    k, lam, T = 300, 300 / 14.4, 200  # ~13 ISIs per pixel: the plain estimate is biased by about -1/13
    out = {}
    for reset in RESETS:
        prof = crossing_profile(40, 40, float(k)).replace(reset=reset)
        s = sensor.simulate(np.full((T, 40, 40), lam, np.float32), prof, "elssim", seed=22)
        out[reset] = lag1_isi_correlation_by_mean_isi(s, (10.0, 20.0))[0]
    iv, cr = out["interval"], out["crossing"]
    assert abs(iv["rho_excess"]) < Z * iv["se_excess"], iv  # renewal: exchangeable ISIs, zero in expectation
    assert iv["rho"] < -0.03  # while the plain estimate is biased
    assert cr["rho_excess"] < -Z * cr["se_excess"], cr


def test_real_recording_supports_the_crossing_reset():
    from pathlib import Path
    path = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "real" / "uhsr.npz"
    if not path.exists():
        pytest.skip("real recording ../shared/data/real/uhsr.npz not present")
    from sensor.calibration.vidar import reset_evidence
    rec = np.load(path)["spk"][:, :100, :100]
    ev = reset_evidence(rec, seed=0, edges=(10.0, 20.0))
    real, iv, cr = ev["real"][0], ev["interval"][0], ev["crossing"][0]
    assert real["pixels"] > 300
    # the real pixels' ISIs are anti-correlated beyond the short-record bias, as the crossing reset's are and the
    # interval reset's (a renewal process) are not
    assert real["rho_excess"] < -Z * real["se_excess"]
    assert cr["rho_excess"] < -Z * cr["se_excess"]
    assert abs(iv["rho_excess"]) < Z * iv["se_excess"]
