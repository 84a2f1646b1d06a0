"""Classic reconstruction: TFP / TFI against hand-computed cases, the dead-time-corrected TFP against simulation."""

import numpy as np
import pytest

from recon.classic import (invert_renewal_rate, renewal_spike_rate, tfi, tfp, tfp_deadtime, tfp_windows,
                           window_bounds)
from sensor import InputError, SensorProfile, simulate


def _stream(T, times):
    s = np.zeros((T, 1, 1), bool)
    s[list(times), 0, 0] = True
    return s


def test_tfp_hand_cases():
    s = _stream(10, [1, 4, 5, 9])
    assert tfp(s)[0, 0] == pytest.approx(4 / 10)
    # window 4 centred at 5 -> intervals 3..6 hold spikes at 4 and 5
    assert tfp(s, window=4, center=5)[0, 0] == pytest.approx(2 / 4)
    # window shifted inside the stream at the edge: [0, 4) holds 1 spike
    assert window_bounds(10, 4, 0) == (0, 4)
    assert tfp(s, window=4, center=0)[0, 0] == pytest.approx(1 / 4)
    assert window_bounds(10, 4, 9) == (6, 10)
    with pytest.raises(InputError):
        tfp(s, window=0)


def test_tfp_windows_hand_case():
    s = _stream(12, [0, 1, 5, 11])
    w = tfp_windows(s, n_windows=3, window=4)
    np.testing.assert_allclose(w[:, 0, 0], [2 / 4, 1 / 4, 1 / 4])
    # centred block of 2 windows of 3 in 12 intervals: [3, 9) -> spike at 5 in the first window
    np.testing.assert_allclose(tfp_windows(s, 2, 3)[:, 0, 0], [1 / 3, 0.0])
    with pytest.raises(InputError, match="need at least"):
        tfp_windows(s, 10, 32)


def test_tfi_hand_cases():
    s = _stream(12, [2, 7, 9])
    assert tfi(s, center=4)[0, 0] == pytest.approx(1 / 5)  # 2 .. 7
    assert tfi(s, center=7)[0, 0] == pytest.approx(1 / 2)  # spike at the centre counts as previous: 7 .. 9
    assert tfi(s, center=8)[0, 0] == pytest.approx(1 / 2)
    # before the first spike: t_prev = -1 -> ISI = 2 - (-1) = 3
    assert tfi(s, center=1)[0, 0] == pytest.approx(1 / 3)
    # after the last spike: t_next = T = 12 -> ISI = 12 - 9 = 3
    assert tfi(s, center=10)[0, 0] == pytest.approx(1 / 3)
    assert tfi(_stream(12, []), center=5)[0, 0] == pytest.approx(1 / 13)
    two = np.concatenate([_stream(12, [2, 7, 9]), _stream(12, [0, 11])], axis=2)
    np.testing.assert_allclose(tfi(two, center=4)[0], [1 / 5, 1 / 11])


def test_renewal_rate_limits():
    # k = 1, f = 0: fire in an interval with prob 1 - exp(-lam): geometric ISI with that p
    lam = 0.3
    assert renewal_spike_rate(lam, 1, 0.0, 0.0)[0] == pytest.approx(1 - np.exp(-lam), rel=1e-10)
    # dark only: rate = p exactly
    assert renewal_spike_rate(0.0, 50, 0.004, 0.01)[0] == pytest.approx(0.01)
    assert renewal_spike_rate(1e4, 50, 0.004, 0.0)[0] == pytest.approx(1.0)


def test_invert_renewal_rate_round_trip():
    k = np.array([1, 3, 17, 200, 2000, 1999, 2100], float)
    lam = k * np.array([0.05, 0.2, 0.01, 0.004, 0.003, 0.005, 0.01])
    p = np.array([0.0, 0.001, 0.002, 0.0047, 0.003, 0.0, 0.01])
    r = renewal_spike_rate(lam, k, 1 / 250, p)
    est = invert_renewal_rate(r, k, 1 / 250, p)
    np.testing.assert_allclose(est, lam, rtol=1e-3)
    # at or below the dark floor -> 0
    assert invert_renewal_rate(0.001, 200, 1 / 250, 0.002) == 0.0


def test_renewal_rate_matches_direct_summation_of_the_isi_law():
    from sensor.analysis import theory  # isi_moments sums S(n) term by term: an independent route to the same number
    lam = np.array([2.0, 20.0, 120.0])
    direct = [1.0 / theory.isi_moments(x, 200, 0.001, 0.004)[0] for x in lam]
    np.testing.assert_allclose(renewal_spike_rate(lam, 200, 0.004, 0.001), direct, rtol=1e-7)


def test_tfp_deadtime_unbiased_on_constant_input(z):
    """Constant lambda on a 32x32 sensor with PRNU and dark events, elssim model.

    Statistics: each pixel's estimate lam_i has the same expectation; their
    spread gives the standard error of the mean, SE = std(lam_i) / sqrt(N).
    Systematic terms, each bounded relative to lambda by ~1/count with count the
    spikes per pixel (~330 here): (a) the stream starts from zero charge, not in
    the stationary regime, which shifts the expected count by at most about one
    spike (after the 200 dropped intervals, less); (b) the inverse of the rate
    curve is smooth, so its Jensen term is O(var(r)/r^2) = O(1/count).
    Tolerance = z * SE + 2 * lambda / count. Plain TFP * theta is shown to miss
    by more than that (refractory loss, discarded excess charge, dark spikes).
    """
    prof = SensorProfile.synthetic(32, 32, threshold_e=200.0, prnu_sigma=0.05, dark_rate=0.004, seed=1)
    _check_unbiased(prof, 8.0, 8200, z)


def _check_unbiased(prof, lam_true, n_intervals, z):
    """tfp_deadtime within z * SE + 2 lam / count of lam_true at constant light; plain TFP * theta > 3x that off."""
    s = simulate(np.full((n_intervals, 32, 32), lam_true, np.float32), prof, "elssim", seed=3)[200:]
    est = tfp_deadtime(s, prof).astype(np.float64)
    count = s.sum(axis=0).mean()
    se = est.std(ddof=1) / np.sqrt(est.size)
    tol = z * se + 2.0 * lam_true / count
    assert abs(est.mean() - lam_true) < tol, (est.mean(), tol)
    naive = (tfp(s) * prof.threshold_e).mean()
    assert abs(naive - lam_true) > 3 * tol


def test_tfp_deadtime_shape_check():
    prof = SensorProfile.synthetic(4, 4, threshold_e=10.0)
    with pytest.raises(InputError, match="profile"):
        tfp_deadtime(np.zeros((10, 4, 5), bool), prof)


def test_tfp_deadtime_unbiased_for_the_crossing_reset(z):
    """Constant light on a crossing-reset sensor (the vidar-default reset) with PRNU and dark events.

    The inversion uses ``sensor.analysis.theory.crossing_rates`` (tabulated in lam / k at the median k and interpolated
    between dark rates). Statistics as in the interval-reset test above: SE from the spread of the per-pixel
    estimates, plus 2 lam / count for the start-up and Jensen terms. Plain TFP * theta misses by far more
    (dark spikes, refractory loss).
    """
    prof = SensorProfile.synthetic(32, 32, threshold_e=2000.0, prnu_sigma=0.05, dark_rate=0.01, dark_rate_spread=0.3,
                                   reset="crossing", seed=1)
    _check_unbiased(prof, 400.0, 4200, z)
