"""Closed-form and exact-numerical statistics of the spike models.

Used as oracles by the tests, by calibration (inverting observed spike rates),
and by reconstruction (dead-time-corrected TFP).

ELSSim renewal result (constant rate, non-hot pixel)
----------------------------------------------------
With reset to zero, every spike starts an independent inter-spike interval
(ISI). Let ``lam`` be the expected photoelectrons per interval, ``k`` the
photoelectrons needed to fire (``ceil(theta / g)``), ``f`` the refractory
fraction of the first interval after a spike, and ``p`` the per-interval
dark-event probability ``1 - exp(-mu_DC)``. After ``n >= 1`` intervals the
pixel has collected Poisson(``lam (n - f)``) photoelectrons, so

    S(n) = P(ISI > n) = Q(k, lam (n - f)) * (1 - p)^n,     S(0) = 1,

with ``Q(k, x) = P(Poisson(x) < k)`` the regularised upper incomplete gamma
function. The mean ISI is ``sum_{n>=0} S(n)`` and the long-run spike rate
(spikes per interval) is its reciprocal (:func:`renewal_spike_rate`;
:func:`invert_renewal_rate` inverts it per pixel).
"""

from __future__ import annotations

import functools

import numpy as np
from scipy import special

from sensor.errors import InputError

_POISSON_TAIL_SIGMAS = 9.0


def isi_survival(n, lam, k, p_dark=0.0, f=0.0):
    """S(n) = P(ISI > n) for integer n >= 0 (arrays broadcast)."""
    n = np.asarray(n, dtype=np.float64)
    lam = np.asarray(lam, dtype=np.float64)
    x = np.clip(lam * (n - f), 0.0, None)
    s = special.gammaincc(np.asarray(k, np.float64), x) * (1.0 - np.asarray(p_dark, np.float64)) ** n
    return np.where(n <= 0, 1.0, s)


def isi_cdf(n, lam, k, p_dark=0.0, f=0.0):
    """P(ISI <= n)."""
    return 1.0 - isi_survival(n, lam, k, p_dark, f)


def isi_pmf(n, lam, k, p_dark=0.0, f=0.0):
    """P(ISI = n), n >= 1."""
    n = np.asarray(n)
    return isi_survival(n - 1, lam, k, p_dark, f) - isi_survival(n, lam, k, p_dark, f)


def isi_moments(lam: float, k: float, p_dark: float = 0.0, f: float = 0.0, n_max: int | None = None):
    """Exact (mean, variance) of the ISI [intervals] by direct summation (scalar arguments).

    ``E[N] = sum_{n>=0} S(n)``, ``E[N^2] = sum_{n>=0} (2n + 1) S(n)``; the sum
    runs until ``S(n) < 1e-15``. Meant for test-sized parameters (mean ISI up
    to ~1e5 intervals).
    """
    lam, k, p, f = float(lam), float(k), float(p_dark), float(f)
    if n_max is None:
        n_max = int(np.ceil((k + _POISSON_TAIL_SIGMAS * np.sqrt(k) + 10) / max(lam, 1e-12) + 2))
        if p > 0:
            n_max = min(n_max, int(40 / p) + 2)
    n = np.arange(0, n_max + 1, dtype=np.float64)
    S = isi_survival(n, lam, k, p, f)
    m1 = S.sum()
    m2 = ((2 * n + 1) * S).sum()
    return float(m1), float(m2 - m1 * m1)


def renewal_density(pmf_first, pmf, T: int) -> np.ndarray:
    """u(n) = P(spike in interval n), n = 1..T, for a discrete renewal process.

    ``pmf_first[m]`` is P(first ISI = m) counted from the start of the stream
    (index 0 unused), ``pmf[m]`` P(ISI = m) between spikes. Solves
    ``u(n) = pmf_first(n) + sum_{m<n} u(m) pmf(n - m)``. The expected number of
    spikes in T intervals is ``u.sum()``: exact, including the start-up.
    """
    pf = np.zeros(T + 1)
    pf[:min(T + 1, len(pmf_first))] = np.asarray(pmf_first, np.float64)[:T + 1]
    pm = np.zeros(T + 1)
    pm[:min(T + 1, len(pmf))] = np.asarray(pmf, np.float64)[:T + 1]
    u = np.zeros(T + 1)
    support = np.flatnonzero(pm > 1e-300)
    for n in range(1, T + 1):
        sup = support[(support >= 1) & (support < n)]
        u[n] = pf[n] + np.dot(u[n - sup], pm[sup])
    return u[1:]


