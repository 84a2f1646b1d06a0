"""Classic spike-camera reconstruction: plain functions on arrays.

Shapes: spikes are bool/uint8 (T, H, W), one row per interval of T_r seconds
(50 us by default). Interval indices count from 0 at the first row.

Units of the outputs
--------------------
* :func:`tfp`, :func:`tfp_windows`, :func:`tfi` return **spikes per interval**
  (dimensionless, in [0, 1]): the firing-rate estimate of each pixel.
* :func:`tfp_deadtime` returns ``rate_e``, **expected photoelectrons per
  interval** [e-/interval], the quantity the sensor integrates; divide by the
  profile's ``threshold_e`` to compare with the other methods on the common
  "ideal spikes per interval" scale (``rate_e / threshold_e``) used by
  :mod:`recon.metrics` and the datasets.
"""

from __future__ import annotations

import functools

import numpy as np

from sensor.errors import InputError

#: number of intervals per TFP window and windows per network input in the ELSSim / RSIR setting (M = 320)
RSIR_WINDOW = 32
RSIR_N_WINDOWS = 10


def _check_spikes(spikes) -> np.ndarray:
    s = np.asarray(spikes)
    if s.ndim != 3:
        raise InputError(f"spikes must be (T, H, W); got shape {s.shape}", field="spikes")
    if s.shape[0] == 0:
        raise InputError("empty spike stream (T = 0)", field="spikes")
    return s


