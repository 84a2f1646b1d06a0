"""Flat-field analysis for calibration: reset test, exact rate inversion, PRNU, threshold and sensitivity.

Inputs are per-level statistics of flat recordings (:func:`flat_level_stats`);
:func:`fit_flats` turns them into the estimates with standard errors. The
derivations are in ``docs/sensor.md`` ("Absolute calibration") and the exact
laws in :mod:`sensor.calib_theory`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import optimize, stats

from . import calib_theory as ct
from .errors import CalibrationError
from .theory import renewal_spike_rate

RESETS = ("interval", "crossing")
#: a level informs the PRNU map only where its expected spike count error is at least this many spikes
#: (below it the read-out is deterministic, e.g. on a plateau of the interval reset's staircase, and the
#: delta-method variance of the inverted rate is not valid)
MIN_COUNT_SD = 1.0
#: interval reset: a (level, pixel) informs PRNU and threshold only where the shot-noise spread of the crossing time,
#: sqrt(k) / lam intervals, is at least this: below it the read-out ISI takes one or two values and the rate is a
#: staircase in light (flat on the plateaus, a jump at the steps), so neither the inversion nor its delta-method
#: variance can be trusted
MIN_SPREAD_INTERVAL = 0.3
#: |z| for the reset decision's test of the interval reset (one-sided)
RESET_Z = 3.9


@dataclass
class FlatLevel:
    """Spike statistics of one flat recording (T intervals, P = H * W pixels)."""

    T: int
    shape: tuple
    rate: np.ndarray  # (H, W) spikes per interval
    times: np.ndarray  # spike interval indices, sorted by pixel then time
    starts: np.ndarray  # (P,) index of each pixel's first spike in ``times``
    counts: np.ndarray  # (P,) spikes per pixel

    def block_variance(self, n: int):
        """Per pixel (variance ddof=1, number of blocks) of sums of ``n`` consecutive read-out ISIs."""
        nb = np.maximum((self.counts - 1) // n, 0)
        P = self.counts.size
        pid = np.repeat(np.arange(P), nb)
        j = np.arange(pid.size) - np.repeat(np.cumsum(nb) - nb, nb)
        a = self.starts[pid] + j * n
        S = (self.times[a + n] - self.times[a]).astype(np.float64)
        s1 = np.bincount(pid, S, P)
        s2 = np.bincount(pid, S * S, P)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = s1 / nb
            var = (s2 - nb * mean ** 2) / (nb - 1)
        return np.where(nb >= 3, var, np.nan), nb

    def lag1(self, mask_flat):
        """Pooled lag-1 correlation of read-out ISIs over the pixels in ``mask_flat`` (P,) bool.

        Returns (rho, n_pairs, n_pixels): ISIs are centred by each pixel's mean,
        ``rho = sum c_j c_{j+1} / sum c_j^2`` over all pixels.
        """
        P = self.counts.size
        keep = mask_flat & (self.counts >= 4)
        pid = np.repeat(np.arange(P), self.counts)
        d = np.diff(self.times).astype(np.float64)
        same = pid[1:] == pid[:-1]
        d, dp = d[same], pid[1:][same]
        sel = keep[dp]
        d, dp = d[sel], dp[sel]
        n_isi = np.bincount(dp, minlength=P)
        mean = np.bincount(dp, d, P) / np.maximum(n_isi, 1)
        c = d - mean[dp]
        pair = dp[1:] == dp[:-1]
        num = float(np.sum((c[1:] * c[:-1])[pair]))
        den = float(np.sum(c * c))
        return num / den if den > 0 else 0.0, int(pair.sum()), int(keep.sum())


def flat_level_stats(spikes: np.ndarray) -> FlatLevel:
    """Statistics of one flat recording, bool (T, H, W)."""
    T = spikes.shape[0]
    flat = spikes.reshape(T, -1)
    pix, t = np.nonzero(flat.T)
    P = flat.shape[1]
    counts = np.bincount(pix, minlength=P)
    starts = np.cumsum(counts) - counts
    return FlatLevel(T=T, shape=spikes.shape[1:], rate=counts.reshape(spikes.shape[1:]) / T,
                     times=t.astype(np.int64), starts=starts, counts=counts)


# --------------------------------------------------------------------------------- rate <-> light, per reset
def spike_rate(reset, x, k, mu, f):
    """Read-out spike rate for light ``x`` [thresholds per interval, lam / k] of a pixel needing ``k`` e-."""
    if reset == "crossing":
        return ct.crossing_spike_rate(x * k, k, mu, f)
    return renewal_spike_rate(x * k, k, f, -np.expm1(-mu))


def invert_rate(reset, rate, k, mu, f):
    """Light ``x = lam / k`` [thresholds per interval] whose read-out rate is ``rate`` (per pixel)."""
    if reset == "crossing":
        return ct.invert_crossing_rate(rate, k, mu, f) / k
    p = -np.expm1(-mu)
    r = np.asarray(rate, np.float64)
    k, p, f, r = np.broadcast_arrays(np.asarray(k, np.float64), p, np.asarray(f, np.float64), r)
    ok = (r > p) & (r < 1)
    target = 1.0 / np.where(ok, r, 0.5)
    # start: mean ISI ~ k / lam + 1/2 + f (the read-out rounds the crossing time up), then Newton on the exact mean
    lam = np.where(ok, k / np.maximum(target - 0.5 - f, 0.25), 0.0)
    for _ in range(10):
        lo = np.where(ok, lam, 1.0)
        m0 = ct.interval_isi_moments(lo, k, p, f)[0]
        m1 = ct.interval_isi_moments(lo * 1.001, k, p, f)[0]
        d = (m1 - m0) / (lo * 0.001)
        step = np.where(d < 0, (target - m0) / np.where(d < 0, d, -1.0), 0.0)
        lam = np.where(ok, np.clip(lo + step, lo * 0.7, lo * 1.3), 0.0)
    return lam / k


def readout_moments(reset, x, k, mu, f):
    """(mean, variance) of the read-out ISI unit [intervals]: i.i.d. ISIs (interval) or ``U`` (crossing)."""
    if reset == "crossing":
        return ct.crossing_readout_unit(x * k, k, mu, f)
    return ct.interval_isi_moments(x * k, k, -np.expm1(-mu), f)


def light_variance(reset, x, k, mu, f, T, rate=None, var_mu=None):
    """Delta-method variance of the inverted light ``x`` from a ``T``-interval recording, and the count sd.

    The read-out count over ``T`` intervals has variance ``T Var(U) / E[U]^3``
    (renewal CLT) plus a bounded boundary term (1/6 spike^2, the phase of the
    window ends); ``Var(x) = Var(rate) / (d rate / d x)^2``.
    """
    m, v = readout_moments(reset, x, k, mu, f)
    var_n = T * v / m ** 3 + 1.0 / 6.0
    h = np.maximum(1e-3 * x, 1e-9)
    d = (spike_rate(reset, x + h, k, mu, f) - spike_rate(reset, np.maximum(x - h, 0), k, mu, f)) / (
        x + h - np.maximum(x - h, 0))
    with np.errstate(divide="ignore", invalid="ignore"):
        var_x = var_n / T ** 2 / d ** 2
    if rate is not None and var_mu is not None:
        # the inversion uses the pixel's estimated dark rate: propagate its error (shared by all levels)
        e = np.maximum(0.02 * mu, 1e-9)
        dx = (invert_rate(reset, rate, k, mu + e, f) - invert_rate(reset, rate, k, np.maximum(mu - e, 0), f)) / (
            mu + e - np.maximum(mu - e, 0))
        var_x = var_x + dx ** 2 * var_mu
    sd_n = np.sqrt(T * v / m ** 3)
    if reset == "interval":
        sd_n = np.where(np.sqrt(k) / np.maximum(x * k, 1e-12) >= MIN_SPREAD_INTERVAL, sd_n, 0.0)
    return np.where(d > 0, var_x, np.inf), sd_n


# ----------------------------------------------------------------------------------------------------- reset
def test_reset(levels, normal, x_levels, theta, gain, mu, f):
    """Reset decision from the lag-1 correlation of read-out ISIs.

    Interval reset: ISIs are i.i.d. (a discrete renewal process), so the pooled
    lag-1 correlation is 0 up to the mean-removal bias ``-P / N`` (P pixels, N
    ISIs) with standard error ``1 / sqrt(N_pairs)``: the statistic ``z =
    (rho + P/N) sqrt(N_pairs)`` is N(0, 1) per level and the levels combine by
    Stouffer's rule. Crossing reset: the shared phase makes neighbouring ISIs
    anti-correlated, ``rho = -(1/12) / (Var(U) + 1/6)`` where the phase is
    mixed (``Var(U) >= 0.3``). Decision: crossing when the combined ``z <
    -RESET_Z``. Confidence: the posterior probability of the decision with equal
    priors from the Gaussian likelihoods of the two predictions on the mixed
    levels (where neither prediction is reliable, the one-sided p-value of the
    interval reset alone).
    """
    mflat = normal.reshape(-1)
    per_level = []
    zs, ws = [], []
    ll_i = ll_c = 0.0
    for lv, x in zip(levels, x_levels):
        rho, npairs, npix = lv.lag1(mflat)
        if npairs < 10:
            per_level.append(dict(rho=rho, n_pairs=npairs, z=None, rho_crossing=None))
            continue
        n_isi = npairs + npix
        se = 1.0 / np.sqrt(npairs)
        z = (rho + npix / n_isi) / se
        k = theta / gain[normal]
        _, vu = ct.crossing_readout_unit(x[normal] * k, k, mu[normal], f[normal])
        vu = float(np.median(vu))
        rc = float(ct.crossing_lag1_correlation(vu)) if vu >= 0.3 else None
        if rc is not None:
            ll_i += -0.5 * z ** 2
            ll_c += -0.5 * ((rho - rc) / se) ** 2
        per_level.append(dict(rho=rho, n_pairs=npairs, z=float(z), rho_crossing=rc))
        zs.append(z)
        ws.append(1.0)
    if not zs:
        return dict(reset=None, reset_z=None, reset_p_interval=None, reset_confidence=0.0, reset_levels=per_level)
    zc = float(np.sum(zs) / np.sqrt(len(zs)))
    p_int = float(stats.norm.cdf(zc))
    decision = "crossing" if zc < -RESET_Z else "interval"
    if ll_i != 0.0 or ll_c != 0.0:
        d = np.clip(ll_c - ll_i, -700, 700)
        post_c = 1.0 / (1.0 + np.exp(-d))
        conf = post_c if decision == "crossing" else 1.0 - post_c
    else:
        conf = 1.0 - p_int if decision == "crossing" else p_int
    return dict(reset=decision, reset_z=zc, reset_p_interval=p_int, reset_confidence=float(conf),
                reset_levels=per_level)


# -------------------------------------------------------------------------------------------------- PRNU
def fit_gain(x, var_x, normal, iterations: int = 20):
    """Weighted rank-1 fit ``x[l, i] = X_l g_i`` (weights ``1 / var_x``), gains normalised to mean 1.

    The paper's regression of each pixel's rate on the level mean, with each
    (level, pixel) weighted by the information it carries and the level means
    fitted from the informative pixels only. Returns (gain (P,), se (P,), X (K,)).
    """
    w = np.where(np.isfinite(var_x) & (var_x > 0), 1.0 / np.where(var_x > 0, var_x, 1.0), 0.0)
    w[:, ~normal] = 0.0
    xx = np.nan_to_num(x)
    g = np.ones(x.shape[1])
    X = np.zeros(x.shape[0])
    for _ in range(iterations):
        den = (w * g[None, :] ** 2).sum(axis=1)
        X = np.where(den > 0, (w * g[None, :] * xx).sum(axis=1) / np.where(den > 0, den, 1), 0.0)
        dg = (w * X[:, None] ** 2).sum(axis=0)
        g = np.where(dg > 0, (w * X[:, None] * xx).sum(axis=0) / np.where(dg > 0, dg, 1), 1.0)
        c = g[normal].mean()
        g, X = g / c, X * c
    info = (w * X[:, None] ** 2).sum(axis=0)
    se = np.where(info > 0, 1.0 / np.sqrt(np.where(info > 0, info, 1)), np.inf)
    return g, se, X


# ------------------------------------------------------------------------------------------------ threshold
def _threshold_terms(reset, lv, normal, x, gain, mu, f, theta_pilot):
    """Per-pixel observed statistic and block length for the photon-transfer fit of one level.

    Interval reset: the sample variance of the i.i.d. ISIs (n = 1), expectation
    ``Var(D)``. Crossing reset: the variance-time slope ``(V_{4n} - V_n) / (3n)``
    of block sums of ``n`` and ``4n`` read-out ISIs, expectation ``Var(U)``:
    the bounded phase terms (1/6 quantisation and the merge-phase covariance)
    cancel, since they no longer depend on the block length once ``n Var(U) >=
    0.5``.
    """
    P = normal.size
    k = theta_pilot / gain
    m, v = readout_moments(reset, x, k, mu, f)
    if reset == "interval":
        obs, nb = lv.block_variance(1)
        return obs, 1, nb
    n = max(1, int(np.ceil(0.5 / float(np.median(v[normal])))))
    v1, nb1 = lv.block_variance(n)
    v4, nb4 = lv.block_variance(4 * n)
    obs = np.where(nb4 >= 4, (v4 - v1) / (3 * n), np.nan)
    return obs, n, nb4


def fit_threshold(reset, levels, normal, x_levels, gain, mu, f, theta_pilot, informative=None,
                  say=lambda m: None):
    """Threshold theta [e-] by photon transfer: the shot-noise part of the ISI variance is ``(E[G])^2 / k``.

    For each level and pixel the observed ISI statistic ``s_il`` (see
    :func:`_threshold_terms`) has expectation ``M_il(theta)``, the exact
    read-out variance for ``k_i = theta / g_i`` and light ``lam = x_il k_i``
    (dark events, refractory time and merges included). theta solves the
    estimating equation ``sum_i psi_i = 0``, ``psi_i = sum_l c_l (s_il /
    M_il(theta) - 1)``, with level weights ``c_l = D_l / V_l`` (``D_l`` the mean
    sensitivity of the ratio to log theta, ``V_l`` its variance over pixels).
    Standard error: the sandwich ``sqrt(sum psi_i^2) / |sum d psi_i / d log
    theta|`` over independent pixels, in log theta. With mean PRNU gain 1 by
    convention, this estimates ``theta = 1 / mean(1 / k_i)``.
    """
    P = normal.size
    nf = normal.reshape(-1)
    terms = []
    for l, (lv, x) in enumerate(zip(levels, x_levels)):
        obs, n, nb = _threshold_terms(reset, lv, nf, x, gain, mu, f, theta_pilot)
        ok = nf & np.isfinite(obs) & np.isfinite(x) & (x > 0)
        if informative is not None:
            ok &= informative[l]
        if ok.sum() < 10:
            continue
        idx = np.flatnonzero(ok)
        terms.append(dict(level=l, idx=idx, obs=obs[idx], rate=lv.rate.reshape(-1)[idx], g=gain[idx], mu=mu[idx],
                          f=f[idx], n=n))
    if not terms:
        return None

    cache = {}

    def model(t, log_theta):
        # the observed rate pins the mean ISI: for each theta the light is re-inverted, so the fit uses the
        # variance *given* the mean (on a plateau of the interval reset's staircase this carries no information)
        key = (t["level"], round(float(log_theta), 12))
        if key not in cache:
            k = np.exp(log_theta) / t["g"]
            x = invert_rate(reset, t["rate"], k, t["mu"], t["f"])
            cache[key] = readout_moments(reset, np.maximum(x, 1e-12), k, t["mu"], t["f"])[1]
        return cache[key]

    def ratio(t, lt):
        return t["obs"] / model(t, lt) - 1

    h = 2e-3
    lt0 = np.log(theta_pilot)
    for t in terms:
        r = ratio(t, lt0)
        dr = (ratio(t, lt0 + h) - ratio(t, lt0 - h)) / (2 * h)
        t["c"] = float(np.mean(dr) / max(np.var(r), 1e-300))
        t["D"] = float(np.mean(dr))

    def total(lt, ts):
        return float(sum(t["c"] * np.sum(ratio(t, lt)) for t in ts))

    def solve(ts):
        # bracket on a coarse grid of log theta, then Brent on the bracketing cell
        grid = lt0 + np.linspace(-np.log(4), np.log(4), 9)
        vals = [total(g, ts) for g in grid]
        sgn = np.sign(vals)
        cells = np.flatnonzero(sgn[:-1] != sgn[1:])
        if not cells.size:
            return None, None
        c = cells[0]
        lt = optimize.brentq(lambda v: total(v, ts), grid[c], grid[c + 1], xtol=2e-4)
        acc = np.zeros(P)
        for t in ts:
            acc[t["idx"]] += t["c"] * ratio(t, lt)  # a pixel's terms over levels are summed: they share mu, g
        dpsi = (total(lt + h, ts) - total(lt - h, ts)) / (2 * h)
        return float(np.exp(lt)), float(np.exp(lt) * np.sqrt(np.sum(acc ** 2)) / abs(dpsi))

    theta, se = solve(terms)
    if theta is None:
        raise CalibrationError("the photon-transfer estimating equation has no root for theta within a factor 4 "
                               f"of {theta_pilot:.0f} e-: the flat ISIs do not follow the {reset} reset's "
                               "shot-noise law", field="--flat")
    per_level = []
    for t in terms:
        th_l, se_l = solve([t])
        per_level.append(dict(level=t["level"], theta_e=th_l, se_e=se_l, block_isis=t["n"],
                              pixels=int(t["idx"].size)))
    say(f"threshold: {theta:.0f} +- {se:.0f} e- ({reset} reset, {len(terms)} levels)")
    return dict(threshold_e=theta, threshold_se=se, threshold_levels=per_level)


# -------------------------------------------------------------------------------------------------- driver
def fit_flats(levels, normal, mu_dc, f_ref, theta_base, median_p, *, var_mu=None, reset=None, flat_lux=None,
              say=lambda m: None, passes: int = 2):
    """Reset, per-pixel light, PRNU gain, threshold and (with ``flat_lux``) sensitivity from flat levels.

    ``reset``: None to decide it from the data, or ``"interval"`` / ``"crossing"``
    to impose it. Returns a dict of maps and numbers (see :func:`sensor.calibration.calibrate`).
    """
    shape = normal.shape
    nf = normal.reshape(-1)
    mu = mu_dc.reshape(-1).astype(np.float64)
    var_mu = None if var_mu is None else np.broadcast_to(var_mu, shape).reshape(-1)
    f = np.broadcast_to(f_ref, shape).reshape(-1).astype(np.float64)
    K = len(levels)
    rates = np.stack([lv.rate.reshape(-1) for lv in levels])
    mean_rate = rates[:, nf].mean(axis=1)
    signal = (mean_rate > 2 * max(median_p, 1e-6)) & (mean_rate < 0.9)
    if not signal.any():
        raise CalibrationError("no flat-field level has a usable signal (mean spike rate must be above twice the "
                               f"dark rate {2 * median_p:.2e} and below 0.9 spikes per interval); record brighter "
                               "or dimmer flats", field="--flat")
    theta = float(theta_base)
    gain = np.ones(nf.size)
    decided = reset
    out = {}
    thr = None
    for it in range(passes):
        r_use = decided or "crossing"  # the first pass needs some relation; the reset test does not depend on it
        k = theta / gain
        x = np.stack([invert_rate(r_use, rates[l], k, mu, f) for l in range(K)])
        var_x = np.full(x.shape, np.inf)
        count_sd = np.zeros(x.shape)
        for l in range(K):
            if signal[l]:
                var_x[l], count_sd[l] = light_variance(r_use, np.maximum(x[l], 1e-9), k, mu, f, levels[l].T)
        var_x = np.where(count_sd >= MIN_COUNT_SD, var_x, np.inf)
        gain, gain_se, X = fit_gain(x, var_x, nf)
        if reset is None and it == 0:
            rt = test_reset(levels, nf, list(x), theta, gain, mu, f)
            out.update(rt)
            decided = rt["reset"] or "interval"
            if rt["reset"] is None:
                say("warning: too few ISIs to test the reset; assuming the interval reset")
            say(f"reset: {decided} (combined z {rt['reset_z']}, confidence {rt['reset_confidence']:.4f})")
            continue
        thr = fit_threshold(decided, levels, normal, list(x), gain, mu, f, theta, informative=count_sd >= MIN_COUNT_SD,
                            say=say)
        if thr is not None:
            theta = thr["threshold_e"]
    # final pass with the fitted theta
    k = theta / gain
    x = np.stack([invert_rate(decided, rates[l], k, mu, f) for l in range(K)])
    var_x = np.full(x.shape, np.inf)
    count_sd = np.zeros(x.shape)
    for l in range(K):
        if signal[l]:
            var_x[l], count_sd[l] = light_variance(decided, np.maximum(x[l], 1e-9), k, mu, f, levels[l].T,
                                                   rates[l], var_mu)
    informative = count_sd >= MIN_COUNT_SD
    var_x = np.where(informative, var_x, np.inf)
    gain, gain_se, X = fit_gain(x, var_x, nf)
    w = np.where(np.isfinite(var_x), 1.0 / np.where(np.isfinite(var_x), var_x, 1), 0.0)
    w[:, ~nf] = 0
    info = (w * X[:, None] ** 2)[:, nf].sum(axis=1)
    share = info / max(info.sum(), 1e-300)
    used = share > 1e-3
    why = []
    for l in range(K):
        if not signal[l]:
            why.append("no signal" if mean_rate[l] <= 2 * median_p else "saturated (mean rate >= 0.9)")
        elif informative[l, nf].mean() < 0.5:
            why.append(f"read-out nearly deterministic for {100 * (1 - informative[l, nf].mean()):.0f} % of pixels "
                       "(a plateau of the rate-vs-light staircase): little information")
        elif not used[l]:
            why.append("information share below 0.1 %")
        else:
            why.append("used")
    out.update(reset=decided, gain=gain.reshape(shape), gain_se=gain_se.reshape(shape), x=x,
               level_light_thresholds=[float(v) for v in X], level_light_e=[float(v * theta) for v in X],
               level_information_share=[float(s) for s in share], level_used=[bool(u) for u in used],
               level_reason=why, level_informative_pixel_fraction=[float(informative[l, nf].mean()) for l in range(K)])
    g_spread = float(gain[nf].std())
    med_se = float(np.median(gain_se[nf]))
    out["prnu_enough"] = bool(med_se < 0.25 * max(g_spread, 1e-12))
    if not out["prnu_enough"]:
        say(f"warning: the flats are not enough for the PRNU map: median standard error {med_se:.4f} against a "
            f"spread of {g_spread:.4f}; record longer flats at levels where the read-out is not deterministic")
    if thr is None and reset is not None:
        thr = fit_threshold(decided, levels, normal, list(x), gain, mu, f, theta, informative=informative, say=say)
    if thr is not None:
        out.update(thr)
    if flat_lux is not None:
        lux = np.asarray(flat_lux, np.float64)
        th = out.get("threshold_e", theta)
        th_se = out.get("threshold_se", 0.0)
        wl = w * lux[:, None] ** 2
        den = wl.sum(axis=0)
        s_pix = np.where(den > 0, th * (w * lux[:, None] * np.nan_to_num(x)).sum(axis=0) / np.where(den > 0, den, 1),
                         np.nan)
        se_stat = np.where(den > 0, th / np.sqrt(np.where(den > 0, den, 1)), np.inf)
        se_pix = np.sqrt(se_stat ** 2 + (s_pix * th_se / th) ** 2)
        s_mean = float(np.nanmean(s_pix[nf]))
        se_mean = float(np.sqrt((s_mean * th_se / th) ** 2 + np.mean(se_stat[nf] ** 2) / nf.sum()))
        out.update(sensitivity_e_per_lux=s_mean, sensitivity_se=se_mean,
                   sensitivity_map=s_pix.reshape(shape), sensitivity_se_map=se_pix.reshape(shape))
    return out