# ------------------------------------------------------------ rate <-> lambda, per pixel

def renewal_spike_rate(lam, k, refractory_fraction=0.0, p_dark=0.0, tol: float = 1e-13) -> np.ndarray:
    """Long-run spike rate [spikes/interval] of an ELSSim pixel under constant light (exact).

    With reset to zero every spike starts an independent inter-spike interval
    (ISI). After a spike the next interval collects ``lam (1 - f)`` expected
    photoelectrons (refractory period), later ones ``lam``; the pixel fires
    when it holds ``k = ceil(theta / g)`` photoelectrons, or on a dark event
    (probability ``p_dark`` per interval), at most once per interval. So

        S(n) = P(ISI > n) = Q(k, lam (n - f)) (1 - p_dark)^n,  S(0) = 1,

    with ``Q(k, x) = P(Poisson(x) < k)``, and by the renewal theorem the rate is
    ``1 / sum_{n >= 0} S(n)``. The sum runs until every term is below ``tol``.
    Hot-pixel charge is not part of this relation.

    Parameters
    ----------
    lam : array_like
        Expected photoelectrons per interval [e-/interval] (>= 0).
    k : array_like
        Photoelectrons needed to fire (integer-valued, >= 1).
    refractory_fraction : array_like
        ``f = refractory_s / interval_s`` (1/250 for the default sensor).
    p_dark : array_like
        Dark-event probability per interval, ``1 - exp(-mu_DC)``.

    Returns
    -------
    numpy.ndarray float64, the broadcast shape of the inputs (at least 1-D)
        Spikes per interval in [p_dark, 1].
    """
    from scipy import special
    lam, k, f, p = np.broadcast_arrays(*(np.asarray(a, np.float64) for a in (lam, k, refractory_fraction, p_dark)))
    out_shape = lam.shape if lam.ndim else (1,)
    lam, k, f, p = (a.reshape(-1) for a in (lam, k, f, p))
    total = np.ones(lam.shape, np.float64)  # the n = 0 term
    zero = lam <= 0
    # no light: only dark events fire, geometric ISI, rate exactly p
    total[zero] = np.where(p[zero] > 0, 1.0 / np.where(p[zero] > 0, p[zero], 1.0), np.inf)
    active = np.flatnonzero(~zero)
    n = 0
    chunk = 64
    logq = np.log1p(-np.clip(p, 0.0, 1.0 - 1e-16))
    while active.size:
        ns = np.arange(n + 1, n + chunk + 1, dtype=np.float64)[None, :]
        la, ka, fa = lam[active, None], k[active, None], f[active, None]
        terms = special.gammaincc(ka, np.clip(la * (ns - fa), 0.0, None)) * np.exp(ns * logq[active, None])
        total[active] += terms.sum(axis=1)
        # every factor of a term decreases with n: once the last term is below tol and the Poisson mean is past
        # k (so Q falls at least geometrically) or the dark factor decays geometrically, the tail is negligible
        past = (terms[:, -1] < tol) & ((la[:, 0] * (n + chunk - fa[:, 0]) > ka[:, 0]) | (p[active] > 0))
        active = active[~past]
        n += chunk
        chunk = min(chunk * 2, 65536)
    return (1.0 / total).reshape(out_shape)


_LAM_REL = np.concatenate([[0.0], np.geomspace(1e-3, 4.0, 320)])  # lambda / k grid of the rate tables


