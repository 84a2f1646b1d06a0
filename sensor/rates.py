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

from sensor.errors import InputError
from sensor.units import INTERVAL_S, MAX_RATE_E

_N_INTERVALS_EPS = 1e-6


def check_times(t_s, path=None, offset: int = 0) -> np.ndarray:
    """Keyframe times [s] as float64 (K,), checked finite and strictly increasing; the error names the index.

    ``offset`` is added to the reported index (for chunks of a longer stream).
    """
    t = np.asarray(t_s, dtype=np.float64).reshape(-1)
    bad = ~np.isfinite(t)
    if bad.any():
        i = int(np.argmax(bad))
        raise InputError(f"keyframe times must be finite; t_s[{i + offset}] = {float(t[i])!r}", path=path, field="t_s")
    d = np.diff(t)
    if np.any(d <= 0):
        i = int(np.argmax(d <= 0))
        raise InputError(f"keyframe times must increase strictly; t_s[{i + offset}] = {float(t[i])!r} and "
                         f"t_s[{i + offset + 1}] = {float(t[i + 1])!r}", path=path, field="t_s")
    return t


def bad_values(arr, top: float | None = None):
    """None if ``arr`` is all finite and >= 0 (and <= ``top`` when given), else (how many values are not,
    index of the first, its value)."""
    arr = np.asarray(arr)
    if arr.size == 0:
        return None
    top = np.inf if top is None else top
    lo, hi = arr.min(), arr.max()  # NaN propagates through min/max: one pass when all is well
    if np.isfinite(lo) and np.isfinite(hi) and lo >= 0 and hi <= top:
        return None
    bad = ~np.isfinite(arr) | (arr < 0) | (arr > top)
    idx = tuple(int(x) for x in np.argwhere(bad)[0])
    return int(bad.sum()), idx, float(arr[idx])


def check_rates(rate_e, path=None, field: str = "rate_e", offset: int = 0) -> None:
    """Raise InputError naming the first (keyframe, row, col) where ``rate_e`` is non-finite, negative or
    above :data:`sensor.units.MAX_RATE_E` [e-/interval].

    ``offset`` is added to the keyframe index (for chunks of a longer array).
    """
    rate_e = np.asarray(rate_e)
    if rate_e.dtype.kind not in "biuf":
        raise InputError(f"has dtype {rate_e.dtype}; expected real numbers (float or integer)", path=path,
                         field=field)
    found = bad_values(rate_e, MAX_RATE_E)
    if found:
        n, idx, v = found
        idx = (idx[0] + offset,) + tuple(idx[1:])
        raise InputError(f"{n} value(s) are non-finite, negative or above {MAX_RATE_E:g}, first at index "
                         f"{list(idx)}: {v!r} (expected finite photoelectrons per interval in [0, {MAX_RATE_E:g}])",
                         path=path, field=field)


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
    b = np.asarray(bounds_s, dtype=np.float64)
    return hat_pair_weights(knots_s, b[:-1], b[1:], interval_s)


def hat_pair_weights(knots_s, lo_s, hi_s, interval_s: float = INTERVAL_S) -> np.ndarray:
    """Like :func:`hat_interval_weights` for arbitrary intervals ``[lo_s[i], hi_s[i]]`` (M,) -> W (M, K)."""
    t = np.asarray(knots_s, dtype=np.float64)
    a_ = np.asarray(lo_s, dtype=np.float64)
    b_ = np.asarray(hi_s, dtype=np.float64)
    if t.ndim != 1 or t.size < 2:
        raise InputError("need at least two keyframe times to interpolate", field="t_s")
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
    t = check_times(t_s)
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


def _knots_of(t, bounds):
    """(lo, hi, keep) for intervals with boundaries ``bounds`` [s] and keyframe times ``t`` [s]: the
    keyframes lo..hi (inclusive) determine those intervals; ``keep`` is the last keyframe at or before
    their end (where the next block starts)."""
    lo = max(int(np.searchsorted(t, bounds[0], "right")) - 1, 0)
    hi = min(int(np.searchsorted(t, bounds[-1], "left")), t.size - 1)
    hi = max(hi, lo + 1)
    keep = max(int(np.searchsorted(t, bounds[-1], "right")) - 1, 0)
    return lo, hi, keep


