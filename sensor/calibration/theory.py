"""Exact statistics used by absolute calibration (threshold, reset, sensitivity), for both resets.

Everything here is for a non-hot pixel under constant light, in the notation of
:mod:`sensor.analysis.theory`: ``lam`` expected photoelectrons per interval, ``k``
photoelectrons needed to fire (``theta / g``), ``f`` the refractory fraction
of an interval, ``mu`` the dark-event rate mu_DC per interval (``p = 1 -
exp(-mu)`` per interval). Time is in intervals. See ``docs/sensor.md``,
"Absolute calibration", for the derivations.

Interval reset (Algorithm 2)
    Read-out ISIs are i.i.d. integers with survival
    ``S(n) = Q(k, lam (n - f)) (1 - p)^n`` (:func:`sensor.analysis.theory.isi_survival`).
    :func:`interval_isi_moments` gives their exact mean and variance.

Crossing reset (continuous time)
    The pixel fires at the k-th photoelectron or at the first dark event (a
    Poisson process of rate ``mu``), whichever comes first, then is blind for
    ``f``. The continuous ISI is ``X = f + min(G, E)``, ``G ~ Gamma(k, lam)``,
    ``E ~ Exp(mu)``: a renewal process, with closed-form moments
    (:func:`crossing_isi_moments`). The read-out reports the *first* firing of
    each interval; a firing that follows another one in the same interval is
    merged. A firing's phase in its interval is uniform in the stationary state
    (a random walk on the circle), so a continuous ISI of length ``x`` is
    merged with probability ``(1 - x)^+``. :func:`crossing_readout_unit` gives
    the mean and variance of the time from one read-out spike to the next
    (``U``, the merged ISIs plus the next unmerged one, a geometric compound);
    the read-out spike rate is ``1 / E[U]``. For ``n`` consecutive read-out ISIs
    the telescoping sum of read-out indices obeys (exactly when nothing merges)

        Var(sum of n read-out ISIs) = n Var(U) + E[q(Y_n)],
        q(y) = frac(y) (1 - frac(y)),  E[q(Y_n)] -> 1/6,

    so the readout quantisation adds a bounded term whatever ``n`` (1/6 to
    within 1e-3 relative once ``n Var(U) >= 0.3`` when nothing merges; merges
    add a small bounded phase-span covariance), while shot noise grows with
    ``n``: the variance-time slope between two block lengths is ``Var(U)``.
    The merge treatment (phase independent of the merged ISI) is exact to first
    order in ``mu``; ``Var(U)`` and ``E[U]`` agree with a direct Monte Carlo of
    the continuous process to 0.1 %.
"""

from __future__ import annotations

import numpy as np
from scipy import special

#: Gauss-Legendre nodes for integrals over one interval
_GL_X, _GL_W = np.polynomial.legendre.leggauss(48)


def _arrays(*a):
    b = np.broadcast_arrays(*(np.asarray(x, np.float64) for x in a))
    return [np.ascontiguousarray(x) for x in b]


# ------------------------------------------------------------------------------------------------ interval reset
def interval_isi_moments(lam, k, p_dark=0.0, f=0.0):
    """Exact (mean, variance) of the read-out ISI [intervals] under the interval reset, vectorised.

    ``E[N] = sum_{n>=0} S(n)``, ``E[N^2] = sum_{n>=0} (2n + 1) S(n)`` with
    ``S(n) = Q(k, lam (n - f)) (1 - p)^n`` (:func:`sensor.analysis.theory.isi_survival`);
    the sums run until the Poisson tail is below 1e-20. Arrays broadcast;
    ``lam > 0`` required.
    """
    lam, k, p, f = _arrays(lam, k, p_dark, f)
    shape = lam.shape
    lam, k, p, f = (x.reshape(-1) for x in (lam, k, p, f))
    n_max = int(np.ceil(np.max((k + 10.0 * np.sqrt(k) + 10.0) / np.maximum(lam, 1e-9) + f))) + 2
    m1 = np.ones(lam.size)
    m2 = np.ones(lam.size)
    logq = np.log1p(-np.clip(p, 0.0, 1 - 1e-16))
    chunk = 256
    for n0 in range(1, n_max + 1, chunk):
        n = np.arange(n0, min(n0 + chunk, n_max + 1), dtype=np.float64)[None, :]
        S = special.gammaincc(k[:, None], np.clip(lam[:, None] * (n - f[:, None]), 0, None)) * np.exp(n * logq[:, None])
        m1 += S.sum(axis=1)
        m2 += ((2 * n + 1) * S).sum(axis=1)
    return m1.reshape(shape), (m2 - m1 * m1).reshape(shape)