@functools.lru_cache(maxsize=1024)
def _rate_table(k: float, f: float, p_nodes: tuple) -> np.ndarray:
    """R[j, i]: renewal spike rate at ``lambda = k * _LAM_REL[j]`` and ``p_dark = p_nodes[i]`` (cached).

    The Poisson survival ``Q(k, lambda (n - f))`` does not depend on the dark
    probability, so it is computed once per lambda and combined with the
    dark factors ``(1 - p)^n`` of all grid values in one matrix product.
    """
    from scipy import special
    pg = np.asarray(p_nodes, np.float64)
    R = np.empty((_LAM_REL.size, pg.size))
    R[0] = pg  # no light: dark events only
    logq = np.log1p(-pg)
    n_tail = k + 12.0 * np.sqrt(k) + 12.0  # Poisson mean where Q(k, .) < 1e-25
    for j in range(1, _LAM_REL.size):
        lam = k * _LAM_REL[j]
        n_max = int(np.ceil(n_tail / lam + f)) + 1
        n = np.arange(1, n_max + 1, dtype=np.float64)
        S = special.gammaincc(k, np.clip(lam * (n - f), 0.0, None))
        mean_isi = 1.0 + np.exp(np.outer(logq, n)) @ S
        R[j] = 1.0 / mean_isi
    return R


def _k_grid(k_values: np.ndarray) -> np.ndarray:
    """Table nodes in k: the distinct values when few, else a geometric grid (1 % steps) spanning them."""
    uniq = np.unique(k_values)
    if uniq.size <= 32:
        return uniq
    lo, hi = float(uniq[0]), float(uniq[-1])
    n = int(np.ceil(np.log(hi / lo) / np.log(1.01))) + 1
    return np.unique(np.concatenate([np.geomspace(lo, hi, n), [lo, hi]]))


def _p_grid(p_values: np.ndarray) -> np.ndarray:
    """Table nodes in p_dark: a geometric grid (5 % steps) spanning the values, plus 0 when present; >= 2 nodes."""
    pos = p_values[p_values > 0]
    nodes = [0.0] if (pos.size < p_values.size) else []
    if pos.size:
        lo, hi = float(pos.min()), float(pos.max())
        n = int(np.ceil(np.log(hi / lo) / np.log(1.05))) + 1 if hi > lo else 1
        nodes.extend(np.geomspace(lo, hi, n).tolist() if n > 1 else [lo])
    nodes = np.unique(np.asarray(nodes, np.float64))
    if nodes.size == 1:
        nodes = np.array([nodes[0], nodes[0] * 1.05 + 1e-9])
    return nodes


