"""Oracle tests of the spike models against closed-form and exact-numerical results.

Every stochastic test uses a fixed seed. Tolerances are standard errors from the
statistics of the quantity tested, times a z-score (``Z`` = 3.9, two-sided
P ~ 1e-4) or a Bonferroni z for per-pixel checks; the derivation is next to each.
They run on both implementations ('reference' step simulator and the default
'fast' path).
"""

import numpy as np
import pytest
from scipy import stats

import sensor
from sensor.analysis import theory
from sensor.models.effects import count_threshold
from sensor.units import TIME_UNIT_S

from ..conftest import Z

IMPLS = ["reference", "fast"]


def bonferroni_z(n_tests: int, alpha: float = 1e-3) -> float:
    """Two-sided z so that n_tests checks together fail by chance with probability <= alpha."""
    return float(stats.norm.isf(alpha / (2 * n_tests)))


def flat_profile(h, w, threshold_e, **kw):
    kw.setdefault("refractory_s", 0.0)
    return sensor.SensorProfile.synthetic(h, w, threshold_e=threshold_e, **kw)


# --------------------------------------------------------------------------- ideal
@pytest.mark.parametrize("impl", IMPLS)
def test_ideal_constant_rate_matches_integrate_and_fire_count(impl):
    # rates chosen so that theta / lam is never an integer (no ties at the threshold)
    lam = np.array([[0.37, 1.3, 2.9], [4.1, 7.7, 19.3]], np.float32)
    theta, M = 20.0, 1000
    prof = flat_profile(2, 3, theta)
    s = sensor.simulate(np.broadcast_to(lam, (M, 2, 3)), prof, "ideal", implementation=impl)
    # deterministic: V reaches theta after ceil(theta / lam) intervals, then resets to 0
    isi = np.ceil(theta / lam.astype(np.float64))
    np.testing.assert_array_equal(s.sum(axis=0), M // isi)
    # and the first spike is in interval isi - 1 (0-based)
    np.testing.assert_array_equal(s.argmax(axis=0), isi - 1)


# --------------------------------------------------------------- elssim shot noise
@pytest.mark.parametrize("impl", IMPLS)
def test_elssim_shot_noise_mean_rate_matches_exact_renewal(impl, slow_scale):
    lam, theta, f = 1.3, 20.0, 0.04
    H, W, T = 40, 50, 3000 * slow_scale
    prof = flat_profile(H, W, theta, refractory_s=f * sensor.INTERVAL_S)
    s = sensor.simulate(np.full((T, H, W), lam, np.float32), prof, "elssim", seed=11, implementation=impl)
    k = 20
    n = np.arange(0, 400)
    pmf_first = theory.isi_pmf(n, lam, k, 0.0, 0.0)  # the stream starts reset, with no refractory loss
    pmf = theory.isi_pmf(n, lam, k, 0.0, f)
    pmf_first[0] = pmf[0] = 0.0
    expected = theory.renewal_density(pmf_first, pmf, T).sum()  # exact E[spikes per pixel in T intervals]
    counts = s.sum(axis=0).ravel()
    # renewal CLT: Var(N_T) ~ T var / mean^3 per pixel; the pixel mean over H*W independent pixels
    m, v = theory.isi_moments(lam, k, 0.0, f)
    se = np.sqrt(T * v / m ** 3 / counts.size)
    assert abs(counts.mean() - expected) < Z * se, (counts.mean(), expected, se)


@pytest.mark.parametrize("impl", IMPLS)
def test_elssim_isi_distribution_passes_ks_against_renewal(impl):
    lam, theta, f = 2.2, 15.0, 0.1
    H, W, T = 40, 50, 260
    prof = flat_profile(H, W, theta, refractory_s=f * sensor.INTERVAL_S)
    s = sensor.simulate(np.full((T, H, W), lam, np.float32), prof, "elssim", seed=5, implementation=impl)
    t_idx = [np.flatnonzero(s[:, i, j]) for i in range(H) for j in range(W)]
    J = 6  # ISIs 2..J+1 of each pixel: iid with the refractory ISI law (ISI 1 starts without refractory)
    assert min(len(t) for t in t_idx) >= J + 2, "stream too short to complete J ISIs everywhere"
    isis = np.concatenate([np.diff(t[:J + 2])[1:] for t in t_idx])
    support = np.arange(1, isis.max() + 30)
    cdf = theory.isi_cdf(support, lam, 15, 0.0, f)
    ecdf = np.searchsorted(np.sort(isis), support, side="right") / isis.size
    D = np.max(np.abs(ecdf - cdf))  # sup over the common jump points: the exact KS statistic
    p = stats.kstwo.sf(D, isis.size)  # conservative for discrete laws (can only make rejection rarer)
    assert p > 1e-3, (D, p)
    # and the test can fail: a law with k one lower is rejected
    cdf_wrong = theory.isi_cdf(support, lam, 14, 0.0, f)
    assert stats.kstwo.sf(np.max(np.abs(ecdf - cdf_wrong)), isis.size) < 1e-6


# --------------------------------------------------------------------- dark only
@pytest.mark.parametrize("impl", IMPLS)
def test_dark_only_spike_probability_is_one_minus_exp(impl, slow_scale):
    H, W, T = 20, 20, 20000 * slow_scale
    # mu_DC ~ 0.05 (log-normal spread): large enough that 1 - exp(-mu) and mu differ by many SEs
    prof = flat_profile(H, W, 1000.0, dark_rate=0.05, dark_rate_spread=0.8, seed=3)
    s = sensor.simulate(np.zeros((T, H, W), np.float32), prof, "elssim", seed=9, implementation=impl)
    p_true = -np.expm1(-prof.dark_rate.astype(np.float64))
    p_hat = s.mean(axis=0)
    # Bernoulli per interval -> binomial: SE = sqrt(p (1 - p) / T) per pixel; Bonferroni over the pixels
    se = np.sqrt(p_true * (1 - p_true) / T)
    zmax = np.max(np.abs(p_hat - p_true) / se)
    assert zmax < bonferroni_z(H * W), zmax
    # the first-order formula p = mu_DC is rejected at these rates: the check has teeth
    assert np.abs(p_hat.mean() - prof.dark_rate.mean()) > Z * np.sqrt((p_true * (1 - p_true)).mean() / (T * H * W))


# ------------------------------------------------------------ refractory and PRNU
@pytest.mark.parametrize("impl", IMPLS)
def test_refractory_period_lowers_the_rate_as_the_model_says(impl):
    lam, theta, T, H, W = 2.0, 6.0, 4000, 25, 40
    rates = {}
    for f in (0.0, 0.5):
        prof = flat_profile(H, W, theta, refractory_s=f * sensor.INTERVAL_S)
        s = sensor.simulate(np.full((T, H, W), lam, np.float32), prof, "elssim", seed=21, implementation=impl)
        rates[f] = s.mean()
        m, v = theory.isi_moments(lam, 6, 0.0, f)
        se = np.sqrt(v / m ** 3 / (T * H * W))  # renewal CLT, per interval
        assert abs(rates[f] - 1 / m) < Z * se + 1.0 / (T * m), (f, rates[f], 1 / m)  # + start-up O(1/T)
    assert rates[0.5] < rates[0.0]


@pytest.mark.parametrize("impl", IMPLS)
def test_prnu_gain_changes_the_photoelectrons_needed(impl):
    lam, theta, T = 3.0, 20.0, 4000
    gain = np.where(np.arange(40 * 25).reshape(40, 25) % 2 == 0, 0.8, 1.25).astype(np.float32)
    prof = flat_profile(40, 25, theta).replace(prnu_gain=gain)
    s = sensor.simulate(np.full((T, 40, 25), lam, np.float32), prof, "elssim", seed=2, implementation=impl)
    for g in (0.8, 1.25):
        k = float(count_threshold(theta, g))  # ceil(20 / 0.8) = 25, ceil(20 / 1.25) = 16
        m, v = theory.isi_moments(lam, k)
        sel = gain == np.float32(g)
        r = s[:, sel].mean()
        se = np.sqrt(v / m ** 3 / (T * sel.sum()))
        assert abs(r - 1 / m) < Z * se + 1.0 / (T * m), (g, r, 1 / m)
    assert count_threshold(theta, 0.8) == 25 and count_threshold(theta, 1.25) == 16


@pytest.mark.parametrize("impl", IMPLS)
def test_hot_pixel_isi_mean_matches_first_passage_model(impl):
    H, W, T = 10, 10, 20000
    prof = flat_profile(H, W, 500.0, dark_rate=0.002)
    mask = np.zeros((H, W), bool)
    mask[::3, ::3] = True
    prof = prof.replace(hot_mask=mask, hot_mu=np.where(mask, 0.07, 0), hot_sigma=np.where(mask, 0.03, 0))
    s = sensor.simulate(np.zeros((T, H, W), np.float32), prof, "elssim", seed=4, implementation=impl)
    isis = np.concatenate([np.diff(np.flatnonzero(s[:, i, j])) for i, j in zip(*np.nonzero(mask))])
    m, v = theory.hot_pixel_isi_moments(0.07, 0.03, -np.expm1(-0.002))
    assert abs(isis.mean() - m) < Z * np.sqrt(v / isis.size), (isis.mean(), m)
    # normal pixels stay at the dark rate
    assert s[:, ~mask].mean() < 0.002 + Z * np.sqrt(0.002 / (T * (~mask).sum()))


# ----------------------------------------------------------------------- isi model
def test_isi_model_constant_rate_mean_matches_gamma_isi():
    # continuous-time ISI ~ Gamma(k, 1/q) with q = g lam + mu_DC theta: spikes per interval -> q / k
    # (at most one spike per interval; q / k << 1 here so collisions are negligible: P ~ (q/k)^2)
    lam, theta, T, H, W = 0.5, 50.0, 20000, 20, 20
    prof = flat_profile(H, W, theta, dark_rate=0.001)
    s = sensor.simulate(np.full((T, H, W), lam, np.float32), prof, "isi", seed=1)
    q = lam + 0.001 * theta
    rate = q / 50
    se = np.sqrt(rate / (T * H * W) / 50)  # Gamma(k) ISIs: CV^2 = 1/k
    assert abs(s.mean() - rate) < Z * se + rate ** 2, (s.mean(), rate)


@pytest.mark.parametrize("impl", IMPLS)
def test_isi_model_gain_enters_once(impl):
    # Gamma(k, 1/q) ISIs with k = ceil(theta / g) counts and q = lam + mu_DC theta / g counts per interval:
    # rate = q / k, so a gain-1.25 pixel fires 1.25x as often as a gain-1 pixel (not 1.25^2)
    lam, theta, T, H, W = 0.5, 50.0, 20000, 20, 20
    gain = np.where(np.arange(H * W).reshape(H, W) % 2 == 0, 1.0, 1.25).astype(np.float32)
    prof = flat_profile(H, W, theta, dark_rate=0.001).replace(prnu_gain=gain)
    s = sensor.simulate(np.full((T, H, W), lam, np.float32), prof, "isi", seed=3, implementation=impl)
    for g in (1.0, 1.25):
        k = float(count_threshold(theta, g))
        rate = (lam + 0.001 * theta / g) / k
        sel = gain == np.float32(g)
        se = np.sqrt(rate / (T * sel.sum()) / k)  # Gamma(k) ISIs: CV^2 = 1/k; renewal CLT
        assert abs(s[:, sel].mean() - rate) < Z * se + rate ** 2, (g, s[:, sel].mean(), rate)


# ------------------------------------------------------------- streaming and seeds
@pytest.mark.parametrize("model", ["ideal", "elssim", "isi"])
@pytest.mark.parametrize("impl", IMPLS)
def test_chunked_equals_whole_bitwise(model, impl):
    prof = sensor.SensorProfile.synthetic(12, 16, threshold_e=30, dark_rate=0.01, prnu_sigma=0.1,
                                          hot_pixel_fraction=0.05, refractory_s=TIME_UNIT_S, seed=7)
    rng = np.random.default_rng(0)
    T = 1300
    lam = rng.uniform(0, 6, (T, 12, 16)).astype(np.float32)
    whole = sensor.simulate(lam, prof, model, seed=3, implementation=impl)
    for chunk in (1, 7, 256, 999):
        np.testing.assert_array_equal(sensor.simulate(lam, prof, model, seed=3, implementation=impl, chunk=chunk),
                                      whole)
    # keyframes with timestamps, irregular spacing, fed in odd chunks
    t = np.cumsum(rng.uniform(0.3e-3, 2e-3, 40))
    r = rng.uniform(0, 8, (40, 12, 16)).astype(np.float32)
    a = sensor.simulate(r, prof, model, seed=5, t_s=t, implementation=impl)
    b = sensor.simulate(r, prof, model, seed=5, t_s=t, implementation=impl, chunk=3)
    np.testing.assert_array_equal(a, b)
    if model != "ideal":
        c = sensor.simulate(r, prof, model, seed=6, t_s=t, implementation=impl)
        assert (a != c).any(), "a different seed must give a different stream"


def test_streaming_class_matches_simulate_and_refuses_after_finish():
    prof = sensor.SensorProfile.synthetic(4, 8, threshold_e=10, seed=0)
    lam = np.full((700, 4, 8), 1.5, np.float32)
    sim = sensor.SpikeSimulator(prof, "elssim", seed=2, per_interval=True)
    parts = [sim.feed(lam[i:i + 100]) for i in range(0, 700, 100)] + [sim.finish()]
    np.testing.assert_array_equal(np.concatenate(parts), sensor.simulate(lam, prof, "elssim", seed=2))
    with pytest.raises(sensor.InputError):
        sim.feed(lam[:10])


def test_unknown_model_lists_the_valid_choices():
    prof = sensor.SensorProfile.synthetic(2, 8, threshold_e=10)
    with pytest.raises(sensor.UnknownMethodError, match="elssim.*ideal.*isi"):
        sensor.simulate(np.zeros((3, 2, 8)), prof, "davis")


def test_rate_shape_mismatch_is_a_clear_error():
    prof = sensor.SensorProfile.synthetic(2, 8, threshold_e=10)
    with pytest.raises(sensor.InputError, match=r"\(K, 2, 8\)"):
        sensor.simulate(np.zeros((3, 4, 8)), prof)
    with pytest.raises(sensor.InputError, match=r"negative.*in \[0, "):
        sensor.simulate(-np.ones((3, 2, 8)), prof)