# ------------------------------------------------------------------------------------------------ crossing reset
def crossing_isi_moments(lam, k, mu=0.0, f=0.0):
    """Exact (E[X], E[X^2]) of the continuous ISI ``X = f + min(Gamma(k, lam), Exp(mu))`` [intervals].

    With ``rho = lam / (lam + mu)``:
    ``E[min] = sum_{j<k} lam^j / (lam + mu)^(j+1) = (1 - rho^k) / mu`` and
    ``E[min^2] = 2 / (lam + mu)^2 sum_{j<k} (j + 1) rho^j`` (integrate the
    survival ``Q(k, lam t) exp(-mu t)`` term by term); ``mu = 0`` gives
    ``k / lam`` and ``k (k + 1) / lam^2``.
    """
    lam, k, mu, f = _arrays(lam, k, mu, f)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = mu / lam
        one_m_rho = u / (1 + u)
        rho_k = np.exp(-k * np.log1p(u))
        a = -np.expm1(-k * np.log1p(u)) / one_m_rho  # sum_{j<k} rho^j
        s2 = (a - k * rho_k) / one_m_rho  # sum_{j<k} (j + 1) rho^j
        ey = a / (lam + mu)
        ey2 = 2.0 * s2 / (lam + mu) ** 2
    nodark = mu <= 0
    ey = np.where(nodark, k / lam, ey)
    ey2 = np.where(nodark, k * (k + 1) / lam ** 2, ey2)
    e1 = f + ey
    e2 = f * f + 2 * f * ey + ey2
    return e1, e2


def _crossing_merge_integrals(lam, k, mu, f):
    """(pi, a1, a2) = E[(1 - X)^+ X^j], j = 0, 1, 2: the merged part of the continuous ISI law.

    The density of ``X`` on ``(f, 1)`` is ``exp(-mu s) (lam gamma_pdf(k, lam s) + mu Q(k, lam s))``,
    ``s = x - f``; integrated by 48-point Gauss-Legendre quadrature (the light
    part is negligible unless ``k / lam < 1``, i.e. the pixel fires more than once
    per interval by light alone).
    """
    lam, k, mu, f = _arrays(lam, k, mu, f)
    x = f[..., None] + (1 - f[..., None]) * (_GL_X + 1) / 2
    w = (1 - f[..., None]) / 2 * _GL_W
    s = x - f[..., None]
    L = lam[..., None]
    kk = k[..., None]
    ls = L * s
    with np.errstate(divide="ignore", invalid="ignore"):
        logpdf = np.where(ls > 0, (kk - 1) * np.log(np.where(ls > 0, ls, 1)) - ls - special.gammaln(kk), -np.inf)
    dens = np.exp(-mu[..., None] * s) * (L * np.exp(logpdf) + mu[..., None] * special.gammaincc(kk, ls))
    g = (1 - x) * dens * w
    return g.sum(-1), (g * x).sum(-1), (g * x * x).sum(-1)


