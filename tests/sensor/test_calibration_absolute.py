"""Absolute calibration round trip at vidar-like statistics (theta = 2000 e-), for both resets.

A profile with planted maps is simulated in the dark and under flat fields up to
0.5 spikes per interval, calibrated with a wrong base threshold (1500 e-), and
every estimate is compared with the truth within ``z`` times its own standard
error (z from tests/conftest.py; Bonferroni over pixels for maps). The standard
errors are derived in docs/sensor.md ("Absolute calibration"); the last check of
each map (mean of z^2 near 1) tests that they are neither too small nor too large.

Targets. With mean PRNU gain 1 by convention and counts multiplied by the gain,
the identifiable threshold is ``1 / mean(1 / k_i)`` over non-hot pixels
(``k_i = ceil(theta / g_i)``), the identifiable gain ``theta / k_i`` normalised
to mean 1, and the mean sensitivity the planted e- per lux per interval.
"""

import numpy as np
import pytest
from scipy import stats

import sensor
from sensor.calibration.estimate import calibrate
from sensor.models.effects import count_threshold
from sensor.calibration.vidar import VIDAR_EVENTS_SYNTHETIC as VIDAR_SYNTHETIC

S_TRUE = 200.0  # planted photoelectrons per lux per interval (a gain-1 pixel)
LUX = (0.5, 1.5, 3.0, 5.0)  # 100 .. 1000 e-/interval: 0.05 .. 0.5 spikes per interval


def zb(n, z):
    """Bonferroni z for n two-sided checks at the per-check level of ``z``."""
    return float(stats.norm.isf(stats.norm.sf(z) / n))


def round_trip(reset, H, W, T_dark, n_dark, T_flat, seed=7):
    true = sensor.SensorProfile.synthetic(H, W, **VIDAR_SYNTHETIC, seed=seed, reset=reset)
    dark = [sensor.simulate(np.zeros((T_dark, H, W), np.float32), true, "elssim", seed=100 + i)
            for i in range(n_dark)]
    flat = [sensor.simulate(np.full((T_flat, H, W), S_TRUE * lx, np.float32), true, "elssim", seed=200 + i)
            for i, lx in enumerate(LUX)]
    est, rep = calibrate(dark, flat, base=true.replace(threshold_e=1500.0, reset="interval"), flat_lux=list(LUX))
    return true, est, rep


@pytest.fixture(scope="module", params=["interval", "crossing"])
def small(request):
    return round_trip(request.param, 24, 32, 20000, 2, 10000)


def check_all(true, est, rep, z):
    n = ~true.hot_mask
    N = rep.numbers
    # hot pixels: the planted ones fire >= 0.02 spikes/interval above the median dark fraction
    np.testing.assert_array_equal(est.hot_mask, true.hot_mask)
    # dark map: binomial error of the pooled dark fraction, d mu / d p = 1 / (1 - p)
    p = -np.expm1(-true.dark_rate[n].astype(np.float64))
    n_int = rep.dark_intervals
    se = np.sqrt(p * (1 - p) / n_int) / (1 - p)
    assert (np.abs(est.dark_rate[n] - true.dark_rate[n]) / se).max() < zb(n.sum(), z)
    # hot-pixel charge: each (mu_HP, sigma_HP) within its delta-method error (exact ISI model of the reset)
    rows = N["hot_mu_sigma"]
    assert len(rows) == int(true.hot_mask.sum())
    for r, c, m, m_se, s, s_se, _ in rows:
        assert abs(m - true.hot_mu[r, c]) < zb(2 * len(rows), z) * m_se, (r, c, m, m_se, true.hot_mu[r, c])
        assert abs(s - true.hot_sigma[r, c]) < zb(2 * len(rows), z) * s_se, (r, c, s, s_se, true.hot_sigma[r, c])
    # reset
    assert N["reset"] == true.reset
    assert N["reset_confidence"] > 1 - 1e-3
    # threshold
    k = count_threshold(true.threshold_e, true.prnu_gain)
    theta_t = 1.0 / np.mean(1.0 / k[n])
    assert abs(N["threshold_e"] - theta_t) < z * N["threshold_se"], (N["threshold_e"], N["threshold_se"], theta_t)
    assert est.threshold_e == pytest.approx(N["threshold_e"])
    # PRNU: every pixel within its standard error, and the standard errors honest on average
    g = true.threshold_e / k
    g = g / g[n].mean()
    zg = (est.prnu_gain[n] - g[n]) / rep.prnu_se[n]
    assert np.abs(zg).max() < zb(n.sum(), z), np.abs(zg).max()
    assert abs(np.mean(zg ** 2) - 1) < z * np.sqrt(2 / n.sum()), np.mean(zg ** 2)
    # sensitivity (mean over pixels; the per-pixel map carries the PRNU)
    assert abs(N["sensitivity_e_per_lux"] - S_TRUE) < z * N["sensitivity_se"], (N["sensitivity_e_per_lux"],
                                                                                N["sensitivity_se"])
    return np.corrcoef(est.prnu_gain[n], true.prnu_gain[n])[0, 1]