def window_bounds(T: int, window: int | None, center: int | None) -> tuple[int, int]:
    """Interval range ``[start, stop)`` of a centred window, clipped to a stream of ``T`` intervals.

    The window is ``[center - window//2, center - window//2 + window)``, shifted
    (not shrunk) to lie inside ``[0, T)`` when possible, and cut to ``T`` when
    ``window > T``. ``window`` defaults to ``T``, ``center`` to ``T // 2``.
    """
    window = T if window is None else int(window)
    if window < 1:
        raise InputError(f"window must be >= 1 interval, got {window}", field="window")
    center = T // 2 if center is None else int(center)
    start = max(0, min(center - window // 2, T - window))
    stop = min(T, start + window)
    return start, stop


def tfp(spikes, window: int | None = None, center: int | None = None) -> np.ndarray:
    """Texture From Playback: mean spike count per interval over a window.

    Parameters
    ----------
    spikes : array (T, H, W)
        Spike stream (bool or 0/1).
    window : int, optional
        Window length in intervals; default all T.
    center : int, optional
        Interval at the window centre; default T // 2. The window is
        ``[center - window//2, center - window//2 + window)``, clipped to the stream.

    Returns
    -------
    numpy.ndarray float32 (H, W)
        Spikes per interval in [0, 1] (the firing probability estimate).
    """
    s = _check_spikes(spikes)
    start, stop = window_bounds(s.shape[0], window, center)
    return s[start:stop].sum(axis=0, dtype=np.float32) / np.float32(stop - start)


def tfp_windows(spikes, n_windows: int = RSIR_N_WINDOWS, window: int = RSIR_WINDOW,
                center: int | None = None) -> np.ndarray:
    """Consecutive TFP windows: the RSIR network input (M = n_windows * window intervals).

    Parameters
    ----------
    spikes : array (T, H, W)
        Spike stream with ``T >= n_windows * window``.
    n_windows, window : int
        Number of windows and intervals per window (10 and 32 in the paper).
    center : int, optional
        Interval at the centre of the M-interval block; default T // 2.

    Returns
    -------
    numpy.ndarray float32 (n_windows, H, W)
        Spikes per interval of each window, in time order.
    """
    s = _check_spikes(spikes)
    M = int(n_windows) * int(window)
    if n_windows < 1 or window < 1:
        raise InputError(f"n_windows and window must be >= 1, got {n_windows}, {window}", field="window")
    if s.shape[0] < M:
        raise InputError(f"need at least {M} intervals ({n_windows} windows of {window}); the stream has "
                         f"{s.shape[0]}", field="spikes")
    start, _ = window_bounds(s.shape[0], M, center)
    block = s[start:start + M].reshape(n_windows, window, *s.shape[1:])
    return block.sum(axis=1, dtype=np.float32) / np.float32(window)


def tfi(spikes, center: int | None = None) -> np.ndarray:
    """Texture From Interval: reciprocal of the inter-spike interval around ``center``.

    For each pixel, ``t_prev`` is the last spike at or before ``center`` and
    ``t_next`` the first spike strictly after it; the estimate is
    ``1 / (t_next - t_prev)`` spikes per interval.

    Edges (documented choice): the ISI is *censored* at the ends of the stream.
    Before the first spike, ``t_prev`` is taken as ``-1`` (as if a spike had
    fired just before the stream began); after the last spike, ``t_next`` is
    taken as ``T`` (the first interval after the stream). The resulting ISI is
    the shortest one consistent with the data, so at the edges the estimate is
    an upper bound on the rate; a pixel with no spike at all gets
    ``1 / (T + 1)``. Use a longer stream (or TFP) where that matters.

    Parameters
    ----------
    spikes : array (T, H, W)
        Spike stream (bool or 0/1).
    center : int, optional
        Interval at which to reconstruct; default T // 2.

    Returns
    -------
    numpy.ndarray float32 (H, W)
        Spikes per interval, in (0, 1].
    """
    s = _check_spikes(spikes).astype(bool, copy=False)
    T = s.shape[0]
    c = T // 2 if center is None else int(center)
    if not 0 <= c < T:
        raise InputError(f"center must lie in [0, {T}), got {c}", field="center")
    idx = np.arange(T, dtype=np.int64)[:, None, None]
    before = s[:c + 1]
    after = s[c + 1:]
    t_prev = np.where(before, idx[:c + 1], -1).max(axis=0)
    if after.shape[0]:
        t_next = np.where(after, idx[c + 1:], T).min(axis=0)
    else:
        t_next = np.full(s.shape[1:], T, np.int64)
    return (1.0 / (t_next - t_prev)).astype(np.float32)


# ---------------------------------------------------------------------------------------------------------------
# dead-time-corrected TFP: invert the exact ELSSim renewal relation rate(lambda)
# ---------------------------------------------------------------------------------------------------------------

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
    numpy.ndarray float64, broadcast shape
        Spikes per interval in [p_dark, 1].
    """
    from scipy import special
    lam, k, f, p = np.broadcast_arrays(*(np.asarray(a, np.float64) for a in (lam, k, refractory_fraction, p_dark)))
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
    return 1.0 / total


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


def tfp_deadtime(spikes, profile, window: int | None = None, center: int | None = None,
                 correct_hot_pixels: bool = True) -> np.ndarray:
    """Dead-time- and reset-corrected TFP: photoelectron rate estimate ``rate_e`` [e-/interval].

    Plain TFP times the threshold (``tfp * theta``) underestimates the
    photoelectron rate: after each spike the pixel is blind for the refractory
    fraction ``f`` of an interval, the charge above the threshold is discarded
    at reset, and at most one spike fits in an interval; dark events add
    spikes. This estimator takes the observed spike rate ``r`` (TFP over the
    window) and inverts the exact ELSSim renewal relation
    ``r = renewal_spike_rate(lambda, k, f, p_dark)`` per pixel, with the
    pixel's ``k = ceil(theta / g)`` (PRNU gain ``g``), refractory fraction and
    dark probability from ``profile``.

    For hot pixels (``profile.hot_mask``) the mean hot charge per interval,
    ``hot_mu * theta`` electrons, acts like ``hot_mu * theta / g`` extra
    photoelectrons and is subtracted (clipped at 0) when
    ``correct_hot_pixels`` is true; that correction is approximate (the hot
    charge is Gaussian and not refractory-gated).

    Statistics: ``r`` is unbiased for the renewal rate when the window starts
    in the stationary regime; the inverse is smooth, so the estimate is
    unbiased up to O(1/count) (second-order Jensen term) and the start-up
    transient of a stream (at most about one spike).

    Parameters
    ----------
    spikes : array (T, H, W)
        Spike stream recorded by a sensor described by ``profile``.
    profile : sensor.SensorProfile
        The sensor (resolution must match H, W).
    window, center : int, optional
        As for :func:`tfp`.
    correct_hot_pixels : bool
        Subtract the mean hot-pixel charge (see above).

    Returns
    -------
    numpy.ndarray float32 (H, W)
        ``rate_e`` [e-/interval]; saturated pixels get ``4 k``.
    """
    from sensor.effects import count_threshold, dark_event_probability
    s = _check_spikes(spikes)
    if tuple(s.shape[1:]) != tuple(profile.shape):
        raise InputError(f"spikes are {s.shape[1]}x{s.shape[2]} but profile '{profile.name}' is "
                         f"{profile.height}x{profile.width}", field="profile")
    r = tfp(s, window, center).astype(np.float64)
    gain = profile.prnu_gain.astype(np.float64)
    k = count_threshold(profile.threshold_e, gain)
    lam = invert_renewal_rate(r, k, profile.refractory_fraction.astype(np.float64),
                              dark_event_probability(profile.dark_rate))
    if correct_hot_pixels and profile.hot_mask.any():
        hot = profile.hot_mask
        lam[hot] = np.maximum(lam[hot] - profile.hot_mu[hot] * profile.threshold_e / gain[hot], 0.0)
    return lam.astype(np.float32)


CLASSIC_METHODS = ("tfp", "tfi", "tfp-dt")