def invert_renewal_rate(rate, k, refractory_fraction, p_dark) -> np.ndarray:
    """Photoelectron rate lambda [e-/interval] whose renewal spike rate equals ``rate`` (per pixel).

    Inverts :func:`renewal_spike_rate` (monotone increasing in lambda) with
    cached tables of the exact rate: 321 nodes in ``lambda / k`` (0, then
    1e-3 .. 4 log-spaced, ratio 1.027), nodes in ``p_dark`` (a 5 % geometric
    grid spanning the pixels' values, plus 0) and nodes in ``k`` (the distinct
    values when there are at most 32, else a 1 % geometric grid), interpolated
    linearly in ``p_dark`` and ``k`` and piecewise-linearly in lambda. Where
    the rate curve is smooth the interpolation error is < 1e-3 relative, below
    the statistical error of any practical window. For large ``k`` and
    ``lambda / k`` above about ``1 / sqrt(k)`` the ISI is nearly deterministic
    and the curve becomes a staircase (plateaus at 1/2, 1/3, ... spikes per
    interval): there the inverse is ill-conditioned whatever the method, and
    the table gives the interpolated value.
    Rates at or below the dark floor give 0; rates at or above the rate at
    ``lambda = 4 k`` (a pixel firing nearly every interval) give ``4 k``
    (saturated).

    Parameters
    ----------
    rate : array (...)
        Observed spikes per interval.
    k, refractory_fraction, p_dark : arrays broadcastable to ``rate``
        As in :func:`renewal_spike_rate`.

    Returns
    -------
    numpy.ndarray float64, shape of ``rate``
    """
    r, k, f, p = np.broadcast_arrays(*(np.asarray(a, np.float64) for a in (rate, k, refractory_fraction, p_dark)))
    shape = r.shape
    r, k, f, p = (np.ascontiguousarray(a).reshape(-1) for a in (r, k, f, p))
    if np.any(k < 1) or not np.all(np.isfinite(k)):
        raise InputError("k (photoelectrons to fire) must be finite and >= 1", field="k")
    out = np.zeros(r.size, np.float64)
    fr = np.round(f, 9)
    for ff in np.unique(fr):
        in_f = np.flatnonzero(fr == ff)
        kg = _k_grid(k[in_f])
        pg = _p_grid(p[in_f])
        pkey = tuple(pg.tolist())
        ia = np.clip(np.searchsorted(kg, k[in_f], side="right") - 1, 0, max(kg.size - 2, 0))
        for a in np.unique(ia):
            sel = in_f[ia == a]
            ka = kg[a]
            kb = kg[a + 1] if kg.size > 1 else ka
            wk = np.zeros(sel.size) if kb == ka else (k[sel] - ka) / (kb - ka)
            ps = np.clip(p[sel], pg[0], pg[-1])
            ip = np.clip(np.searchsorted(pg, ps, side="right") - 1, 0, pg.size - 2)
            wp = ((ps - pg[ip]) / (pg[ip + 1] - pg[ip]))[:, None]
            curves = 0.0
            for kk, w in ((ka, 1.0 - wk), (kb, wk)):
                R = _rate_table(float(kk), float(ff), pkey)
                curves = curves + w[:, None] * (R[:, ip].T * (1.0 - wp) + R[:, ip + 1].T * wp)
            rs = r[sel]
            j = (curves < rs[:, None]).sum(axis=1)  # first node with curve >= r
            res = np.zeros(sel.size)
            high = j >= _LAM_REL.size
            res[high] = _LAM_REL[-1]
            mid = np.flatnonzero((j > 0) & ~high)
            jm = j[mid]
            r0, r1 = curves[mid, jm - 1], curves[mid, jm]
            t = np.where(r1 > r0, (rs[mid] - r0) / np.where(r1 > r0, r1 - r0, 1.0), 0.0)
            res[mid] = _LAM_REL[jm - 1] + t * (_LAM_REL[jm] - _LAM_REL[jm - 1])
            out[sel] = res * k[sel]
    return out.reshape(shape)


# ------------------------------------------------------------------ hot pixels
def hot_pixel_isi_moments(mu, sigma, p_dark=0.0, n_bins: int = 200, tol: float = 1e-10, max_steps: int = 200_000):
    """Mean and variance of the ISI [intervals] of a hot pixel, computed exactly on a charge grid.

    Per interval the integrator (in threshold units, reset to 0) receives
    Normal(``mu``, ``sigma``^2), is clipped at 0, fires at >= 1; independently a
    dark event (probability ``p_dark``) fires it. The charge distribution is
    propagated on ``n_bins`` cells of [0, 1) plus an atom at 0 (the reset state)
    until the surviving mass is below ``tol``. No light is assumed (dark
    recordings).
    """
    mu, sigma = float(mu), max(float(sigma), 1e-4)
    from scipy.stats import norm
    edges = np.linspace(0.0, 1.0, n_bins + 1)
    centers = np.concatenate([[0.0], 0.5 * (edges[:-1] + edges[1:])])  # state 0 = atom at 0
    # transition from state i to cell j (cells 1..n_bins), and to the atom (clipped below 0)
    cdf = norm.cdf((edges[None, :] - centers[:, None] - mu) / sigma)  # (S, n_bins+1)
    A = np.zeros((centers.size, centers.size))
    A[:, 0] = cdf[:, 0]  # V + X < 0 -> clipped to 0
    A[:, 1:] = np.diff(cdf, axis=1)
    fire = 1.0 - cdf[:, -1]
    q = np.zeros(centers.size)
    q[0] = 1.0
    m1 = m2 = 0.0
    surv = 1.0
    n = 0
    keep = 1.0 - p_dark
    while surv > tol and n < max_steps:
        n += 1
        pf = q @ (p_dark + keep * fire)  # fire at step n
        q = keep * (q @ A)
        m1 += n * pf
        m2 += n * n * pf
        surv = q.sum()
    return m1, m2 - m1 * m1


