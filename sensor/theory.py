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
(spikes per interval) is its reciprocal.
"""

from __future__ import annotations

import numpy as np
from scipy import special

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


def mean_isi(lam, k, p_dark=0.0, f=0.0, max_terms: int = 4000) -> np.ndarray:
    """Mean ISI [intervals] of a constant-rate ELSSim pixel (scalar ``k``, ``p_dark``, ``f``; ``lam`` array).

    ``sum_{n>=0} S(n)``: the sum runs exactly over the geometric head (where the
    Poisson term is 1 to double precision) and over the transition window
    ``lam n in k +- 9 sqrt(k)``; when that window is longer than ``max_terms``
    the smooth summand is integrated with the trapezoid rule on ``max_terms``
    nodes (relative error far below 1e-6 in that regime).
    """
    lam = np.atleast_1d(np.asarray(lam, dtype=np.float64))
    k = float(k)
    p = float(p_dark)
    out = np.empty_like(lam)
    q = 1.0 - p
    width = _POISSON_TAIL_SIGMAS * np.sqrt(k) + 10.0
    n_cap = np.inf if p <= 0 else 40.0 / p  # (1-p)^n < 4e-18 beyond
    for i, L in enumerate(lam):
        if L <= 0:
            out[i] = np.inf if p <= 0 else 1.0 / p
            continue
        n_lo = max(1.0, np.floor((k - width) / L + f))
        n_hi = min(np.ceil((k + width) / L + f) + 1, n_cap)
        head = n_lo if p <= 0 else (1.0 - q ** n_lo) / p  # sum_{n=0}^{n_lo-1} q^n
        if n_hi <= n_lo:
            out[i] = head
            continue
        span = n_hi - n_lo + 1
        if span <= max_terms:
            n = np.arange(n_lo, n_hi + 1)
            out[i] = head + isi_survival(n, L, k, p, f).sum()
        else:
            n = np.linspace(n_lo, n_hi, max_terms)
            y = isi_survival(n, L, k, p, f)
            h = n[1] - n[0]
            # sum over integers ~ trapezoid integral + half the end values (Euler-Maclaurin)
            out[i] = head + np.trapezoid(y, n) + 0.5 * (y[0] + y[-1]) + (h * 0.0)
    return out


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


def spike_rate(lam, k, p_dark=0.0, f=0.0) -> np.ndarray:
    """Long-run spikes per interval of a constant-rate ELSSim pixel: 1 / mean ISI."""
    return 1.0 / mean_isi(lam, k, p_dark, f)


class RateInverter:
    """Invert the ELSSim renewal relation: observed spikes per interval -> lam [e-/interval].

    A table of the mean ISI over a log-spaced ``lam`` grid (and a grid of dark
    probabilities) is computed once for a given ``k`` and ``f``; inversion is
    then vectorised interpolation (monotone in ``lam``). Rates at or below the
    dark-only rate give 0; rates above the table give ``nan``.

    Parameters
    ----------
    k : float
        Photoelectrons to fire (``ceil(theta / g)``; use theta for a gain-1 pixel).
    f : float
        Refractory fraction of the interval after a spike.
    p_dark_max : float
        Largest dark probability to tabulate (grid of ``n_dark`` values from 0).
    lam_range : (float, float)
        Range of lam [e-/interval] tabulated.
    """

    def __init__(self, k: float, f: float = 0.0, p_dark_max: float = 0.0, lam_range=None, n_lam: int = 400,
                 n_dark: int = 33):
        self.k, self.f = float(k), float(f)
        lo, hi = lam_range if lam_range is not None else (self.k * 1e-5, self.k * 2.0)
        self.lam = np.geomspace(lo, hi, n_lam)
        self.p_grid = np.linspace(0.0, max(float(p_dark_max), 0.0), n_dark) if p_dark_max > 0 else np.zeros(1)
        # table[j, i]: mean ISI at p_grid[j], lam[i]; decreasing in i
        self.table = np.stack([mean_isi(self.lam, self.k, p, self.f) for p in self.p_grid])

    def __call__(self, rate, p_dark=0.0) -> np.ndarray:
        """lam [e-/interval] for observed spikes per interval ``rate`` (arrays broadcast with ``p_dark``)."""
        rate, p_dark = np.broadcast_arrays(np.asarray(rate, np.float64), np.asarray(p_dark, np.float64))
        shape = rate.shape
        r = rate.reshape(-1)
        pd = np.clip(p_dark.reshape(-1), 0.0, self.p_grid[-1])
        if self.p_grid.size > 1:
            pos = pd / self.p_grid[-1] * (self.p_grid.size - 1)
            j = np.minimum(np.floor(pos).astype(int), self.p_grid.size - 2)
            w = (pos - j)[:, None]
        else:
            j = np.zeros(r.size, int)
            w = np.zeros((r.size, 1))
        out = np.empty(r.size)
        log_lam = np.log(self.lam)
        target = 1.0 / np.where(r > 0, r, np.nan)  # mean ISI to match
        for s in range(0, r.size, 8192):  # bounded memory: 8192 x n_lam rows at a time
            sl = slice(s, s + 8192)
            rows = (1 - w[sl]) * self.table[j[sl]] + w[sl] * self.table[np.minimum(j[sl] + 1, self.p_grid.size - 1)]
            t = target[sl]
            # rows decrease along lam: count entries above target
            idx = (rows > t[:, None]).sum(axis=1)
            res = np.full(t.size, np.nan)
            below = idx == 0  # faster than the largest tabulated lam
            dark_only = idx >= self.lam.size  # slower than the smallest: at/below the dark-only rate
            mid = ~below & ~dark_only & np.isfinite(t)
            ii = idx[mid]
            y0, y1 = rows[mid, ii - 1], rows[mid, ii]
            frac = np.clip((y0 - t[mid]) / (y0 - y1), 0.0, 1.0)
            res[mid] = np.exp(log_lam[ii - 1] + frac * (log_lam[ii] - log_lam[ii - 1]))
            res[dark_only] = 0.0
            res[~np.isfinite(t)] = 0.0
            out[sl] = res
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


def fit_hot_pixel(mean_isi_obs: float, var_isi_obs: float, p_dark: float = 0.0):
    """Method-of-moments (mu_HP, sigma_HP) [threshold units / interval] from a hot pixel's dark ISIs.

    Solves ``hot_pixel_isi_moments(mu, sigma, p_dark) == (mean, var)`` by least
    squares in (log mu, log sigma). Returns (mu, sigma).
    """
    from scipy.optimize import least_squares
    m_obs, v_obs = float(mean_isi_obs), max(float(var_isi_obs), 1e-6)
    mu0 = 1.0 / max(m_obs - 0.5, 0.5)
    s0 = max(np.sqrt(v_obs * mu0 ** 3), 1e-3)

    def resid(x):
        m, v = hot_pixel_isi_moments(np.exp(x[0]), np.exp(x[1]), p_dark)
        return [(m - m_obs) / m_obs, (np.sqrt(max(v, 0.0)) - np.sqrt(v_obs)) / max(np.sqrt(v_obs), 0.05)]

    sol = least_squares(resid, x0=[np.log(mu0), np.log(s0)], bounds=([np.log(1e-4), np.log(1e-4)], [np.log(5.0), np.log(5.0)]),
                        x_scale=[0.1, 0.5], diff_step=1e-3)
    return float(np.exp(sol.x[0])), float(np.exp(sol.x[1]))
