"""Round trip: simulate dark and flat recordings from a profile with planted maps, calibrate, recover the maps.

Tolerances are standard errors computed from the true parameters with the
renewal theory of :mod:`sensor.analysis.theory`, times a Bonferroni z over the pixels
checked (family-wise false-failure probability 1e-3).
"""

import numpy as np
import pytest
from scipy import stats

import sensor
from sensor.analysis import theory
from sensor.calibration.estimate import calibrate
from sensor.models.effects import count_threshold

H, W, T_DARK, N_DARK, T_FLAT = 24, 32, 20000, 4, 20000
LEVELS = (2.0, 6.0, 15.0)  # e- per interval


def zb(n, alpha=1e-3):
    return float(stats.norm.isf(alpha / (2 * n)))


@pytest.fixture(scope="module")
def planted():
    true = sensor.SensorProfile.synthetic(H, W, threshold_e=100, dark_rate=0.004, dark_rate_spread=0.3,
                                          prnu_sigma=0.05, hot_pixel_fraction=0.01, hot_mu=0.08, hot_mu_spread=0.2,
                                          hot_sigma=0.03, seed=5)
    dark = [sensor.simulate(np.zeros((T_DARK, H, W), np.float32), true, "elssim", seed=100 + i)
            for i in range(N_DARK)]
    flat = [sensor.simulate(np.full((T_FLAT, H, W), lv, np.float32), true, "elssim", seed=200 + i)
            for i, lv in enumerate(LEVELS)]
    est, report = calibrate(dark, flat, base=true)
    return true, est, report, dark


def test_hot_pixel_mask_recovered_exactly(planted):
    true, est, _, _ = planted
    # planted hot pixels fire at ~0.05-0.1 per interval, normal ones at ~0.004: with 80,000 intervals the
    # binomial SE is < 1e-3, so theta_HT = 0.02 separates them with > 15 SE margin on both sides
    np.testing.assert_array_equal(est.hot_mask, true.hot_mask)


def test_dark_rate_recovered_within_binomial_error(planted):
    true, est, _, _ = planted
    n = ~true.hot_mask
    p = -np.expm1(-true.dark_rate[n].astype(np.float64))
    # p_hat ~ Binomial(N_DARK T_DARK, p) / N; mu = -ln(1 - p): d mu / d p = 1 / (1 - p)
    se = np.sqrt(p * (1 - p) / (N_DARK * T_DARK)) / (1 - p)
    z = np.abs(est.dark_rate[n] - true.dark_rate[n]) / se
    assert z.max() < zb(n.sum()), z.max()


def test_prnu_recovered_within_statistical_error(planted):
    true, est, report, _ = planted
    n = ~true.hot_mask
    theta, f = true.threshold_e, true.refractory_fraction.astype(np.float64)
    k_true = count_threshold(theta, true.prnu_gain)
    p_d = -np.expm1(-true.dark_rate.astype(np.float64))
    rate, inv = theory.renewal_spike_rate, theory.invert_renewal_rate

    # noise-free expectation of the estimator: invert the exact expected rates, regress, normalise
    lam_nf = np.stack([inv(rate(lv, k_true, f, p_d), theta, f, p_d) for lv in LEVELS])
    L_nf = lam_nf[:, n].mean(axis=1)
    g_nf = np.tensordot(L_nf, lam_nf, axes=(0, 0)) / np.sum(L_nf ** 2)
    g_nf = g_nf / g_nf[n].mean()

    # sampling error of each pixel's slope (renewal CLT for each level's spike fraction, delta method)
    L = np.array(report.flat_levels_e)
    se2 = np.zeros((H, W))
    for lv, Lk in zip(LEVELS, L):
        for kk in np.unique(k_true[n]):
            sel = n & (k_true == kk)
            pd, ff = float(np.median(p_d[sel])), float(np.median(f[sel]))
            m, v = theory.isi_moments(lv, kk, pd, ff)
            se_r = np.sqrt(v / m ** 3 / T_FLAT)
            lam_eff = lv * theta / kk
            h = 1e-3 * lam_eff
            drdl = (rate(lam_eff + h, theta, ff, pd) - rate(lam_eff - h, theta, ff, pd))[0] / (2 * h)
            se2[sel] += (Lk * se_r / drdl) ** 2
    se = np.sqrt(se2) / np.sum(L ** 2)  # slope through the origin: var = sum L^2 var(lam) / (sum L^2)^2
    z = np.abs(est.prnu_gain[n] - g_nf[n]) / se[n]
    assert z.max() < zb(n.sum()), z.max()

    # the method's systematic error: its noise-free result against the effective gain theta / ceil(theta / g)
    # (the identifiable quantity, since counts are multiplied by g). Requirement: below 0.1 % for every pixel.
    g_eff = theta / k_true
    g_eff = g_eff / g_eff[n].mean()
    assert np.abs(g_nf[n] - g_eff[n]).max() < 1e-3