def crossing_readout_unit(lam, k, mu=0.0, f=0.0):
    """(E[U], Var(U)) of the time between consecutive *read-out* spikes under the crossing reset [intervals].

    ``U`` = the merged continuous ISIs (a geometric number, each merged with
    probability ``(1 - x)^+``) plus the next unmerged one. With ``pi =
    E[(1 - X)^+]``, merged moments ``a_j = E[X^j (1 - X)^+]`` and unmerged
    ``b_j = E[X^j] - a_j``: ``E[U] = E[X] / (1 - pi)`` and
    ``Var(U) = E[K] Var(A) + Var(K) E[A]^2 + Var(B)``, ``E[K] = pi / (1 - pi)``,
    ``Var(K) = pi / (1 - pi)^2``. The read-out spike rate is ``1 / E[U]``.
    """
    e1, e2 = crossing_isi_moments(lam, k, mu, f)
    pi, a1, a2 = _crossing_merge_integrals(lam, k, mu, f)
    pi = np.clip(pi, 0.0, 0.999)
    b1, b2 = e1 - a1, e2 - a2
    with np.errstate(divide="ignore", invalid="ignore"):
        ea = np.where(pi > 0, a1 / np.where(pi > 0, pi, 1), 0.0)
        va = np.where(pi > 0, a2 / np.where(pi > 0, pi, 1), 0.0) - ea ** 2
    eb = b1 / (1 - pi)
    vb = b2 / (1 - pi) - eb ** 2
    ek = pi / (1 - pi)
    vk = pi / (1 - pi) ** 2
    return e1 / (1 - pi), ek * va + vk * ea ** 2 + vb


def crossing_spike_rate(lam, k, mu=0.0, f=0.0):
    """Read-out spike rate [spikes/interval] under the crossing reset: ``1 / E[U]``."""
    return 1.0 / crossing_readout_unit(lam, k, mu, f)[0]


def invert_crossing_rate(rate, k, mu, f, iterations: int = 8):
    """Photoelectron rate lam [e-/interval] whose crossing-reset read-out rate is ``rate`` (per pixel).

    Fixed point: ``E[min(G, E)] = (1 - pi) / rate - f`` is solved for lam in
    closed form (``rho^k = 1 - mu y``, ``lam = mu rho / (1 - rho)``; ``k / y``
    without dark), then the merge probability ``pi`` is updated; ``pi`` depends
    weakly on lam, so a few iterations converge to machine precision in the
    regime of interest. Rates at or below the dark floor give 0.
    """
    r, k, mu, f = _arrays(rate, k, mu, f)
    pi = np.zeros(r.shape)
    lam = np.zeros(r.shape)
    ok = r > 0
    for _ in range(iterations):
        with np.errstate(divide="ignore", invalid="ignore"):
            y = (1 - pi) / np.where(ok, r, 1.0) - f
            t = 1 - mu * y
            good = ok & (y > 0) & (t > 0)
            lk = np.where(good, np.log(np.where(good, t, 1.0)) / k, 0.0)  # log rho
            one_m_rho = -np.expm1(lk)
            lam_d = mu * np.exp(lk) / np.where(one_m_rho > 0, one_m_rho, 1.0)
            lam = np.where(good, np.where(mu > 0, lam_d, k / np.where(y > 0, y, 1.0)), 0.0)
        pi = np.clip(_crossing_merge_integrals(np.maximum(lam, 1e-12), k, mu, f)[0], 0, 0.999)
    return lam


def crossing_lag1_correlation(var_unit):
    """Predicted lag-1 correlation of read-out ISIs under the crossing reset, for ``Var(U) = var_unit``.

    Consecutive read-out ISIs share the phase of the spike between them:
    ``Var(D1 + D2) = 2 Var(U) + 1/6`` and ``Var(D) = Var(U) + 1/6`` (phases
    spread over the interval), so ``Cov = -1/12`` and
    ``rho_1 = -(1/12) / (Var(U) + 1/6)``: -1/2 when the ISI is nearly
    deterministic, -> 0 when it is much wider than one interval. (When the
    ISI's spread is below ~0.3 interval the phase terms deviate from 1/6 and
    this is an approximation.) Under the interval reset ISIs are i.i.d.: 0.
    """
    return -(1.0 / 12.0) / (np.asarray(var_unit, np.float64) + 1.0 / 6.0)