def block_keyframe_rows(t_s, block: int, interval_s: float = INTERVAL_S) -> list[tuple[int, int]]:
    """Keyframe rows to read per simulator block so that no block's keyframes span two reads.

    For keyframe times ``t_s`` (K,) [s] and blocks of ``block`` intervals from ``t_s[0]`` (the last one
    partial), the row ranges ``[i, j)`` to feed a :class:`RateSchedule` one after the other. The plan
    follows the schedule's own rules, step by step: a block runs as soon as the keyframes fed cover it
    (:meth:`RateSchedule.covered`, with its round-off tolerance), and afterwards the schedule keeps the
    keyframes from the last one at or before the block's end. Each range starts at the first keyframe
    the schedule still holds, so with ``overlap`` = the rows it repeats
    (``RateSchedule.add(..., overlap=)``) the schedule replaces them and every block's keyframes are
    one array (a view of one chunk) instead of rows joined from two chunks -- a copy of every
    keyframe, serial with the kernel. Ranges that would add no row are skipped; every row
    ``0 .. K-1`` is in some range.
    """
    t = np.asarray(t_s, dtype=np.float64).reshape(-1)
    K = int(t.size)
    if K < 2:
        return [(0, K)] if K else []
    total = n_intervals_spanned(t[0], t[-1], interval_s)
    # intervals that keyframes 0..k cover, as RateSchedule.covered() counts them (non-decreasing in k)
    spanned = np.floor((t - t[0]) / float(interval_s) + _N_INTERVALS_EPS).astype(np.int64)
    out: list[tuple[int, int]] = []
    end = 0  # rows [0, end) fed so far
    held = 0  # the first row the schedule still holds
    for m0 in range(0, total, block):
        m1 = min(m0 + block, total)
        need = int(np.searchsorted(spanned, m1, "left")) + 1  # rows up to the first that covers the block
        if need > end:
            out.append((held, need))
            end = need
        # the block runs now; the schedule keeps the keyframes from the last one at or before its end
        bound = float(interval_bounds_s(t[0], m1, m1, interval_s)[0])
        held += max(int(np.searchsorted(t[held:end], bound, "right")) - 1, 0)
    if end < K:  # keyframes after the last whole interval: fed as well (they change nothing)
        out.append((held, K))
    return out