def fit_hot_pixel(mean_isi_obs: float, var_isi_obs: float, p_dark: float = 0.0, moments=None):
    """Method-of-moments (mu_HP, sigma_HP) [threshold units / interval] from a hot pixel's dark ISIs.

    Solves ``moments(mu, sigma, p_dark) == (mean, var)`` by least squares in
    (log mu, log sigma); ``moments`` defaults to :func:`hot_pixel_isi_moments`
    (interval reset; the crossing reset's is
    :func:`sensor.calibration.theory.crossing_hot_pixel_isi_moments`). Returns (mu, sigma).
    """
    moments = moments or hot_pixel_isi_moments
    from scipy.optimize import least_squares
    m_obs, v_obs = float(mean_isi_obs), max(float(var_isi_obs), 1e-6)
    mu0 = 1.0 / max(m_obs - 0.5, 0.5)
    s0 = max(np.sqrt(v_obs * mu0 ** 3), 1e-3)

    def resid(x):
        m, v = moments(np.exp(x[0]), np.exp(x[1]), p_dark)
        return [(m - m_obs) / m_obs, (np.sqrt(max(v, 0.0)) - np.sqrt(v_obs)) / max(np.sqrt(v_obs), 0.05)]

    sol = least_squares(resid, x0=[np.log(mu0), np.log(s0)], bounds=([np.log(1e-4), np.log(1e-4)], [np.log(5.0), np.log(5.0)]),
                        x_scale=[0.1, 0.5], diff_step=1e-3)
    return float(np.exp(sol.x[0])), float(np.exp(sol.x[1]))


# ------------------------------------------------------------------------------------------------------------
# The crossing reset (profile.reset == "crossing"; docs/sensor.md, "The crossing reset")
#
# Continuous time t in intervals. Under constant light lam [photoelectrons/interval] a non-hot pixel fires at the
# k-th photoelectron after the end of its blind time f, or at the first dark event (rate mu per interval) after it;
# each firing resets it. So the firing times form a renewal process with inter-firing time
#
#     X = f + min(G, E),   G ~ Gamma(k, rate lam),   E ~ Exp(mu),
#     S_X(x) = P(X > x) = 1 (x < f),   Q(k, lam (x - f)) exp(-mu (x - f)) (x >= f).
#
# The read-out reports interval m when at least one firing falls in [m, m + 1). For a stationary renewal process the
# first firing after any fixed time comes after the forward recurrence time, P(B > 1) = (1/E X) int_1^inf S_X, so the
# read-out rate is  R = 1 - P(B > 1) = (1/E X) int_0^1 S_X(x) dx = E[min(X, 1)] / E[X]  (<= 1, and R -> 1/E[X] when
# firings never share an interval).
#
# With f = 0 and no dark events the count of photoelectrons is a Poisson process and the pixel fires each time it
# passes a multiple of k, so the phase r = (photoelectrons since the stream started) mod k, sampled at interval
# boundaries, is a Markov chain on {0..k-1}: r' = (r + D) mod k, D ~ Poisson(lam_m), and interval m reads 1 iff
# r + D >= k. Every read-out statistic (the exact start-up, time-varying input, read-out ISI law, its lag-1
# correlation, window-count Fano factors) follows by linear algebra on that chain (the functions below).

