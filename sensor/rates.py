"""From photoelectron-rate keyframes to expected photoelectrons per interval.

The time convention (the one place it is defined)
-------------------------------------------------
* Keyframes: ``rate_e`` (K, H, W) [e-/interval] at times ``t_s`` (K,) [s],
  strictly increasing, any spacing. Between keyframes the rate is
  **piecewise-linear** in time; there is no extrapolation outside
  ``[t_s[0], t_s[-1]]``.
* Interval ``m`` (m = 0, 1, ...) covers ``[t0 + m T_r, t0 + (m+1) T_r)`` with
  ``t0 = t_s[0]``. A stream of keyframes spanning ``D = t_s[-1] - t0`` seconds
  has ``T = floor(D / T_r + 1e-6)`` whole intervals (a partial last interval is
  dropped; the 1e-6 guards against round-off in ``D / T_r``).
* The expected photoelectrons of interval ``m`` is the exact average of the
  piecewise-linear rate over the interval:
  ``lambda_m = (1/T_r) * integral_{interval m} rate(t) dt`` [e-]. With one
  keyframe per interval at its centre and a linear rate this equals the rate at
  the centre; it is *not* a point sample at ``m T_r`` as in the paper's
  Algorithms 1-2, which alias fast changes.
* Without timestamps, ``rate_e`` (T, H, W) is taken as one value per interval
  (piecewise-constant): ``lambda_m = rate_e[m]``.

The linear map keyframes -> lambda is computed with the integrals of the
piecewise-linear "hat" basis functions, which depend on times only; the pixel
data then enter through one small matrix product.
"""

from __future__ import annotations

import numpy as np

from .errors import InputError
from .units import INTERVAL_S

_N_INTERVALS_EPS = 1e-6


def n_intervals_spanned(t_first_s: float, t_last_s: float, interval_s: float = INTERVAL_S) -> int:
    """Whole intervals between the first and the last keyframe time."""
    return int(np.floor((float(t_last_s) - float(t_first_s)) / float(interval_s) + _N_INTERVALS_EPS))


def interval_bounds_s(t0_s: float, m0: int, m1: int, interval_s: float = INTERVAL_S) -> np.ndarray:
    """Boundaries [s] of intervals m0..m1-1: ``t0 + m T_r`` for m = m0..m1 (float64, m1-m0+1 values)."""
    return float(t0_s) + np.arange(m0, m1 + 1, dtype=np.float64) * float(interval_s)


def hat_interval_weights(knots_s, bounds_s, interval_s: float = INTERVAL_S) -> np.ndarray:
    """Weights W (M, K): lambda_m = sum_j W[m, j] * rate_e[j] for a piecewise-linear rate.

    ``W[m, j] = (1/T_r) integral_{bounds[m]}^{bounds[m+1]} phi_j(t) dt`` where
    ``phi_j`` is the hat function of knot j (1 at ``knots[j]``, 0 at its
    neighbours). The first knot has no left ramp and the last no right ramp, so
    the result does not depend on knots outside ``knots_s`` as long as every
    bound lies within ``[knots[0], knots[-1]]``.
    """
    t = np.asarray(knots_s, dtype=np.float64)
    b = np.asarray(bounds_s, dtype=np.float64)
    if t.ndim != 1 or t.size < 2:
        raise InputError("need at least two keyframe times to interpolate", field="t_s")
    a_, b_ = b[:-1], b[1:]
    W = np.zeros((a_.size, t.size), dtype=np.float64)
    for j in range(t.size):
        if j > 0:
            lo, hi = t[j - 1], t[j]
            xa, xb = np.clip(a_, lo, hi) - lo, np.clip(b_, lo, hi) - lo
            W[:, j] += (xb * xb - xa * xa) / (2.0 * (hi - lo))
        if j < t.size - 1:
            lo, hi = t[j], t[j + 1]
            xa, xb = np.clip(a_, lo, hi) - lo, np.clip(b_, lo, hi) - lo
            W[:, j] += (xb - xb * xb / (2.0 * (hi - lo))) - (xa - xa * xa / (2.0 * (hi - lo)))
    return W / float(interval_s)


def interval_rates(rate_e, t_s=None, n_intervals: int | None = None, interval_s: float = INTERVAL_S,
                   m0: int = 0) -> np.ndarray:
    """Expected photoelectrons per interval, lambda (T, H, W) float32 [e-].

    Parameters
    ----------
    rate_e : array (K, H, W)
        Photoelectron rate [e-/interval] at the keyframes.
    t_s : array (K,), optional
        Keyframe times [s]. When None, ``rate_e`` holds one value per interval.
    n_intervals : int, optional
        How many intervals (from ``m0``) to return; default: all spanned.
    m0 : int
        First interval index, counted from ``t_s[0]``.
    """
    rate_e = np.asarray(rate_e, dtype=np.float32)
    if t_s is None:
        stop = rate_e.shape[0] if n_intervals is None else m0 + n_intervals
        return rate_e[m0:stop]
    t = np.asarray(t_s, dtype=np.float64)
    total = n_intervals_spanned(t[0], t[-1], interval_s)
    n = total - m0 if n_intervals is None else int(n_intervals)
    if m0 + n > total:
        raise InputError(f"asked for intervals {m0}..{m0 + n - 1} but the keyframes span only {total}")
    bounds = interval_bounds_s(t[0], m0, m0 + n, interval_s)
    lo = max(int(np.searchsorted(t, bounds[0], "right")) - 1, 0)
    hi = min(int(np.searchsorted(t, bounds[-1], "left")), t.size - 1)
    hi = max(hi, lo + 1)
    W = hat_interval_weights(t[lo:hi + 1], bounds, interval_s).astype(np.float32)
    K, H, Wd = rate_e[lo:hi + 1].shape
    return (W @ rate_e[lo:hi + 1].reshape(K, H * Wd)).reshape(n, H, Wd)