class Segments:
    """The rate of a block of intervals as affine pieces (the input of event-driven models).

    Intervals ``m0 + start[i] .. m0 + start[i] + length[i] - 1`` form piece ``i``; within
    it, for every pixel p, the exact expected count of interval ``m0 + start[i] + q`` is
    affine in ``q``::

        lambda_first = sum_r w[i, 1, r] * rates[lo[i] + r, p]
        lambda(q)    = lambda_first + q * sum_r w[i, 2, r] * rates[lo[i] + r, p]
        sum over the piece = sum_r w[i, 0, r] * rates[lo[i] + r, p]

    for r < nk[i]. With piecewise-linear keyframes every run of whole intervals between
    two keyframes is one piece (the interval average of a linear rate is its value at
    the interval centre, affine in m); an interval containing a keyframe time is a piece
    of its own. With one rate per interval every interval is a piece. The weights come
    from the same hat-function integrals as :func:`interval_rates`, so both describe the
    same lambda_m (up to float round-off: lambda here is evaluated in float64).
    """

    __slots__ = ("rates", "start", "length", "lo", "nk", "w", "m0", "m1")

    def __init__(self, rates, start, length, lo, nk, w, m0, m1):
        self.rates = np.ascontiguousarray(rates, dtype=np.float32)  # (K, P)
        self.start = np.ascontiguousarray(start, dtype=np.int64)
        self.length = np.ascontiguousarray(length, dtype=np.int64)
        self.lo = np.ascontiguousarray(lo, dtype=np.int64)
        self.nk = np.ascontiguousarray(nk, dtype=np.int64)
        self.w = np.ascontiguousarray(w, dtype=np.float64)  # (n_pieces, 3, nk_max)
        self.m0, self.m1 = int(m0), int(m1)

    @property
    def n_pieces(self) -> int:
        return int(self.start.size)

    def dense(self) -> np.ndarray:
        """lambda (m1 - m0, P) float64, evaluated from the pieces (for tests)."""
        out = np.zeros((self.m1 - self.m0, self.rates.shape[1]))
        for i in range(self.n_pieces):
            r = self.rates[self.lo[i]:self.lo[i] + self.nk[i]].astype(np.float64)
            first = self.w[i, 1, :self.nk[i]] @ r
            slope = self.w[i, 2, :self.nk[i]] @ r
            q = np.arange(self.length[i])[:, None]
            out[self.start[i]:self.start[i] + self.length[i]] = first + q * slope
        return out

    @classmethod
    def per_interval(cls, lam, m0: int = 0) -> "Segments":
        """One piece per interval for lambda given per interval, (B, H, W) or (B, P)."""
        lam = np.asarray(lam, dtype=np.float32)
        B = lam.shape[0]
        w = np.zeros((B, 3, 1))
        w[:, 0, 0] = 1.0
        w[:, 1, 0] = 1.0
        idx = np.arange(B)
        return cls(lam.reshape(B, -1), idx, np.ones(B, np.int64), idx, np.ones(B, np.int64), w, m0, m0 + B)

    @classmethod
    def from_knots(cls, knots_s, rates, t0_s: float, m0: int, m1: int, interval_s: float = INTERVAL_S) -> "Segments":
        """Pieces of intervals [m0, m1) for keyframes (times ``knots_s`` [s], rates (K, ...)) starting at ``t0_s``."""
        t = np.asarray(knots_s, dtype=np.float64)
        rates = np.asarray(rates, dtype=np.float32)
        rates = rates.reshape(rates.shape[0], -1)
        n = m1 - m0
        bounds = interval_bounds_s(t0_s, m0, m1, interval_s)
        a_, b_ = bounds[:-1], bounds[1:]
        tol = _N_INTERVALS_EPS * float(interval_s)
        # knot segment j holding the start of each interval; interior if the interval ends before knot j+1
        j = np.clip(np.searchsorted(t, a_ + tol, "right") - 1, 0, t.size - 2)
        interior = (t[j] <= a_ + tol) & (b_ <= t[j + 1] + tol)
        # runs of interior intervals in the same knot segment are one piece; other intervals one piece each
        key = np.where(interior, j, -1 - np.arange(n))
        new = np.ones(n, bool)
        new[1:] = key[1:] != key[:-1]
        start = np.flatnonzero(new)
        length = np.diff(np.append(start, n))
        last = start + length - 1
        npc = start.size
        lo = np.zeros(npc, np.int64)
        nk = np.full(npc, 2, np.int64)
        first_w = np.zeros((npc, 2))
        last_w = np.zeros((npc, 2))
        pin = interior[start]
        # interior pieces: the interval average is the linear rate at the interval centre
        ji = j[start[pin]]
        lo[pin] = ji
        span = t[ji + 1] - t[ji]
        for wmat, idx in ((first_w, start[pin]), (last_w, last[pin])):
            x = np.clip((0.5 * (a_[idx] + b_[idx]) - t[ji]) / span, 0.0, 1.0)
            wmat[pin, 0], wmat[pin, 1] = 1.0 - x, x
        nkmax = 2
        extra = {}
        if np.any(~pin):  # intervals that contain a keyframe time: full hat-function integral
            sel = np.flatnonzero(~pin)
            ia = start[sel]
            jl = np.clip(np.searchsorted(t, a_[ia], "right") - 1, 0, t.size - 1)
            jh = np.clip(np.searchsorted(t, b_[ia], "left"), 0, t.size - 1)
            jh = np.maximum(jh, jl + 1)
            W = hat_pair_weights(t, a_[ia], b_[ia], interval_s)
            for s, i0, i1, row in zip(sel, jl, jh, W):
                lo[s], nk[s] = i0, i1 - i0 + 1
                extra[s] = row[i0:i1 + 1]
            nkmax = max(nkmax, int(nk.max()))
        w = np.zeros((npc, 3, nkmax))
        w[:, 1, :2] = first_w
        slope = np.where(length[:, None] > 1, (last_w - first_w) / np.maximum(length - 1, 1)[:, None], 0.0)
        w[:, 2, :2] = slope
        w[:, 0, :2] = 0.5 * length[:, None] * (first_w + last_w)
        for s, row in extra.items():
            w[s, :, :] = 0.0
            w[s, 0, :row.size] = row
            w[s, 1, :row.size] = row
        return cls(rates, start, length, lo, nk, w, m0, m1)