def test_hot_pixel_charge_recovered_within_statistical_error(planted):
    true, est, _, dark = planted
    p_d = float(np.median(-np.expm1(-true.dark_rate[~true.hot_mask].astype(np.float64))))
    idx = list(zip(*np.nonzero(true.hot_mask)))
    for (i, j) in idx:
        mu, sg = float(true.hot_mu[i, j]), float(true.hot_sigma[i, j])
        isis = np.concatenate([np.diff(np.flatnonzero(d[:, i, j])) for d in dark])
        n = isis.size
        # sampling covariance of (mean, sd) of the ISIs (delta method, empirical 4th moment)
        m2 = isis.var()
        m4 = np.mean((isis - isis.mean()) ** 4)
        cov_ms = np.diag([m2 / n, (m4 - m2 ** 2) / (4 * m2 * n)])
        # Jacobian of (mean, sd) w.r.t. (mu, sigma) of the exact first-passage model, central differences
        def ms(a, b):
            mm, vv = theory.hot_pixel_isi_moments(a, b, p_d)
            return np.array([mm, np.sqrt(vv)])
        J = np.column_stack([(ms(mu * 1.02, sg) - ms(mu * 0.98, sg)) / (0.04 * mu),
                             (ms(mu, sg * 1.05) - ms(mu, sg * 0.95)) / (0.10 * sg)])
        Jinv = np.linalg.inv(J)
        cov = Jinv @ cov_ms @ Jinv.T
        zmu = abs(est.hot_mu[i, j] - mu) / np.sqrt(cov[0, 0])
        zsg = abs(est.hot_sigma[i, j] - sg) / np.sqrt(cov[1, 1])
        assert zmu < zb(2 * len(idx)) and zsg < zb(2 * len(idx)), (i, j, est.hot_mu[i, j], mu, zmu,
                                                                   est.hot_sigma[i, j], sg, zsg)


def test_calibration_errors_are_clear():
    true = sensor.SensorProfile.synthetic(4, 8, threshold_e=10)
    d = [np.zeros((10, 4, 8), bool)]
    d[0][0] = True  # a dark recording where every pixel fires once: dark spike fraction 0.1
    with pytest.raises(sensor.CalibrationError, match=">= 2 brightness levels"):
        calibrate(d, [np.zeros((10, 4, 8), bool)], base=true)
    dim = [np.zeros((n, 4, 8), bool) for n in (10, 12)]  # two levels (different lengths) below the dark rate
    for f in dim:
        f[1, 0, 1] = True
    with pytest.raises(sensor.CalibrationError, match="no flat-field level has a usable signal"):
        calibrate(d, dim, base=true)
    with pytest.raises(sensor.CalibrationError, match="base profile"):
        calibrate([np.zeros((10, 2, 8), bool)], [np.zeros((10, 2, 8), bool)] * 2, base=true)
