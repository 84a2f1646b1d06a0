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


# dead-time-corrected TFP inverts the exact ELSSim renewal relation; it lives in sensor.analysis.theory
from sensor.analysis.theory import invert_renewal_rate, renewal_spike_rate  # noqa: E402,F401  (re-exported)


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
    s = _check_spikes(spikes)
    return deadtime_correct(tfp(s, window, center), profile, correct_hot_pixels)


def deadtime_correct(rate, profile, correct_hot_pixels: bool = True) -> np.ndarray:
    """The inversion step of :func:`tfp_deadtime` on an observed spike rate map.

    ``rate`` float (H, W) [spikes per interval] (TFP, or a smoothed TFP) ->
    ``rate_e`` float32 (H, W) [e-/interval], per pixel with the profile's
    ``k``, refractory fraction, dark probability and hot-pixel charge; with
    ``dark == "current"`` the inversion gives ``lambda + d`` and the pixel's
    dark current ``d`` is taken off.
    """
    from sensor.models.effects import count_threshold, dark_event_probability
    r = np.asarray(rate, np.float64)
    if tuple(r.shape) != tuple(profile.shape):
        raise InputError(f"spikes are {r.shape[0]}x{r.shape[1]} but profile '{profile.name}' is "
                         f"{profile.height}x{profile.width}", field="profile")
    gain = profile.prnu_gain.astype(np.float64)
    k = count_threshold(profile.threshold_e, gain)
    if profile.reset == "crossing":
        lam = _invert_crossing(r, k, profile.refractory_fraction.astype(np.float64),
                               profile.dark_rate.astype(np.float64))
    else:
        lam = invert_renewal_rate(r, k, profile.refractory_fraction.astype(np.float64),
                                  dark_event_probability(profile.dark_rate))
    if getattr(profile, "dark", "events") == "current":  # the rate came from lambda + d: take the dark current off
        lam = np.maximum(lam - profile.dark_current_e.astype(np.float64), 0.0)
    if correct_hot_pixels and profile.hot_mask.any():
        hot = profile.hot_mask
        lam[hot] = np.maximum(lam[hot] - profile.hot_mu[hot] * profile.threshold_e / gain[hot], 0.0)
    return lam.astype(np.float32)


#: x = lam / k nodes of the crossing-reset read-out table (0, then log-spaced to saturation)
_CROSSING_X = np.concatenate([[0.0], np.geomspace(1e-4, 1.0, 31)])
_CROSSING_CACHE: dict = {}


def _crossing_curves(k: int, f: float, mus: tuple) -> np.ndarray:
    """Read-out spike rate (len(mus), len(_CROSSING_X)) of a stationary crossing-reset pixel (cached)."""
    from sensor.analysis.theory import crossing_rates
    key = (int(k), round(float(f), 9), mus)
    if key not in _CROSSING_CACHE:
        out = np.empty((len(mus), _CROSSING_X.size))
        for i, mu in enumerate(mus):
            out[i, 0] = -np.expm1(-mu)  # no light: dark events only
            for j, x in enumerate(_CROSSING_X[1:], start=1):
                out[i, j] = crossing_rates(x * k, k, f, mu)[1]
        _CROSSING_CACHE[key] = np.maximum.accumulate(out, axis=1)  # monotone for interpolation
    return _CROSSING_CACHE[key]


def _invert_crossing(r, k, f, mu) -> np.ndarray:
    """Invert the crossing-reset read-out rate per pixel: ``rate_e`` [e-/interval] (``sensor.analysis.theory.crossing_rates``).

    The curve ``r(x)``, ``x = lam / k``, is tabulated at the median ``k`` and
    refractory fraction of the pixels (``r`` depends on ``k`` only through
    ``x`` to O(1/sqrt(k)) for the thresholds of ~2000 e- of a spike camera) and
    at up to four dark rates spanning the pixels'; each pixel interpolates
    between the two nearest dark-rate curves, inverts in ``x`` and scales by
    its own ``k``. Rates at or below the dark floor give 0; saturated read-outs
    give ``lam = k`` (one firing per interval).
    """
    k_med = int(np.median(k))
    f_med = float(np.median(f))
    lo, hi = float(mu.min()), float(mu.max())
    mus = (lo,) if hi <= lo * 1.0001 else tuple(float(v) for v in np.geomspace(max(lo, 1e-9), hi, 4))
    curves = _crossing_curves(k_med, f_med, tuple(round(m, 12) for m in mus))
    xs = np.stack([np.interp(r, c, _CROSSING_X) for c in curves])  # (n_mu, H, W)
    if len(mus) == 1:
        x = xs[0]
    else:
        lm = np.log(np.asarray(mus))
        pos = np.clip(np.interp(np.log(np.maximum(mu, 1e-9)), lm, np.arange(len(mus))), 0, len(mus) - 1)
        i0 = np.minimum(np.floor(pos).astype(int), len(mus) - 2)
        w = pos - i0
        x = np.take_along_axis(xs, i0[None], 0)[0] * (1 - w) + np.take_along_axis(xs, i0[None] + 1, 0)[0] * w
    return x * k


CLASSIC_METHODS = ("tfp", "tfi", "tfp-dt")