class RateSchedule:
    """Streaming buffer of keyframes that hands out lambda for whole blocks of intervals.

    Feed keyframes in time order with :meth:`add`; ask for the lambda of
    intervals ``[m0, m1)`` with :meth:`rates` (dense) or :meth:`segments`
    (affine pieces, for event-driven models) once :meth:`covered` says the
    keyframes reach ``m1``. The result for a block depends only on the
    keyframes around it, never on how the input was chunked, which keeps
    seeded simulations bitwise reproducible across chunk sizes.
    """

    def __init__(self, interval_s: float = INTERVAL_S, per_interval: bool = False):
        self.interval_s = float(interval_s)
        self.per_interval = per_interval
        self._t: np.ndarray = np.zeros(0, np.float64)
        self._chunks: list[np.ndarray] = []  # buffered rows (keyframes, or intervals in per_interval mode)
        self._borrowed: list[bool] = []  # chunk i is a view of a caller's array (add(copy=False))
        self._scratch_pair: list = [None, None]  # reused buffers for gathers that span chunks, in turn
        self._n = 0  # number of buffered rows
        self._shape = None
        self._offset = 0  # per_interval mode: index of the first buffered interval
        self.t0_s: float | None = None

    def add(self, rate_e, t_s=None, copy: bool = True, *, check: bool = True, owned: bool = False,
            overlap: int = 0) -> None:
        """Buffer keyframes ``rate_e`` (K, H, W) at times ``t_s`` (K,) [s] (no ``t_s`` in per-interval mode).

        ``copy=False`` keeps a reference to the caller's array instead of a private copy
        (when no dtype conversion made one anyway); the caller must then call
        :meth:`detach` before it modifies that array (``SpikeSimulator`` does, at the
        end of every feed, so only the few keyframes still needed are ever copied).
        ``owned=True``: the caller hands the array over and never modifies it again, so it is
        kept as it is, without a copy now or at :meth:`detach`.
        ``check=False`` skips :func:`check_rates` (finite, >= 0) for rates the caller has
        already checked (timestamps are always checked).
        ``overlap=n`` (keyframes only): the first ``n`` rows repeat the last ``n`` keyframes added
        (same times, same rates; the times are checked): they replace those rows, so the rows of
        a block can lie in one chunk (:func:`block_keyframe_rows`).
        """
        given = rate_e
        if check and np.asarray(given).dtype.kind not in "biuf":
            raise InputError(f"has dtype {np.asarray(given).dtype}; expected real numbers (float or integer)",
                             field="rate_e")
        rate_e = np.asarray(rate_e, dtype=np.float32)
        # keep a private copy (the caller may reuse its buffer), unless the conversion already made one
        shared = isinstance(given, np.ndarray) and np.may_share_memory(rate_e, given)
        if rate_e.ndim != 3:
            raise InputError(f"rate_e must be (K, H, W); got shape {rate_e.shape}", field="rate_e")
        if self._shape is not None and self._shape != rate_e.shape[1:]:
            raise InputError(f"frame shape changed from {self._shape} to {rate_e.shape[1:]}", field="rate_e")
        if check:
            check_rates(rate_e)
        if self.per_interval:
            if t_s is not None:
                raise InputError("this stream takes one rate per interval (t_s=None)", field="t_s")
            if overlap:
                raise InputError("overlap applies to keyframes (with t_s), not to one rate per interval",
                                 field="overlap")
        else:
            if t_s is None:
                raise InputError("this stream takes keyframes with timestamps t_s", field="t_s")
            t_new = np.asarray(t_s, dtype=np.float64).reshape(-1)
            if t_new.size != rate_e.shape[0]:
                raise InputError(f"{t_new.size} timestamps for {rate_e.shape[0]} keyframes", field="t_s")
            overlap = int(overlap)
            if overlap:
                if not 0 < overlap <= min(self._n, t_new.size) or \
                        not np.array_equal(t_new[:overlap], self._t[self._t.size - overlap:]):
                    raise InputError(f"overlap={overlap}: the first {overlap} keyframe time(s) of this chunk must "
                                     f"repeat the last ones buffered ({self._t[-overlap:].tolist() if self._n else []})",
                                     field="t_s")
                self._t = self._t[:self._t.size - overlap]
                self._drop_last(overlap)
            check_times(t_new, offset=self._t.size)
            allt = np.concatenate([self._t, t_new])
            if np.any(np.diff(allt) <= 0):
                i = int(np.argmax(np.diff(allt) <= 0))
                raise InputError(f"keyframe times must increase strictly across all chunks; t_s[{i}] = {float(allt[i])!r}, "
                                 f"t_s[{i + 1}] = {float(allt[i + 1])!r}", field="t_s")
            if self.t0_s is None and t_new.size:
                self.t0_s = float(t_new[0])
            self._t = allt
        self._shape = rate_e.shape[1:]
        if rate_e.shape[0]:
            if owned:
                shared = False
            elif shared and copy:
                rate_e, shared = rate_e.copy(), False
            self._chunks.append(rate_e)
            self._borrowed.append(shared)
            self._n += rate_e.shape[0]

    def detach(self) -> None:
        """Copy the buffered rows that still reference a caller's array (see ``add(copy=False)``)."""
        for i, b in enumerate(self._borrowed):
            if b:
                self._chunks[i] = self._chunks[i].copy()
                self._borrowed[i] = False

    def _gather(self, lo: int, hi: int, scratch: bool = False) -> np.ndarray:
        """Buffered rows [lo, hi) as one array (a view when they lie in one chunk).

        ``scratch=True``: rows spanning chunks are joined in one of two buffers used in turn (no fresh
        allocation per block), valid until the next call but one.
        """
        parts, pos = [], 0
        for c in self._chunks:
            a, b = max(lo - pos, 0), min(hi - pos, c.shape[0])
            if a < b:
                parts.append(c[a:b])
            pos += c.shape[0]
            if pos >= hi:
                break
        if len(parts) == 1:
            return parts[0]
        if not scratch:
            return np.concatenate(parts)
        n = hi - lo
        row = parts[0].shape[1:]
        # two buffers, used in turn: a block in flight (SpikeSimulator's lookahead) still reads the rows of
        # the previous call while the next block's are joined
        self._scratch_pair.reverse()
        buf = self._scratch_pair[0]
        if buf is None or buf.shape[0] < n or buf.shape[1:] != row:
            buf = self._scratch_pair[0] = np.empty((max(n, 2 * n if buf is None else n),) + row, np.float32)
        return np.concatenate(parts, out=buf[:n])

    def _drop_last(self, n: int) -> None:
        """Forget the last ``n`` buffered rows."""
        while n > 0 and self._chunks:
            c = self._chunks[-1]
            if c.shape[0] <= n:
                n -= c.shape[0]
                self._n -= c.shape[0]
                self._chunks.pop()
                self._borrowed.pop()
            else:
                self._chunks[-1] = c[:c.shape[0] - n]
                self._n -= n
                n = 0

    def _drop(self, n: int) -> None:
        """Forget the first ``n`` buffered rows."""
        while n > 0 and self._chunks:
            c = self._chunks[0]
            if c.shape[0] <= n:
                n -= c.shape[0]
                self._n -= c.shape[0]
                self._chunks.pop(0)
                self._borrowed.pop(0)
            else:
                self._chunks[0] = c[n:]
                self._n -= n
                n = 0

    @property
    def frame_shape(self):
        return self._shape

    def covered(self) -> int:
        """Number of intervals (from interval 0) that the buffered keyframes fully determine."""
        if self._shape is None:
            return 0
        if self.per_interval:
            return self._offset + self._n
        if self._t.size < 2:
            return 0
        return n_intervals_spanned(self.t0_s, self._t[-1], self.interval_s)

    def _knot_range(self, m0: int, m1: int):
        bounds = interval_bounds_s(self.t0_s, m0, m1, self.interval_s)
        lo, hi, keep = _knots_of(self._t, bounds)
        return bounds, lo, hi, keep

    def _forget_knots(self, keep: int) -> None:
        self._t = self._t[keep:]
        self._drop(keep)

    def rates(self, m0: int, m1: int) -> np.ndarray:
        """lambda for intervals [m0, m1), float32 (m1-m0, H, W); drops keyframes no longer needed."""
        if m1 > self.covered():
            raise InputError(f"intervals up to {m1} requested but keyframes cover only {self.covered()}")
        if self.per_interval:
            out = self._gather(m0 - self._offset, m1 - self._offset)
            self._drop(m1 - self._offset)
            self._offset = m1
            return out
        bounds, lo, hi, keep = self._knot_range(m0, m1)
        t = self._t
        W = hat_interval_weights(t[lo:hi + 1], bounds, self.interval_s).astype(np.float32)
        r = self._gather(lo, hi + 1)
        K, H, Wd = r.shape
        out = (W @ r.reshape(K, H * Wd)).reshape(m1 - m0, H, Wd)
        self._forget_knots(keep)
        return out

    def segments(self, m0: int, m1: int) -> Segments:
        """The rate of intervals [m0, m1) as affine :class:`Segments`; drops keyframes no longer needed.

        ``Segments.rates`` may be a view of the buffered keyframes or of a scratch buffer:
        use it before the next call but one.
        """
        if m1 > self.covered():
            raise InputError(f"intervals up to {m1} requested but keyframes cover only {self.covered()}")
        if self.per_interval:
            seg = Segments.per_interval(self._gather(m0 - self._offset, m1 - self._offset, scratch=True), m0)
            self._drop(m1 - self._offset)
            self._offset = m1
            return seg
        bounds, lo, hi, keep = self._knot_range(m0, m1)
        seg = Segments.from_knots(self._t[lo:hi + 1], self._gather(lo, hi + 1, scratch=True), self.t0_s, m0, m1,
                                  self.interval_s)
        self._forget_knots(keep)
        return seg

    def knots(self):
        """Buffered keyframe times [s] and rates (K, H, W)."""
        return self._t, (np.array(self._gather(0, self._n)) if self._n else None)