def crossing_inter_firing_mean(lam, k, f=0.0, mu=0.0) -> float:
    """E[X] [intervals] of the continuous-time inter-firing time (scalars): f + E[min(Gamma(k, lam), Exp(mu))].

    E[min(G, E)] = (1 - (lam / (lam + mu))^k) / mu  (the probability that the dark event comes first over mu),
    k / lam without dark events.
    """
    lam, k, f, mu = float(lam), float(k), float(f), float(mu)
    if mu <= 0:
        return f + (k / lam if lam > 0 else np.inf)
    return f + (1.0 - (lam / (lam + mu)) ** k) / mu


def crossing_firing_survival(x, lam, k, f=0.0, mu=0.0):
    """S_X(x) = P(X > x) of the continuous-time inter-firing time (x [intervals], arrays broadcast)."""
    x = np.asarray(x, np.float64)
    y = np.clip(x - f, 0.0, None)
    s = special.gammaincc(float(k), lam * y) * np.exp(-mu * y) if lam > 0 else np.exp(-mu * y)
    return np.where(x < f, 1.0, s)


def crossing_rates(lam, k, f=0.0, mu=0.0):
    """(continuous firing rate, read-out spike rate) [per interval] of a stationary crossing-reset pixel (scalars).

    Continuous: ``1 / E[X]``. Read-out: ``E[min(X, 1)] / E[X]`` with
    ``E[min(X, 1)] = int_0^1 S_X`` (renewal theory, see the section comment);
    closed form without dark events, ``E[min(G, a)] = (k/lam) P(Gamma(k+1) <= lam a) + a Q(k, lam a)``,
    ``a = 1 - f``; adaptive quadrature otherwise.
    """
    lam, k, f, mu = float(lam), float(k), float(f), float(mu)
    ex = crossing_inter_firing_mean(lam, k, f, mu)
    a = max(1.0 - f, 0.0)
    if mu <= 0:
        emin = (k / lam) * special.gammainc(k + 1.0, lam * a) + a * special.gammaincc(k, lam * a) if lam > 0 else a
    else:
        from scipy.integrate import quad
        emin = quad(lambda y: float(crossing_firing_survival(y + f, lam, k, f, mu)), 0.0, a, epsabs=1e-13,
                    epsrel=1e-11, limit=200)[0]
    return 1.0 / ex, (min(f, 1.0) + emin) / ex


def _poisson_mod_k(lam: float, k: int):
    """P(D = d) of D ~ Poisson(lam) folded by (quotient, remainder): returns (pmf (d_max+1,), d_max)."""
    d_max = int(np.ceil(lam + 12.0 * np.sqrt(lam + 1.0) + 12.0))
    d = np.arange(d_max + 1)
    from scipy import stats
    return stats.poisson.pmf(d, lam), d_max


def crossing_phase_chain(lam: float, k: int):
    """Transition matrices (A0, A1), each (k, k), of the phase chain (f = 0, no dark events).

    ``A0[r, r']``: the interval reads 0 and the phase goes r -> r'; ``A1``: it reads 1.
    ``A0 + A1`` is stochastic (doubly stochastic: the stationary phase is uniform).
    """
    k = int(k)
    pmf, d_max = _poisson_mod_k(float(lam), k)
    A0 = np.zeros((k, k))
    A1 = np.zeros((k, k))
    for r in range(k):
        tot = r + np.arange(d_max + 1)
        dest = tot % k
        fire = tot >= k
        np.add.at(A0[r], dest[~fire], pmf[~fire])
        np.add.at(A1[r], dest[fire], pmf[fire])
    return A0, A1


def crossing_readout_probability(lam_m, k: int) -> np.ndarray:
    """P(interval m reads 1), m = 0..T-1, for any per-interval light ``lam_m`` (T,) (f = 0, no dark; exact).

    The stream starts reset (phase 0). Works for time-varying (keyframed) input:
    the phase distribution is propagated through each interval's chain.
    """
    k = int(k)
    lam_m = np.asarray(lam_m, np.float64)
    out = np.empty(lam_m.size)
    q = np.zeros(k)
    q[0] = 1.0
    cache = {}
    for m, lam in enumerate(lam_m):
        key = float(lam)
        if key not in cache:
            cache[key] = crossing_phase_chain(key, k)
        A0, A1 = cache[key]
        q1 = q @ A1
        out[m] = q1.sum()
        q = q @ A0 + q1
    return out