def test_round_trip_small(small, z):
    true, est, rep = small
    check_all(true, est, rep, z)
    assert est.reset == true.reset


@pytest.mark.slow
@pytest.mark.parametrize("reset", ["interval", "crossing"])
def test_round_trip_large(reset, z):
    true, est, rep = round_trip(reset, 64, 96, 20000, 4, 40000, seed=11)
    check_all(true, est, rep, z)


def test_bright_flats_regression(small, z):
    """The issue's failure: flats up to 0.5 spikes/interval used to drag the PRNU map (correlation 0.26 with the
    interval reset). Now levels on the interval reset's staircase carry no weight and the map is recovered."""
    true, est, rep = small
    N = rep.numbers
    assert N["flat_mean_spike_rate"][-1] > 0.4
    n = ~true.hot_mask
    if true.reset == "interval":
        # the bright levels are on the staircase (sqrt(k)/lam < 0.3 interval): reported and not used
        assert N["level_used"][-1] is False and "staircase" in N["level_reason"][-1]
    else:
        # the crossing reset's rate is smooth in light: the brightest level carries the most information
        assert int(np.argmax(N["level_information_share"])) == len(LUX) - 1
    # the map's spread is the planted spread within the counting error
    g = true.threshold_e / count_threshold(true.threshold_e, true.prnu_gain)
    assert abs(est.prnu_gain[n].std() - (g[n] / g[n].mean()).std()) < z * np.sqrt(np.mean(rep.prnu_se[n] ** 2))


def test_warns_when_only_staircase_levels(capsys):
    true = sensor.SensorProfile.synthetic(16, 16, **VIDAR_SYNTHETIC, seed=3)
    dark = [sensor.simulate(np.zeros((4000, 16, 16), np.float32), true, "elssim", seed=1)]
    flat = [sensor.simulate(np.full((4000, 16, 16), lv, np.float32), true, "elssim", seed=2 + i)
            for i, lv in enumerate((700.0, 1000.0))]
    msgs = []
    _, rep = calibrate(dark, flat, base=true, reset="interval", progress=msgs.append)
    assert rep.numbers["prnu_enough"] is False
    assert any("not enough" in m for m in msgs)


@pytest.mark.parametrize("reset", ["interval", "crossing"])
def test_invert_rate_round_trips_any_shape(reset):
    """The exact rate-vs-light inversion returns the light it was given, for (H, W) as for flat inputs."""
    from sensor.calibration.flatfield import invert_rate, spike_rate
    x = np.array([[0.02, 0.05], [0.1, 0.3]])  # thresholds per interval (off the interval staircase for k = 100)
    k = np.full((2, 2), 100.0)
    mu = np.full((2, 2), 0.004)
    f = np.full((2, 2), 1 / 250)
    r = spike_rate(reset, x, k, mu, f).reshape(2, 2)
    back = invert_rate(reset, r, k, mu, f)
    assert back.shape == (2, 2)
    np.testing.assert_allclose(back, x, rtol=1e-6)
    np.testing.assert_allclose(invert_rate(reset, r.reshape(-1), k.reshape(-1), mu.reshape(-1), f.reshape(-1)),
                               x.reshape(-1), rtol=1e-6)