class RateSchedule:
    """Streaming buffer of keyframes that hands out lambda for whole blocks of intervals.

    Feed keyframes in time order with :meth:`add`; ask for the lambda of
    intervals ``[m0, m1)`` with :meth:`rates` once :meth:`covered` says the
    keyframes reach ``m1``. The result for a block depends only on the
    keyframes around it, never on how the input was chunked, which keeps
    seeded simulations bitwise reproducible across chunk sizes.
    """

    def __init__(self, interval_s: float = INTERVAL_S, per_interval: bool = False):
        self.interval_s = float(interval_s)
        self.per_interval = per_interval
        self._t: np.ndarray = np.zeros(0, np.float64)
        self._r: np.ndarray | None = None
        self._offset = 0  # per_interval mode: index of the first buffered interval
        self.t0_s: float | None = None

    def add(self, rate_e, t_s=None) -> None:
        rate_e = np.asarray(rate_e, dtype=np.float32)
        if rate_e.ndim != 3:
            raise InputError(f"rate_e must be (K, H, W); got shape {rate_e.shape}", field="rate_e")
        if not np.all(np.isfinite(rate_e)) or np.any(rate_e < 0):
            raise InputError("rate_e must be finite and >= 0 (expected photoelectrons per interval)",
                             field="rate_e")
        if self.per_interval:
            if t_s is not None:
                raise InputError("this stream takes one rate per interval (t_s=None)", field="t_s")
        else:
            if t_s is None:
                raise InputError("this stream takes keyframes with timestamps t_s", field="t_s")
            t_new = np.asarray(t_s, dtype=np.float64).reshape(-1)
            if t_new.size != rate_e.shape[0]:
                raise InputError(f"{t_new.size} timestamps for {rate_e.shape[0]} keyframes", field="t_s")
            allt = np.concatenate([self._t, t_new])
            if np.any(np.diff(allt) <= 0):
                raise InputError("keyframe times must increase strictly across all chunks", field="t_s")
            if self.t0_s is None and t_new.size:
                self.t0_s = float(t_new[0])
            self._t = allt
        if self._r is not None and self._r.shape[1:] != rate_e.shape[1:]:
            raise InputError(f"frame shape changed from {self._r.shape[1:]} to {rate_e.shape[1:]}", field="rate_e")
        self._r = rate_e.copy() if self._r is None else np.concatenate([self._r, rate_e])

    @property
    def frame_shape(self):
        return None if self._r is None else self._r.shape[1:]

    def covered(self) -> int:
        """Number of intervals (from interval 0) that the buffered keyframes fully determine."""
        if self._r is None:
            return 0
        if self.per_interval:
            return self._offset + self._r.shape[0]
        if self._t.size < 2:
            return 0
        return n_intervals_spanned(self.t0_s, self._t[-1], self.interval_s)

    def rates(self, m0: int, m1: int) -> np.ndarray:
        """lambda for intervals [m0, m1), float32 (m1-m0, H, W); drops keyframes no longer needed."""
        if m1 > self.covered():
            raise InputError(f"intervals up to {m1} requested but keyframes cover only {self.covered()}")
        if self.per_interval:
            out = self._r[m0 - self._offset:m1 - self._offset]
            self._r = self._r[m1 - self._offset:]
            self._offset = m1
            return out
        bounds = interval_bounds_s(self.t0_s, m0, m1, self.interval_s)
        t = self._t
        lo = max(int(np.searchsorted(t, bounds[0], "right")) - 1, 0)
        hi = min(int(np.searchsorted(t, bounds[-1], "left")), t.size - 1)
        hi = max(hi, lo + 1)
        W = hat_interval_weights(t[lo:hi + 1], bounds, self.interval_s).astype(np.float32)
        K, H, Wd = self._r[lo:hi + 1].shape
        out = (W @ self._r[lo:hi + 1].reshape(K, H * Wd)).reshape(m1 - m0, H, Wd)
        # keep the last knot at or before the end of this block: the next block starts there
        keep = max(int(np.searchsorted(t, bounds[-1], "right")) - 1, 0)
        self._t, self._r = t[keep:], self._r[keep:]
        return out

    def knots(self):
        """Buffered keyframe times [s] and rates (for implementations that integrate per segment)."""
        return self._t, self._r