def crossing_readout_isi_stats(lam: float, k: int):
    """Read-out ISI law of a stationary crossing-reset pixel (f = 0, no dark): (mean, variance, lag-1 correlation).

    After a read-out spike the phase has law ``nu ∝ pi A1`` (pi uniform); the next
    spike comes n intervals later with probability ``nu A0^(n-1) A1 1``. With
    ``M = (I - A0)^-1``: ``E[N] = nu M^2 A1 1``, ``E[N^2] = nu (I + A0) M^3 A1 1``, and
    consecutive ISIs share the phase between them, ``E[N1 N2] = nu (M^2 A1)^2 1``
    (nu is stationary for the spike-embedded chain). The continuous-time ISIs are
    independent; the negative correlation is the read-out's: a firing late in its
    interval makes this read-out ISI long and the next one short.
    """
    A0, A1 = crossing_phase_chain(lam, k)
    kk = A0.shape[0]
    nu = np.full(kk, 1.0 / kk) @ A1
    nu /= nu.sum()
    I = np.eye(kk)
    M = np.linalg.inv(I - A0)
    G = M @ M @ A1  # sum_n n A0^(n-1) A1
    one = np.ones(kk)
    m1 = nu @ G @ one
    m2 = nu @ (I + A0) @ M @ M @ M @ A1 @ one
    m12 = nu @ G @ G @ one
    var = m2 - m1 * m1
    return float(m1), float(var), float((m12 - m1 * m1) / var)


def crossing_readout_isi_pmf(n, lam: float, k: int, after_spikes: int | None = None) -> np.ndarray:
    """P(read-out ISI = n), n >= 1 (f = 0, no dark): ``nu A0^(n-1) A1 1``.

    ``after_spikes=None``: the stationary ISI (``nu ∝ pi A1``). An integer j: the
    ISI between read-out spikes j and j + 1 of a stream that starts reset
    (phase 0); the phase after spike j has law ``delta_0 (M A1)^j``, with
    ``M = (I - A0)^-1`` (the spike-embedded chain). One such ISI per pixel gives
    independent samples of an exactly known law (consecutive ISIs are not
    independent under the crossing reset).
    """
    n = np.asarray(n, np.int64)
    A0, A1 = crossing_phase_chain(lam, k)
    kk = A0.shape[0]
    if after_spikes is None:
        nu = np.full(kk, 1.0 / kk) @ A1
    else:
        P = np.linalg.solve(np.eye(kk) - A0, A1)
        nu = np.zeros(kk)
        nu[0] = 1.0
        for _ in range(int(after_spikes)):
            nu = nu @ P
    nu = nu / nu.sum()
    out = np.zeros(int(n.max()) + 1)
    a1 = A1.sum(axis=1)
    v = nu.copy()
    for j in range(1, out.size):
        out[j] = v @ a1
        v = v @ A0
    return out[n]


def crossing_window_count_moments(lam: float, k: int, window: int):
    """(mean, variance) of the read-out spike count in ``window`` consecutive intervals (stationary; f = 0, no dark).

    Generating function ``E[z^C] = pi (A0 + z A1)^W 1``: its first two derivatives at
    z = 1 by the recursion ``u' <- u' A + u A1``, ``u'' <- u'' A + 2 u' A1``. The
    Fano factor is ``variance / mean``.
    """
    A0, A1 = crossing_phase_chain(lam, k)
    A = A0 + A1
    kk = A.shape[0]
    u = np.full(kk, 1.0 / kk)
    d1 = np.zeros(kk)
    d2 = np.zeros(kk)
    for _ in range(int(window)):
        d2 = d2 @ A + 2.0 * d1 @ A1
        d1 = d1 @ A + u @ A1
        u = u @ A
    m1, f2 = d1.sum(), d2.sum()
    return float(m1), float(f2 + m1 - m1 * m1)
