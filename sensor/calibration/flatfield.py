"""Flat-field analysis for calibration: reset test, exact rate inversion, PRNU, threshold and sensitivity.

Inputs are per-level statistics of flat recordings (:func:`flat_level_stats`);
:func:`fit_flats` turns them into the estimates with standard errors. The
derivations are in ``docs/sensor.md`` ("Absolute calibration") and the exact
laws in :mod:`sensor.calibration.theory`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import optimize, special, stats

from sensor.calibration import theory as ct
from sensor.errors import CalibrationError
from sensor.analysis.theory import renewal_spike_rate

#: a level informs the PRNU map only where its expected spike count error is at least this many spikes
#: (below it the read-out is deterministic, e.g. on a plateau of the interval reset's staircase, and the
#: delta-method variance of the inverted rate is not valid)
MIN_COUNT_SD = 1.0
#: interval reset: a (level, pixel) informs PRNU and threshold only where the shot-noise spread of the crossing time,
#: sqrt(k) / lam intervals, is at least this: below it the read-out ISI takes one or two values and the rate is a
#: staircase in light (flat on the plateaus, a jump at the steps), so neither the inversion nor its delta-method
#: variance can be trusted
MIN_SPREAD_INTERVAL = 0.3
#: the photon-transfer root is searched within this factor of the base threshold
SEARCH_FACTOR = 10.0
#: relative standard error above which the threshold is reported as weakly identified
WEAK_THRESHOLD = 0.2
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

    @property
    def isi_rate(self) -> np.ndarray:
        """(P,) spikes per interval as 1 / mean ISI: ``(N - 1) / (t_last - t_first)``.

        Unbiased for the stationary rate of a renewal process started at a spike
        (``N / T`` is low by about half a spike: the recording starts with the
        pixel reset); ``N / T`` where a pixel has fewer than two spikes.
        """
        c = self.counts
        has = c >= 2
        if not has.any():
            return c / self.T
        first = self.times[np.where(has, self.starts, 0)]
        last = self.times[np.where(has, self.starts + c - 1, 0)]
        span = np.where(has, last - first, 1)
        return np.where(has & (span > 0), (c - 1) / np.maximum(span, 1), c / self.T)

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
    shape = r.shape
    k, p, f, r = (np.ascontiguousarray(a).reshape(-1) for a in (k, p, f, r))  # any shape in, the same shape out
    ok = (r > p) & (r < 1)
    target = 1.0 / np.where(ok, r, 0.5)
    # start: mean ISI ~ k / lam + 1/2 + f (the read-out rounds the crossing time up), then Newton on the exact mean
    lam = np.where(ok, k / np.maximum(target - 0.5 - f, 0.25), 0.0).astype(np.float64)
    act = np.flatnonzero(ok)
    for _ in range(12):  # Newton on the pixels not yet converged (mean and its derivative in one call)
        if not act.size:
            break
        lo = lam[act]
        mm = ct.interval_isi_moments(np.concatenate([lo, lo * 1.001]), np.tile(k[act], 2), np.tile(p[act], 2),
                                     np.tile(f[act], 2))[0]
        m0, m1 = mm[:act.size], mm[act.size:]
        d = (m1 - m0) / (lo * 0.001)
        step = np.where(d < 0, (target[act] - m0) / np.where(d < 0, d, -1.0), 0.0)
        new = np.clip(lo + step, lo * 0.7, lo * 1.3)
        lam[act] = new
        act = act[np.abs(new - lo) > 1e-9 * lo]
    return (lam / k).reshape(shape)


def readout_moments(reset, x, k, mu, f):
    """(mean, variance) of the read-out ISI unit [intervals]: i.i.d. ISIs (interval) or ``U`` (crossing)."""
    if reset == "crossing":
        return ct.crossing_readout_unit(x * k, k, mu, f)
    return ct.interval_isi_moments(x * k, k, -np.expm1(-mu), f)


def light_variance(reset, x, k, mu, f, T, rate=None):
    """Delta-method variance of the inverted light ``x`` from a ``T``-interval recording, and the count sd.

    The read-out count over ``T`` intervals has variance ``T Var(U) / E[U]^3``
    (renewal CLT) plus a bounded boundary term (1/6 spike^2, the phase of the
    window ends); ``Var(x) = Var(rate) / (d rate / d x)^2``. Returns (variance,
    count sd [spikes], d x / d mu_DC): the last propagates the dark-rate
    estimate's error, which all levels of a pixel share.

    A pixel without light (``x <= 1e-9``: no spike at this level) carries no information: infinite variance,
    count sd 0 (its exact moments would need ~1 / x terms: a dim, short flat must not stall the fit).
    """
    x, k, mu, f = np.broadcast_arrays(*(np.asarray(a, np.float64) for a in (x, k, mu, f)))
    dark = x <= 1e-9
    if dark.any():
        var = np.full(x.shape, np.inf)
        sd = np.zeros(x.shape)
        dxm = np.zeros(x.shape)
        lit = ~dark
        if lit.any():
            r = None if rate is None else np.broadcast_to(np.asarray(rate, np.float64), x.shape)[lit]
            var[lit], sd[lit], dxm[lit] = light_variance(reset, x[lit], k[lit], mu[lit], f[lit], T, r)
        return var, sd, dxm
    m, v = readout_moments(reset, x, k, mu, f)
    var_n = T * v / m ** 3 + 1.0 / 6.0
    h = np.maximum(1e-3 * x, 1e-9)
    d = (spike_rate(reset, x + h, k, mu, f) - spike_rate(reset, np.maximum(x - h, 0), k, mu, f)) / (
        x + h - np.maximum(x - h, 0))
    with np.errstate(divide="ignore", invalid="ignore"):
        var_x = var_n / T ** 2 / d ** 2
    dx = np.zeros(np.shape(var_x))
    if rate is not None:
        # the inversion uses the pixel's estimated dark rate, whose error is shared by all levels: its derivative
        e = np.maximum(0.02 * mu, 1e-9)
        dx = (invert_rate(reset, rate, k, mu + e, f) - invert_rate(reset, rate, k, np.maximum(mu - e, 0), f)) / (
            mu + e - np.maximum(mu - e, 0))
    sd_n = np.sqrt(T * v / m ** 3)
    if reset == "interval":
        sd_n = np.where(np.sqrt(k) / np.maximum(x * k, 1e-12) >= MIN_SPREAD_INTERVAL, sd_n, 0.0)
    return np.where(d > 0, var_x, np.inf), sd_n, dx


# ----------------------------------------------------------------------------------------------------- reset
def decide_reset(levels, normal, x_levels, theta, gain, mu, f, use=None):
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
    interval reset alone). Levels where ``use`` (bool per level) is False (saturated, or no signal: their
    ISIs say nothing of the reset) are left out.
    """
    mflat = normal.reshape(-1)
    per_level = []
    zs = []
    ll_i = ll_c = 0.0
    for i, (lv, x) in enumerate(zip(levels, x_levels)):
        if use is not None and not use[i]:
            per_level.append(dict(rho=None, n_pairs=0, z=None, rho_crossing=None, skipped=True))
            continue
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
def fit_gain(x, var_x, normal, dx_dmu=None, var_mu=None, iterations: int = 20):
    """Weighted rank-1 fit ``x[l, i] = X_l g_i`` (weights ``1 / var_x``), gains normalised to mean 1.

    The paper's regression of each pixel's rate on the level mean, with each
    (level, pixel) weighted by the information it carries and the level means
    fitted from the informative pixels only. The standard error adds the error
    of the pixel's dark rate (``var_mu``), shared by all its levels through
    ``dx_dmu`` (K, P). Returns (gain (P,), se (P,), X (K,)).
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
    safe = np.where(info > 0, info, 1)
    var = 1.0 / safe
    if dx_dmu is not None and var_mu is not None:
        var = var + ((w * X[:, None] * np.nan_to_num(dx_dmu)).sum(axis=0) / safe) ** 2 * var_mu
    se = np.where(info > 0, np.sqrt(var), np.inf)
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
    if reset == "interval":
        obs, nb = lv.block_variance(1)
        return obs, 1, nb
    k = theta_pilot / gain
    v = readout_moments(reset, x, k, mu, f)[1]
    n = max(1, int(np.ceil(0.5 / float(np.median(v[normal])))))
    v1, nb1 = lv.block_variance(n)
    v4, nb4 = lv.block_variance(4 * n)
    # E[V_n] = n Var(U) + c N_b / (N_b - 1) (ddof=1 with the telescoped total; c the bounded phase term): remove
    # the small difference of the c terms with c estimated from the intercept (4 V_n - V_4n) / 3, pooled
    with np.errstate(invalid="ignore", divide="ignore"):
        a1, a4 = nb1 / (nb1 - 1.0), nb4 / (nb4 - 1.0)
        good = normal & (nb4 >= 4)
        c = float(np.nanmean(((4 * v1 - v4) / 3)[good])) if good.any() else 1.0 / 6.0
        obs = np.where(nb4 >= 4, (v4 - v1 - c * (a4 - a1)) / (3 * n), np.nan)
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
        terms.append(dict(level=l, idx=idx, obs=obs[idx], rate=lv.isi_rate[idx], g=gain[idx], mu=mu[idx],
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
        # the sum increases with theta (less shot variance predicted, c_l > 0): walk from the pilot in factors of
        # 2 towards the sign change (at most SEARCH_FACTOR away), then Brent on the bracket
        a = lt0
        fa = total(a, ts)
        step = np.log(2.0) * (1 if fa < 0 else -1)
        b = a
        while True:
            b = a + step
            if abs(b - lt0) > np.log(SEARCH_FACTOR) + 1e-9:
                return None, None
            fb = total(b, ts)
            if np.sign(fb) != np.sign(fa):
                break
            a, fa = b, fb
        lt = optimize.brentq(lambda v: total(v, ts), min(a, b), max(a, b), xtol=2e-4)
        acc = np.zeros(P)
        for t in ts:
            acc[t["idx"]] += t["c"] * ratio(t, lt)  # a pixel's terms over levels are summed: they share mu, g
        dpsi = (total(lt + h, ts) - total(lt - h, ts)) / (2 * h)
        return float(np.exp(lt)), float(np.exp(lt) * np.sqrt(np.sum(acc ** 2)) / abs(dpsi))

    theta, se = solve(terms)
    if theta is None:
        say(f"warning: the threshold is not identifiable from these flats (no root of the photon-transfer equation "
            f"within a factor {SEARCH_FACTOR:g} of {theta_pilot:.0f} e-, {reset} reset); keeping the base threshold")
        return dict(threshold_e=None, threshold_se=None, threshold_levels=[],
                    threshold_note="not identifiable from these flats")
    per_level = []
    for t in terms:
        th_l, se_l = solve([t])
        per_level.append(dict(level=t["level"], theta_e=th_l, se_e=se_l, block_isis=t["n"],
                              pixels=int(t["idx"].size)))
    say(f"threshold: {theta:.0f} +- {se:.0f} e- ({reset} reset, {len(terms)} levels)")
    note = _threshold_note(theta, se, "the delta-method error is only a guide; record longer or dimmer flats "
                           "(interval reset) or brighter ones (crossing reset)", say)
    return dict(threshold_e=theta, threshold_se=se, threshold_levels=per_level, threshold_note=note)


def _threshold_note(theta: float, se: float, advice: str, say) -> str:
    """'ok', or (with a warning through ``say``) why a threshold estimate [e-] of standard error ``se`` is weak."""
    if se <= WEAK_THRESHOLD * theta:
        return "ok"
    note = f"weakly identified (standard error {100 * se / theta:.0f} %): {advice}"
    say("warning: threshold " + note)
    return note


def interval_isi_logpmf(n_max, lam, k, p_dark, f):
    """log P(ISI = n), n = 1..n_max, per pixel (P, n_max), interval reset: ``S(n - 1) - S(n)``."""
    n = np.arange(0, n_max + 1, dtype=np.float64)[None, :]
    S = special.gammaincc(k[:, None], np.clip(lam[:, None] * (n - f[:, None]), 0, None)) * \
        np.exp(n * np.log1p(-np.clip(p_dark, 0, 1 - 1e-16))[:, None])
    S[:, 0] = 1.0
    pmf = S[:, :-1] - S[:, 1:]
    with np.errstate(divide="ignore"):
        return np.log(np.clip(pmf, 1e-300, None))


def fit_threshold_interval_ml(levels, normal, x_levels, gain, mu, f, theta_pilot, informative=None,
                              say=lambda m: None):
    """Threshold theta [e-] under the interval reset by maximum likelihood on the whole ISI law.

    Under the interval reset read-out ISIs are i.i.d. with the exact pmf
    ``P(n) = S(n - 1) - S(n)``, ``S(n) = Q(k, lam (n - f)) (1 - p)^n``. For a
    trial theta each pixel gets ``k_i = theta / g_i`` and the light that
    reproduces its observed rate (so, as in photon transfer, only the *shape*
    of the ISI law at the observed mean carries information on k: its shot-noise
    width ``sqrt(k) / lam`` against the dark events' geometric tail, which the
    variance alone cannot separate). The log-likelihood summed over pixels and
    informative levels is maximised in log theta; standard error: the sandwich
    ``sqrt(sum_i s_i^2) / |d^2 logL / d log theta^2|`` with per-pixel scores
    ``s_i`` (pixels independent).
    """
    from scipy import optimize as opt
    nf = normal.reshape(-1)
    P = nf.size
    terms = []
    for l, (lv, x) in enumerate(zip(levels, x_levels)):
        ok = nf & np.isfinite(x) & (x > 0) & (lv.counts >= 3)
        if informative is not None:
            ok &= informative[l]
        if ok.sum() < 10:
            continue
        pid = np.repeat(np.arange(P), lv.counts)
        d = np.diff(lv.times)
        same = pid[1:] == pid[:-1]
        d, dp = d[same], pid[1:][same]
        sel = ok[dp]
        d, dp = d[sel], dp[sel]
        idx = np.flatnonzero(ok)
        row = np.full(P, -1)
        row[idx] = np.arange(idx.size)
        n_max = int(d.max())
        H = np.bincount(row[dp] * n_max + (d - 1), minlength=idx.size * n_max).reshape(idx.size, n_max)
        terms.append(dict(level=l, idx=idx, H=H, n_max=n_max, rate=lv.isi_rate[idx], g=gain[idx],
                          mu=mu[idx], f=f[idx]))
    if not terms:
        return None
    cache = {}

    def pix_ll(t, lam, k):
        lp = interval_isi_logpmf(t["n_max"], lam, k, -np.expm1(-t["mu"]), t["f"])
        return (t["H"] * lp).sum(axis=1)

    def loglik_pix(lt):
        # profile likelihood: each pixel's light maximises its own likelihood (Newton in log lam from the
        # rate-inverted start); pinning the light to the noisy observed rate would bias theta low, since a
        # misplaced ISI peak is best explained by a wider (lower-k) law
        key = round(float(lt), 12)
        if key not in cache:
            acc = np.zeros(P)
            for t in terms:
                k = np.exp(lt) / t["g"]
                if "lam" in t:  # warm start: at a fixed mean ISI the light scales with k
                    lam = t["lam"] * np.exp(lt - t["lt"])
                else:
                    lam = np.maximum(invert_rate("interval", t["rate"], k, t["mu"], t["f"]) * k, 1e-9)
                e = 1e-3
                for _ in range(6):
                    a, b, c = pix_ll(t, lam * np.exp(-e), k), pix_ll(t, lam, k), pix_ll(t, lam * np.exp(e), k)
                    d1, d2 = (c - a) / (2 * e), (c - 2 * b + a) / e ** 2
                    step = np.clip(np.where(d2 < 0, -d1 / np.where(d2 < 0, d2, -1.0), 0.0), -0.1, 0.1)
                    lam = lam * np.exp(step)
                    if np.abs(step).max() < 1e-6:
                        break
                t["lam"], t["lt"] = lam, lt
                acc[t["idx"]] += pix_ll(t, lam, k)
            cache[key] = acc
        return cache[key]

    lt0 = np.log(theta_pilot)
    span = np.log(SEARCH_FACTOR)
    res = opt.minimize_scalar(lambda v: -loglik_pix(v).sum(), bounds=(lt0 - span, lt0 + span), method="bounded",
                              options=dict(xatol=3e-4))
    lt = float(res.x)
    if abs(lt - lt0) > span - 1e-3:
        say(f"warning: the threshold is not identifiable from these flats (the likelihood peaks at the edge of "
            f"the search, a factor {SEARCH_FACTOR:g} from {theta_pilot:.0f} e-); keeping the base threshold")
        return dict(threshold_e=None, threshold_se=None, threshold_levels=[],
                    threshold_note="not identifiable from these flats")
    h = 0.01
    lp, l0, lm = loglik_pix(lt + h), loglik_pix(lt), loglik_pix(lt - h)
    score = (lp - lm) / (2 * h)
    curv = (lp.sum() - 2 * l0.sum() + lm.sum()) / h ** 2
    theta = float(np.exp(lt))
    se = float(theta * np.sqrt(np.sum(score ** 2)) / abs(curv)) if curv < 0 else float("inf")
    say(f"threshold: {theta:.0f} +- {se:.0f} e- (interval reset, maximum likelihood, {len(terms)} levels)")
    note = _threshold_note(theta, se, "record longer flats at levels where the ISI spreads over several intervals",
                           say)
    per_level = [dict(level=t["level"], theta_e=None, se_e=None, block_isis=1, pixels=int(t["idx"].size))
                 for t in terms]
    return dict(threshold_e=theta, threshold_se=se, threshold_levels=per_level, threshold_note=note,
                threshold_method="maximum likelihood (interval reset)")


def _threshold(reset, levels, normal, x, gain, mu, f, theta, informative, say):
    if reset == "interval":
        return fit_threshold_interval_ml(levels, normal, x, gain, mu, f, theta, informative=informative, say=say)
    return fit_threshold(reset, levels, normal, x, gain, mu, f, theta, informative=informative, say=say)


# -------------------------------------------------------------------------------------------------- driver
def fit_flats(levels, normal, mu_dc, f_ref, theta_base, median_p, *, var_mu=None, reset=None, flat_lux=None,
              say=lambda m: None, passes: int = 2, dark_current_rate=None, dark_current_rate_var=None):
    """Reset, per-pixel light, PRNU gain, threshold and (with ``flat_lux``) sensitivity from flat levels.

    ``reset``: None to decide it from the data, or ``"interval"`` / ``"crossing"``
    to impose it. Returns a dict of maps and numbers (see :func:`sensor.calibration.estimate.calibrate`).

    Dark current as charge (``dark == "current"``): pass ``mu_dc`` zero and ``dark_current_rate``, each pixel's
    dark read-out rate [spikes/interval] (with its variance ``dark_current_rate_var``). A flat's rate then
    comes from ``lambda + d``: the reset test and the threshold use the inverted total ``(lambda + d) / k``,
    while the PRNU fit and the sensitivity use the light alone, the total minus the dark rate inverted through
    the same law at the same ``k`` (``x_dark = d / k``, returned as ``dark_x``; its error is shared by the
    pixel's levels and enters the gain's standard error).
    """
    shape = normal.shape
    nf = normal.reshape(-1)
    mu = mu_dc.reshape(-1).astype(np.float64)
    var_mu = None if var_mu is None else np.broadcast_to(var_mu, shape).reshape(-1)
    f = np.broadcast_to(f_ref, shape).reshape(-1).astype(np.float64)
    K = len(levels)
    rates = np.stack([lv.isi_rate for lv in levels])
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
    dcr = None if dark_current_rate is None else np.broadcast_to(dark_current_rate, shape).reshape(-1)

    def minus_dark(x, reset_, k):
        """The light alone [thresholds per interval]: total minus the dark current's share (current mode)."""
        if dcr is None:
            return x, None
        xd = invert_rate(reset_, dcr, k, np.zeros_like(k), f)
        return x - xd[None, :], xd

    for it in range(passes):
        r_use = decided or "crossing"  # the first pass needs some relation; the reset test does not depend on it
        k = theta / gain
        x = np.stack([invert_rate(r_use, rates[l], k, mu, f) for l in range(K)])
        var_x = np.full(x.shape, np.inf)
        count_sd = np.zeros(x.shape)
        for l in range(K):
            if signal[l]:
                var_x[l], count_sd[l], _ = light_variance(r_use, np.maximum(x[l], 1e-9), k, mu, f, levels[l].T)
        var_x = np.where(count_sd >= MIN_COUNT_SD, var_x, np.inf)
        gain, gain_se, X = fit_gain(minus_dark(x, r_use, k)[0], var_x, nf)
        if reset is None and it == 0:
            rt = decide_reset(levels, nf, list(x), theta, gain, mu, f, use=signal)
            out.update(rt)
            decided = rt["reset"] or "interval"
            if rt["reset"] is None:
                say("warning: too few ISIs to test the reset; assuming the interval reset")
            say(f"reset: {decided} (combined z {rt['reset_z']}, confidence {rt['reset_confidence']:.4f})")
            continue
        thr = _threshold(decided, levels, normal, list(x), gain, mu, f, theta, count_sd >= MIN_COUNT_SD, say)
        if thr is not None and thr["threshold_e"] is not None:
            theta = thr["threshold_e"]
    # final pass with the fitted theta
    k = theta / gain
    x = np.stack([invert_rate(decided, rates[l], k, mu, f) for l in range(K)])
    var_x = np.full(x.shape, np.inf)
    count_sd = np.zeros(x.shape)
    dx_dmu = np.zeros(x.shape)
    for l in range(K):
        if signal[l]:
            var_x[l], count_sd[l], dx_dmu[l] = light_variance(decided, np.maximum(x[l], 1e-9), k, mu, f,
                                                              levels[l].T, rates[l])
    informative = count_sd >= MIN_COUNT_SD
    var_x = np.where(informative, var_x, np.inf)
    x_tot = x
    x, x_dark = minus_dark(x, decided, k)
    if x_dark is not None:
        # the dark share's error, shared by the pixel's levels: dx / d(rate_dark) = -dx_dark / d(rate_dark)
        if dark_current_rate_var is not None:
            e = np.maximum(1e-4 * dcr, 1e-12)
            dxd = (invert_rate(decided, dcr + e, k, np.zeros_like(k), f)
                   - invert_rate(decided, np.maximum(dcr - e, 0.0), k, np.zeros_like(k), f)) / (2 * e)
            dx_dmu = np.broadcast_to(-dxd, x.shape)
            var_mu = np.broadcast_to(dark_current_rate_var, shape).reshape(-1)
        else:
            dx_dmu = var_mu = None
    gain, gain_se, X = fit_gain(x, var_x, nf, dx_dmu, var_mu)
    if x_dark is not None and dx_dmu is not None:
        # for the dark current's error budget: the gain's error from the flats alone, and dg / d(dark rate)
        _, se_flat, _ = fit_gain(x, var_x, nf)
        wg = np.where(np.isfinite(var_x) & (var_x > 0), 1.0 / np.where(var_x > 0, var_x, 1.0), 0.0)
        wg[:, ~nf] = 0.0
        info_g = (wg * X[:, None] ** 2).sum(axis=0)
        coeff = (wg * X[:, None] * dx_dmu).sum(axis=0) / np.where(info_g > 0, info_g, 1.0)
        out.update(gain_se_flat=se_flat.reshape(shape), gain_dark_coeff=coeff.reshape(shape))
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
               level_reason=why, level_mean_rate=[float(r) for r in mean_rate],
               level_informative_pixel_fraction=[float(informative[l, nf].mean()) for l in range(K)])
    g_spread = float(gain[nf].std())
    med_se = float(np.median(gain_se[nf]))
    out["prnu_enough"] = bool(med_se < 0.25 * max(g_spread, 1e-12))
    if not out["prnu_enough"]:
        say(f"warning: the flats are not enough for the PRNU map: median standard error {med_se:.4f} against a "
            f"spread of {g_spread:.4f}; record longer flats at levels where the read-out is not deterministic")
    if x_dark is not None:
        out["dark_x"] = x_dark.reshape(shape)
    if thr is None and reset is not None:
        thr = _threshold(decided, levels, normal, list(x_tot), gain, mu, f, theta, informative, say)
    if thr is not None:
        out.update(thr)
    if flat_lux is not None:
        lux = np.asarray(flat_lux, np.float64)
        th = out.get("threshold_e") or theta
        th_se = out.get("threshold_se") or 0.0
        wl = w * lux[:, None] ** 2
        den = wl.sum(axis=0)
        s_pix = np.where(den > 0, th * (w * lux[:, None] * np.nan_to_num(x)).sum(axis=0) / np.where(den > 0, den, 1),
                         np.nan)
        se_stat = np.where(den > 0, th / np.sqrt(np.where(den > 0, den, 1)), np.inf)
        se_pix = np.sqrt(se_stat ** 2 + (s_pix * th_se / th) ** 2)
        s_mean = float(np.nanmean(s_pix[nf]))
        se_mean = float(np.sqrt((s_mean * th_se / th) ** 2 + np.mean(se_stat[nf] ** 2) / nf.sum()))
        if out.get("threshold_e") is None:
            out["sensitivity_note"] = ("scaled by the base threshold (the threshold was not identified): only "
                                       "relative to it")
        out.update(sensitivity_e_per_lux=s_mean, sensitivity_se=se_mean,
                   sensitivity_map=s_pix.reshape(shape), sensitivity_se_map=se_pix.reshape(shape))
    return out