# ------------------------------------------------------------------------------------------ hot pixels, crossing
def crossing_hot_pixel_isi_moments(mu, sigma, p_dark=0.0, f=0.0, n_bins: int = 200):
    """Mean and variance of the read-out dark ISI [intervals] of a hot pixel under the crossing reset.

    Per interval the pixel receives a current ``c ~ N(mu, sigma^2)`` [threshold
    units per interval], spread evenly over the interval; the charge stays >= 0;
    it fires the moment it reaches 1, is blind for ``f`` and keeps integrating
    ``c`` for the rest of the interval (so after a firing at ``t = (1 - v) / c``
    the charge at the interval's end is ``v + c - 1 - c f``). A dark event
    (probability ``p_dark`` per interval, uniform time ``u``) fires it at once
    and leaves ``max(c (1 - u - f), 0)`` (second dark events in one interval are
    neglected, O(p_dark^2)). The charge at interval ends is a Markov chain on
    ``n_bins`` cells of [0, 1) plus an atom at 0; ``A0`` / ``A1`` are its
    transitions without / with a read-out spike. The ISIs are the first-passage
    times from the post-spike distribution ``nu ~ pi A1`` (``pi`` stationary), so
    these are the exact marginal moments of the read-out ISIs (they are serially
    correlated: the charge left after a firing carries over). Assumes ``c < 1``
    in practice (at most one firing per interval by the hot current).
    """
    from scipy.stats import norm
    mu, sigma, p, f = float(mu), max(float(sigma), 1e-4), float(p_dark), float(f)
    edges = np.linspace(0.0, 1.0, n_bins + 1)
    v = np.concatenate([[0.0], 0.5 * (edges[:-1] + edges[1:])])
    S = v.size
    A0 = np.zeros((S, S))
    A1 = np.zeros((S, S))
    cdf = lambda c: norm.cdf((c - mu) / sigma)  # noqa: E731
    # no dark event: no firing if c < 1 - v (charge v + c, clipped at 0)
    up = cdf(edges[None, :] - v[:, None])  # P(c < e_j - v)
    A0[:, 0] = up[:, 0]
    A0[:, 1:] = np.diff(up, axis=1)
    # firing: c >= 1 - v; charge after = v - 1 + c (1 - f) in bin j  <=>  c in [(1 - v + e_j)/(1-f), ...)
    fc = cdf((1.0 - v[:, None] + edges[None, :]) / (1.0 - f))
    A1[:, 0] = fc[:, 0] - cdf(1.0 - v)  # lands below 0 after the blind loss: clipped to the atom
    A1[:, 1:] = np.diff(fc, axis=1)
    A1[:, -1] += 1.0 - fc[:, -1]  # c > 2 - v: more than one firing; lump into the top cell (negligible)
    # dark event: spike; charge left U c (1 - f), U uniform: independent of v
    cq = mu + sigma * norm.ppf((np.arange(400) + 0.5) / 400)  # quantiles of c
    top = np.clip(cq, 0, None) * (1 - f)
    dark_row = np.zeros(S)
    pos = top > 0
    dark_row[0] = np.mean(~pos)
    if pos.any():
        frac = np.clip((np.minimum(edges[None, :], top[pos, None])) / top[pos, None], 0, 1)
        dark_row[1:] += np.diff(frac, axis=1).sum(axis=0) / cq.size
    A0, A1 = (1 - p) * A0, (1 - p) * A1 + p * dark_row[None, :]
    P = A0 + A1
    # stationary distribution: pi (P - I) = 0, sum pi = 1 (one equation replaced by the normalisation)
    M = (P - np.eye(S)).T
    M[-1] = 1.0
    rhs = np.zeros(S)
    rhs[-1] = 1.0
    # scipy's LAPACK solve: numpy's is ~100x slower here (thread start-up on small matrices)
    from scipy.linalg import solve
    pi = np.clip(solve(M, rhs), 0, None)
    nu = pi @ A1
    nu /= nu.sum()
    # first passage from nu: E[N] = nu R, E[N^2] = nu (2 A0 (I - A0)^-1 R + R), R = (I - A0)^-1 1
    I_A0 = np.eye(S) - A0
    R = solve(I_A0, np.ones(S))
    m1 = float(nu @ R)
    m2 = float(nu @ (2 * A0 @ solve(I_A0, R) + R))
    return m1, m2 - m1 * m1
