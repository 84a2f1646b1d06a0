"""The numba kernels of the event-driven ("fast") spike models, and the samplers they draw with.

Why this is the same model as the step simulator (:class:`sensor.models.step.ELSSimStep`)
-----------------------------------------------------------------------------------
For a pixel that is not hot, one interval of Algorithm 2 adds ``g * n_m`` with
``n_m ~ Poisson(lambda'_m)`` (``lambda'_m = lambda_m (1 - f)`` in the interval
after a spike, Eq. 6), plus a full threshold when a dark event occurs
(probability ``p = 1 - exp(-mu_DC)``, Eq. 1), then fires and resets to zero.
Hence, since the last reset:

* the light fires in the first interval in which the photoelectron count reaches
  ``k = ceil(theta / g)`` (:func:`sensor.models.effects.count_threshold`). Counts of
  disjoint intervals are independent Poisson variables, so the count is a unit
  Poisson process in the rescaled time ``Lambda = sum of lambda'_m``, and the
  count reaches ``k`` exactly when ``Lambda`` passes the k-th arrival time
  ``Gamma ~ Gamma(k, 1)`` (time rescaling). One Gamma variate per spike
  replaces one Poisson variate per interval;
* dark events are an independent Bernoulli(p) process over intervals, so the
  next one comes after a Geometric(p) gap (memoryless, so a pending dark event
  survives a light spike unchanged);
* the spike comes at the earlier of the two; either resets the integrator
  (excess discarded), so a new Gamma is drawn and the next interval is the
  refractory one.

This is exact in distribution (not an approximation); only the random numbers
differ from the step simulator, so the two agree statistically, never bitwise.
Hot pixels (Eq. 4, Gaussian charge that may be negative, clipped at zero) have
no such shortcut; the few of them (0.1 % in ``vidar-default``) take the step
path inside the same kernel, in exactly the order of Algorithm 2. Under the crossing
reset a hot pixel's charge is walked event by event in continuous time; with
``dark == "current"`` (no dark events) it rises monotonically over any run of
intervals whose hot current is >= 0, so one Poisson count per such stretch says
whether it fires there, and a search among the order statistics of the arrivals
finds when (:func:`_hot_crossing_piece_current`), exact in distribution as well.

``ideal`` is deterministic: the fast path skips whole pieces while the charge
stays below threshold and steps otherwise; with one rate per interval it is
bitwise identical to the reference; with keyframes lambda_m is evaluated in
float64 from the pieces instead of a float32 matrix product, so a spike can move
by one interval where the charge meets the threshold within float round-off.
``isi`` draws the same Gamma inter-spike intervals as the reference, skipping
the intervals in between.

Each ``*_tile`` kernel runs one block (all its pieces) over one tile of pixels, carrying the
tile's state in place and OR-ing its spikes into the packed output; :mod:`sensor.models.fast`
cuts the pixels into tiles and runs them on a thread pool.

Needs ``numba``; without it :data:`HAVE_NUMBA` is False and no kernel is defined.
"""

from __future__ import annotations

import math

import numpy as np

try:  # pragma: no cover - exercised by the environment, not by a test toggle
    import numba
    from numba import njit
    HAVE_NUMBA = True
except ImportError:  # pragma: no cover
    numba = None
    HAVE_NUMBA = False

#: pixels per sub-chunk inside a tile: the kernel runs all pieces of a block on one sub-chunk at a time
SUB_PIXELS = 512
#: "never" for the next dark event (int64)
_NEVER = np.int64(1) << np.int64(62)

# ----------------------------------------------------------------------------------------------- kernels
if HAVE_NUMBA:
    _jit = njit(nogil=True, cache=True, error_model="numpy")
    _jit_inline = njit(nogil=True, cache=True, inline="always", error_model="numpy")

    @_jit_inline
    def _rotl(x, k):
        return (x << np.uint64(k)) | (x >> np.uint64(64 - k))

    @_jit_inline
    def _uniform(xs):
        """U[0, 1) with 53 random bits from the tile's xoshiro256+ state ``xs`` (uint64[4])."""
        s0, s1, s2, s3 = xs[0], xs[1], xs[2], xs[3]
        r = s0 + s3
        t = s1 << np.uint64(17)
        s2 ^= s0
        s3 ^= s1
        s1 ^= s2
        s0 ^= s3
        s2 ^= t
        s3 = _rotl(s3, 45)
        xs[0], xs[1], xs[2], xs[3] = s0, s1, s2, s3
        return np.float64(r >> np.uint64(11)) * 1.1102230246251565e-16

    @_jit_inline
    def _gamma(rng, xs, b, c):
        """Gamma(k, 1) for k >= 1 (b = k - 1/3, c = 1/sqrt(9b)): Marsaglia-Tsang, as numpy's standard_gamma.

        With x ~ N(0, 1), v = (1 + c x)^3 and u ~ U(0, 1), ``b v`` is accepted iff
        u < exp(h), h = x^2/2 + b (1 - v + log v). Expanding log(1 + y), y = c x, the
        x^2 terms cancel exactly (9 b c^2 = 1): h = 3 b (-y^4/4 + y^5/5 - y^6/6 + ...), and for
        |y| <= 1/2 the tail beyond y^5 is >= -y^6/3, so h >= h_low = 3 b y^4 (-1/4 + y/5 - y^2/3).
        Since exp(h) >= 1 + h >= 1 + h_low, ``u < 1 + h_low`` accepts without a logarithm (for
        large k almost always); otherwise numpy's squeeze and exact test decide. Every branch
        accepts only when u < exp(h): the law is exactly Marsaglia-Tsang's.
        """
        while True:
            x = rng.standard_normal()
            v = 1.0 + c * x
            while v <= 0.0:
                x = rng.standard_normal()
                v = 1.0 + c * x
            y = v - 1.0
            v = v * v * v
            u = _uniform(xs)
            if abs(y) <= 0.5:
                y2 = y * y
                if u < 1.0 + 3.0 * b * y2 * y2 * (-0.25 + 0.2 * y - y2 / 3.0):
                    return b * v
            if u < 1.0 - 0.0331 * (x * x) * (x * x):
                return b * v
            if math.log(u) < 0.5 * x * x + b * (1.0 - v + math.log(v)):
                return b * v

    @_jit_inline
    def _gamma_int(rng, xs, a):
        """Gamma(a, 1) for a >= 1 (:func:`_gamma` with its constants made here)."""
        b = a - 1.0 / 3.0
        return _gamma(rng, xs, b, 1.0 / math.sqrt(9.0 * b))

    @_jit_inline
    def _beta_int(rng, xs, a, b):
        """Beta(a, b) for integers a, b >= 1: ``U^(1/a)`` when b = 1, ``1 - U^(1/b)`` when a = 1, else
        ``X / (X + Y)`` with X ~ Gamma(a, 1), Y ~ Gamma(b, 1)."""
        if b == 1:
            return _uniform(xs) ** (1.0 / a)
        if a == 1:
            return 1.0 - _uniform(xs) ** (1.0 / b)
        x = _gamma_int(rng, xs, np.float64(a))
        return x / (x + _gamma_int(rng, xs, np.float64(b)))

    @_jit_inline
    def _geometric(rng, inv):
        """Geometric(p) on {1, 2, ...} by inversion, ``inv = -1 / log(1 - p)`` (as numpy's for small p)."""
        g = math.ceil(rng.standard_exponential() * inv)
        if g < 1.0:
            return np.int64(1)
        if g > 4.0e18:
            return _NEVER
        return np.int64(g)

    _INV = 1.0 / np.arange(1, 65, dtype=np.float64)

    @_jit_inline
    def _poisson(rng, xs, lam):
        """Poisson(lam): inversion (chop-down search, one uniform) for lam < 30, numpy's PTRS otherwise."""
        if lam <= 0.0:
            return 0.0
        if lam < 30.0:
            u = _uniform(xs)
            p = math.exp(-lam)
            x = 0
            while u > p:
                u -= p
                x += 1
                p *= lam * (_INV[x - 1] if x <= 64 else 1.0 / x)
                if p == 0.0:
                    break
            return float(x)
        return float(rng.poisson(lam))

    @_jit_inline
    def _piece_coeffs(R, w, i, lo, nk, p):
        s = 0.0
        l0 = 0.0
        sl = 0.0
        for r in range(nk):
            x = np.float64(R[lo + r, p])
            s += w[i, 0, r] * x
            l0 += w[i, 1, r] * x
            sl += w[i, 2, r] * x
        return s, l0, sl

    @_jit_inline
    def _piece_coeffs_dc(R, w, i, lo, nk, p, n, dc, use_dc):
        """:func:`_piece_coeffs` of the pixel's electron rate: with ``use_dc`` its dark current ``dc[p]``
        [e-/interval] adds to the light of every interval (``l0``) and ``n dc[p]`` to the piece's total ``s``."""
        s, l0, sl = _piece_coeffs(R, w, i, lo, nk, p)
        if use_dc:
            s += n * dc[p]
            l0 += dc[p]
        return s, l0, sl

    @_jit_inline
    def _crossing(rp, A, beta, nmax):
        """Smallest x in 1..nmax with C(x) = A x + beta x (x - 1) / 2 >= rp, given C(nmax) >= rp.

        C(x) is the expected count of x intervals whose lambda starts at A and changes by beta per
        interval (lambda >= 0 throughout, so C increases with x). The root of the quadratic gives
        the answer up to round-off; the two loops make it exact for the float C.
        """
        b2 = A - 0.5 * beta
        disc = b2 * b2 + 2.0 * beta * rp
        den = b2 + math.sqrt(disc) if disc > 0.0 else b2
        x = math.ceil(2.0 * rp / den) if den > 0.0 else float(nmax)
        xi = np.int64(min(max(x, 1.0), float(nmax)))
        while xi > 1 and (xi - 1) * A + beta * 0.5 * (xi - 1) * (xi - 2) >= rp:
            xi -= 1
        while xi < nmax and xi * A + beta * 0.5 * xi * (xi - 1) < rp:
            xi += 1
        return xi

    @_jit_inline
    def _subtract_and_flag(R, w, i, lo, nk, c0, nt, rm, gd, limit, flag, n, dc, use_dc):
        """Pass 1 of the ELSSim kernels (vectorised): subtract piece i's light from the targets ``rm``; flag the
        pixels whose target is reached or whose ``guard`` (an event time, or a "must look" sentinel) is < ``limit``.
        With ``use_dc`` the dark current ``dc`` [e-/interval] adds ``n dc`` to each pixel's piece (``n`` intervals)."""
        if use_dc and nk == 2:
            nf = np.float64(n)
            w00 = w[i, 0, 0]
            w01 = w[i, 0, 1]
            R0 = R[lo, c0:c0 + nt]
            R1 = R[lo + 1, c0:c0 + nt]
            d = dc[c0:c0 + nt]
            for t in range(nt):
                r_ = rm[t] - ((w00 * np.float64(R0[t]) + w01 * np.float64(R1[t])) + nf * d[t])
                rm[t] = r_
                flag[t] = np.uint8(r_ <= 0.0) | np.uint8(gd[t] < limit)
        elif use_dc:
            nf = np.float64(n)
            for t in range(nt):
                s = 0.0
                for r in range(nk):
                    s += w[i, 0, r] * np.float64(R[lo + r, c0 + t])
                r_ = rm[t] - (s + nf * dc[c0 + t])
                rm[t] = r_
                flag[t] = np.uint8(r_ <= 0.0) | np.uint8(gd[t] < limit)
        elif nk == 2:
            w00 = w[i, 0, 0]
            w01 = w[i, 0, 1]
            R0 = R[lo, c0:c0 + nt]
            R1 = R[lo + 1, c0:c0 + nt]
            for t in range(nt):
                r_ = rm[t] - (w00 * np.float64(R0[t]) + w01 * np.float64(R1[t]))
                rm[t] = r_
                flag[t] = np.uint8(r_ <= 0.0) | np.uint8(gd[t] < limit)
        else:
            for t in range(nt):
                s = 0.0
                for r in range(nk):
                    s += w[i, 0, r] * np.float64(R[lo + r, c0 + t])
                r_ = rm[t] - s
                rm[t] = r_
                flag[t] = np.uint8(r_ <= 0.0) | np.uint8(gd[t] < limit)

    @_jit_inline
    def _lockstep(rng, xs, R, w, i, lo, nk, a, n, m0, c0, nt, gb, gc, omf, dinv, rem, dark_next, refr, guard,
                  out, l0v, slv, rmv, jdv, flag, idx, dc, use_dc):
        """Piece ``i`` of sub-chunk ``c0`` for every pixel, one interval at a time (see elssim_tile)."""
        big = np.int64(1) << np.int64(40)
        for t in range(nt):
            p = c0 + t
            s = 0.0
            l0 = 0.0
            sl = 0.0
            for r in range(nk):
                x = np.float64(R[lo + r, p])
                s += w[i, 0, r] * x
                l0 += w[i, 1, r] * x
                sl += w[i, 2, r] * x
            if use_dc:
                s += n * dc[p]
                l0 += dc[p]
            l0v[t] = l0
            slv[t] = sl
            rp = rem[p] + s  # undo pass 1
            if refr[p]:
                rp += (1.0 - omf[p]) * l0
            rmv[t] = rp
            jdv[t] = dark_next[p] - a if rp != np.inf else big  # hot pixels: never here
        for q in range(n):
            for t in range(nt):  # vectorised
                r_ = rmv[t] - (l0v[t] + slv[t] * q)
                rmv[t] = r_
                flag[t] = np.uint8(r_ <= 0.0) | np.uint8(jdv[t] == q)
            cnt = 0
            for t in range(nt):
                idx[cnt] = t
                cnt += flag[t]
            m = a + q
            row = m - m0
            for c_ in range(cnt):
                t = idx[c_]
                p = c0 + t
                out[row, p >> 3] |= np.uint8(1 << (p & 7))
                rp = _gamma(rng, xs, gb[p], gc[p])
                if q + 1 < n:  # the next interval is the refractory one: fold f * lambda into the target
                    rp += (1.0 - omf[p]) * (l0v[t] + slv[t] * (q + 1))
                rmv[t] = rp
                if jdv[t] == q:
                    jdv[t] = q + _geometric(rng, dinv[p])
                flag[t] = 2  # spiked at q
        for t in range(nt):
            p = c0 + t
            if rmv[t] == np.inf:
                continue
            rem[p] = rmv[t]
            rf = np.uint8(1) if flag[t] == 2 else np.uint8(0)  # spiked in the last interval
            refr[p] = rf
            dn = a + jdv[t]
            dark_next[p] = dn
            guard[p] = -1 if rf else dn

    @_jit
    def elssim_tile(rng, xs, R, start, length, lo_, nk_, w, m0, p0, p1, hot_idx,
                     gb, gc, omf, dinv, has_dark, gain, hot_mu, hot_sigma, theta,
                     rem, dark_next, refr, guard, v, out, dc, use_dc):
        """``elssim`` with the interval reset over one tile (see the module doc). ``dc`` [e-/interval] is each
        pixel's dark current, added to its light when ``use_dc`` (``dark == "current"``); dark events otherwise."""
        # ---- first block: draw the initial state
        for p in range(p0, p1):
            if rem[p] != rem[p]:  # NaN: not drawn yet
                rem[p] = _gamma(rng, xs, gb[p], gc[p])
                dark_next[p] = m0 - 1 + _geometric(rng, dinv[p]) if has_dark[p] else _NEVER
        for p in range(p0, p1):
            guard[p] = -1 if refr[p] else dark_next[p]
        for h in hot_idx:
            rem[h] = np.inf  # hot pixels never take the event path
            guard[h] = _NEVER
        npc = start.size
        flag = np.zeros(SUB_PIXELS, np.uint8)
        idx = np.empty(SUB_PIXELS + 1, np.int64)
        l0v = np.empty(SUB_PIXELS)
        slv = np.empty(SUB_PIXELS)
        rmv = np.empty(SUB_PIXELS)
        jdv = np.empty(SUB_PIXELS, np.int64)
        # sub-chunks of SUB_PIXELS pixels, all pieces of the block each: the state stays in L1/L2
        for c0 in range(p0, p1, SUB_PIXELS):
            c1 = min(c0 + SUB_PIXELS, p1)
            nt = c1 - c0
            for i in range(npc):
                a = m0 + start[i]
                n = length[i]
                end = a + n
                lo = lo_[i]
                nk = nk_[i]
                # ---- pass 1 (vectorised): subtract the piece's expected count; flag pixels that may spike
                # (guard = dark_next, or -1 while the next interval is a refractory one)
                _subtract_and_flag(R, w, i, lo, nk, c0, nt, rem[c0:c1], guard[c0:c1], end, flag, n, dc, use_dc)
                # ---- pass 2: the flagged pixels, event by event (compacted first: no branch per pixel)
                cnt = 0
                for t in range(nt):
                    idx[cnt] = t
                    cnt += flag[t]
                if cnt * 4 > nt and n > 1:
                    # most pixels spike here (bright light): step all pixels interval by interval in
                    # lock-step, vectorised; the same algorithm as below, without per-pixel branches
                    _lockstep(rng, xs, R, w, i, lo, nk, a, n, m0, c0, nt, gb, gc, omf, dinv, rem, dark_next,
                              refr, guard, out, l0v, slv, rmv, jdv, flag, idx, dc, use_dc)
                    continue
                for c_ in range(cnt):
                    p = c0 + idx[c_]
                    if rem[p] == np.inf:
                        continue  # hot pixel
                    s, l0, sl = _piece_coeffs_dc(R, w, i, lo, nk, p, n, dc, use_dc)
                    rp = rem[p] + s  # undo pass 1: this piece is now taken interval by interval
                    fp = 1.0 - omf[p]
                    dn = dark_next[p]
                    # Refractory (Eq. 6): the interval after a spike collects lambda (1 - f), which is the
                    # same as adding f * lambda of that interval to the target of the new count.
                    if refr[p]:
                        rp += fp * l0
                    rf = 0
                    q = 0
                    jd = dn - a  # the dark event, relative to the piece
                    while True:
                        # no light crossing in the rest of the piece?
                        rest = (n - q) * (l0 + sl * q) + sl * 0.5 * (n - q) * (n - q - 1)
                        if rest < rp:
                            if jd >= n:
                                rp -= rest
                                break
                            j = jd
                        else:  # the first interval where the count reaches the target
                            A = l0 + sl * q
                            if rp <= 4.0 * A:  # a few intervals away: step
                                j = q
                                c = A
                                while c < rp and j < n - 1:
                                    j += 1
                                    c += l0 + sl * j
                            else:  # closed form
                                j = q - 1 + _crossing(rp, A, sl, n - q)
                            if jd < j:
                                j = jd
                        m = a + j
                        out[m - m0, p >> 3] |= np.uint8(1 << (p & 7))
                        rp = _gamma(rng, xs, gb[p], gc[p])
                        if jd == j:
                            dn = m + _geometric(rng, dinv[p])
                            jd = dn - a
                        q = j + 1
                        if q >= n:
                            rf = 1  # the refractory interval is the first of the next piece
                            break
                        rp += fp * (l0 + sl * q)
                    rem[p] = rp
                    refr[p] = rf
                    dark_next[p] = dn
                    guard[p] = -1 if rf else dn
        # ---- hot pixels: the step simulator, in the order of Algorithm 2
        for i in range(npc):
            a = m0 + start[i]
            n = length[i]
            lo = lo_[i]
            nk = nk_[i]
            for h in hot_idx:
                s, l0, sl = _piece_coeffs_dc(R, w, i, lo, nk, h, n, dc, use_dc)
                for q in range(n):
                    m = a + q
                    lam = l0 + sl * q
                    if refr[h]:
                        lam *= omf[h]
                    vv = v[h] + gain[h] * _poisson(rng, xs, lam)
                    if dark_next[h] == m:
                        vv += theta
                        dark_next[h] = m + _geometric(rng, dinv[h])
                    vv += (hot_mu[h] + hot_sigma[h] * rng.standard_normal()) * theta
                    if vv < 0.0:
                        vv = 0.0
                    if vv >= theta:
                        out[m - m0, h >> 3] |= np.uint8(1 << (h & 7))
                        vv = 0.0
                        refr[h] = 1
                    else:
                        refr[h] = 0
                    v[h] = vv

    @_jit
    def ideal_tile(R, start, length, lo_, nk_, w, m0, p0, p1, theta, v, out):
        npc = start.size
        flag = np.zeros(SUB_PIXELS, np.uint8)
        idx = np.empty(SUB_PIXELS + 1, np.int64)
        for c0 in range(p0, p1, SUB_PIXELS):
            c1 = min(c0 + SUB_PIXELS, p1)
            nt = c1 - c0
            vs = v[c0:c1]
            for i in range(npc):
                a = m0 + start[i]
                n = length[i]
                lo = lo_[i]
                nk = nk_[i]
                # ---- pass 1 (vectorised): add the piece when the charge stays below threshold
                for t in range(nt):
                    s = 0.0
                    for r in range(nk):
                        s += w[i, 0, r] * np.float64(R[lo + r, c0 + t])
                    vv = vs[t] + s
                    f = vv >= theta
                    flag[t] = np.uint8(f)
                    vs[t] = vs[t] if f else vv
                cnt = 0
                for t in range(nt):
                    idx[cnt] = t
                    cnt += flag[t]
                # ---- pass 2: the pixels that reach the threshold in this piece, interval by interval
                for c_ in range(cnt):
                    t = idx[c_]
                    p = c0 + t
                    vp = vs[t]
                    if n == 1:  # one interval: the reference's very operation, V += lambda_m
                        out[a - m0, p >> 3] |= np.uint8(1 << (p & 7))
                        vs[t] = 0.0
                        continue
                    s, l0, sl = _piece_coeffs(R, w, i, lo, nk, p)
                    for q in range(n):
                        vp += l0 + sl * q
                        if vp >= theta:
                            out[a + q - m0, p >> 3] |= np.uint8(1 << (p & 7))
                            vp = 0.0
                    vs[t] = vp

    @_jit
    def isi_tile(rng, xs, R, start, length, lo_, nk_, w, m0, p0, p1, gb, gc, dark_q, tau, out):
        npc = start.size
        flag = np.zeros(SUB_PIXELS, np.uint8)
        idx = np.empty(SUB_PIXELS + 1, np.int64)
        for c0 in range(p0, p1, SUB_PIXELS):
            c1 = min(c0 + SUB_PIXELS, p1)
            nt = c1 - c0
            ts = tau[c0:c1]
            for i in range(npc):
                a = m0 + start[i]
                n = length[i]
                end = a + n
                lo = lo_[i]
                nk = nk_[i]
                # pass 1: pixels whose next firing falls in this piece (or is not drawn yet: NaN)
                for t_ in range(nt):
                    flag[t_] = np.uint8(not (ts[t_] >= end))
                cnt = 0
                for t_ in range(nt):
                    idx[cnt] = t_
                    cnt += flag[t_]
                for c_ in range(cnt):
                    p = c0 + idx[c_]
                    s, l0, sl = _piece_coeffs(R, w, i, lo, nk, p)
                    if tau[p] != tau[p] and dark_q[p] <= 0.0 and l0 <= 0.0 and l0 + sl * (n - 1) <= 0.0:
                        continue  # no charge anywhere in this piece
                    for q in range(n):
                        m = a + q
                        qq = (l0 + sl * q) + dark_q[p]  # photoelectron-equivalents per interval
                        t = tau[p]
                        if t != t:
                            if qq > 0.0:
                                t = m + _gamma(rng, xs, gb[p], gc[p]) / qq
                            else:
                                continue
                        if t < m + 1:
                            out[m - m0, p >> 3] |= np.uint8(1 << (p & 7))
                            while t < m + 1:
                                if qq > 0.0:
                                    t = t + _gamma(rng, xs, gb[p], gc[p]) / qq
                                else:
                                    t = np.nan
                                    break
                        tau[p] = t
                        if t >= end:
                            break

    @_jit_inline
    def _exp_gap(rng, rate):
        """Exp(rate) waiting time [intervals] (inf when rate <= 0)."""
        if rate <= 0.0:
            return np.inf
        return rng.standard_exponential() / rate

    @_jit_inline
    def _hot_crossing_interval(rng, xs, mq, m0, lam, cur, h, g, theta, frh, muh, v, blind, dark_next, out,
                               scratch):
        """Hot pixel ``h`` through interval ``mq`` under the crossing reset, window by window (a window ends at the
        next dark event or the interval end): the photoelectron count of the window, and when a firing or the
        clip at 0 is possible, its arrivals (iid uniform times given their number) walked in time order, the
        current's crossing solved linearly. ``cur`` [e-/interval] is the interval's hot current, ``lam``
        [e-/interval] its photoelectron rate; updates ``v[h]``, ``blind[h]``, ``dark_next[h]``."""
        m = np.float64(mq)
        sp = blind[h] if blind[h] > m else m
        vv = v[h]
        while sp < m + 1.0:
            d = dark_next[h]
            if d < sp:  # fell in the blind time: lost (memoryless: the next one from sp)
                d = sp + _exp_gap(rng, muh)
                dark_next[h] = d
            wend = d if d < m + 1.0 else m + 1.0
            L = wend - sp
            nph = _poisson(rng, xs, lam * L)  # photoelectrons in the window
            tau = np.inf
            if vv + g * nph + (cur if cur > 0.0 else 0.0) * L < theta and (cur >= 0.0 or vv + cur * L >= 0.0):
                # no firing and no clipping possible in the window: only the end charge matters
                vv = vv + g * nph + cur * L
            else:  # walk the arrivals in time order
                ne = np.int64(nph)
                arr = scratch if ne < scratch.size else np.empty(ne + 1)
                for e in range(ne):
                    arr[e] = sp + L * _uniform(xs)
                arr[:ne].sort()
                arr[ne] = wend
                t0 = sp
                for e in range(ne + 1):
                    tn = arr[e]
                    if cur > 0.0 and vv + cur * (tn - t0) >= theta:
                        tau = t0 + (theta - vv) / cur
                        break
                    vv = vv + cur * (tn - t0)
                    if vv < 0.0:
                        vv = 0.0
                    t0 = tn
                    if e < ne:
                        vv += g
                        if vv >= theta:
                            tau = tn
                            break
            if tau == np.inf and d < m + 1.0:
                tau = d
            if tau == np.inf:
                break
            mi = np.int64(tau)
            if mi > mq:
                mi = mq
            out[mi - m0, h >> 3] |= np.uint8(1 << (h & 7))
            vv = 0.0
            sp = tau + frh
            blind[h] = sp
            if dark_next[h] <= sp:
                dark_next[h] = sp + _exp_gap(rng, muh)
        v[h] = vv

    @_jit_inline
    def _last_at_most(c, k, x, r):
        """Largest r in 0..k-1 with c[r] <= x (c nondecreasing, c[0] <= x), walked from the guess ``r``."""
        if r > k - 1:
            r = k - 1
        while r > 0 and c[r] > x:
            r -= 1
        while r < k - 1 and c[r + 1] <= x:
            r += 1
        return r

    @_jit_inline
    def _last_below(c, k, y, r):
        """Largest r in 0..k-1 with c[r] < y (c nondecreasing, c[0] < y), walked from the guess ``r``."""
        if r > k - 1:
            r = k - 1
        while r > 0 and c[r] >= y:
            r -= 1
        while r < k - 1 and c[r + 1] < y:
            r += 1
        return r

    @_jit_inline
    def _stretch_first_passage(rng, xs, nph, D, g, k, tb, lc, zc, lamv, curv):
        """First time [intervals] at which a hot pixel's charge, rising from ``theta - D`` (``D > 0``), reaches
        theta in a stretch of ``k`` intervals (or parts of intervals) with currents >= 0, given that its
        ``nph`` photoelectrons reach it: ``zc[k] + g nph >= D``.

        Stretch part r runs from ``tb[r]`` to ``tb[r + 1]`` with photoelectron rate ``lamv[r]`` and current
        ``curv[r]`` [e-/interval]; ``lc``, ``zc`` are the cumulative expected photoelectrons and current charge
        at the part starts (``lc[0] = zc[0] = 0``). The photoelectrons are a Poisson process: given their
        number, their rescaled times ``Lambda(T_j) / lc[k]`` are the order statistics of ``nph`` uniforms. The
        charge ``Z(t) + g N(t)`` only rises, so the firing comes at arrival j iff
        ``c_j: Z(T_j) + g j >= D``, false up to some j' and true after (T_j and Z increase with j); a
        bisection finds J = j' + 1 from O(log nph) order statistics, each drawn given the two around it (the
        j-th of the uniforms between known ones at ranks j_l < j < j_h, values u_l < u_h, is
        ``u_l + (u_h - u_l) Beta(j - j_l, j_h - j)``). Between T_j' and T_J (the stretch end when
        J = nph + 1) only the current moves the charge: the firing is the earlier of T_J and the time the
        current brings Z to ``D - g j'``. Exact in distribution: the walk over every arrival, drawing only the
        arrivals it looks at."""
        ltot = lc[k]
        jl = np.int64(0)
        ul = 0.0
        fl = -D  # c_j's margin, Z(T_j) + g j - D, at the known ranks jl (< 0) and jh (>= 0)
        jh = np.int64(nph) + 1
        uh = 1.0
        fh = zc[k] + g * jh - D
        th = tb[k]  # time of arrival jh (the stretch end while jh = nph + 1)
        r = k - 1  # the stretch part of the last order statistic drawn
        interp = True
        while jh - jl > 1:
            # the next rank to look at: where the margin's chord crosses 0 (few steps: the margin is close to
            # linear in j), the middle after a step that did not halve the bracket. Any rule that uses only what
            # is drawn keeps the law.
            if interp:
                jm = jl + np.int64((jh - jl) * (-fl / (fh - fl)) + 0.5)
                if jm <= jl:
                    jm = jl + 1
                elif jm >= jh:
                    jm = jh - 1
            else:
                jm = (jl + jh) >> 1
            width = jh - jl
            um = ul + (uh - ul) * _beta_int(rng, xs, jm - jl, jh - jm)
            x = um * ltot
            r = _last_at_most(lc, k, x, r)
            t = tb[r] + (x - lc[r]) / lamv[r] if lamv[r] > 0.0 else tb[r + 1]
            if t > tb[r + 1]:
                t = tb[r + 1]
            fm = zc[r] + curv[r] * (t - tb[r]) + g * jm - D
            if fm >= 0.0:
                jh = jm
                uh = um
                fh = fm
                th = t
            else:
                jl = jm
                ul = um
                fl = fm
            interp = 2 * (jh - jl) <= width
        y = D - g * jl  # charge the current still has to bring after arrival jl (> 0)
        if zc[k] < y:
            return th
        r = _last_below(zc, k, y, r)  # zc[r] < y <= zc[r + 1]: curv[r] > 0
        t = tb[r] + (y - zc[r]) / curv[r]
        if t > tb[r + 1]:
            t = tb[r + 1]
        return t if t < th else th

    @_jit_inline
    def _hot_crossing_piece_current(rng, xs, a, n, m0, l0, sl, h, g, hmu, hsig, theta, frh, v, blind, dark_next,
                                    out, scratch, curq, tb, lc, zc, lamv, curv):
        """Hot pixel ``h`` through one piece (intervals ``a .. a + n - 1``, photoelectron rate ``l0 + sl q``
        [e-/interval], the dark current included) with ``dark == "current"`` (no dark events), in stretches.

        A stretch is a run of intervals whose hot current (drawn first, one per interval, as the step path)
        is >= 0, from the current time; the charge then only rises, so it fires in the stretch iff its end
        charge (current charge plus ``g`` times one Poisson count of the whole stretch) reaches theta, and
        :func:`_stretch_first_passage` finds when. After a firing the pixel is blind, the rest of the stretch's
        photoelectrons are not used (the Poisson process after the firing time, a stopping time, is a fresh
        one) and a new stretch starts at the end of the blind time. A stretch stops once its expected charge
        reaches 1.15 times what is missing (decided from the currents and rates, never from the count it then
        draws). An interval with a negative current (the charge may clip at 0) goes through
        :func:`_hot_crossing_interval`. One Poisson variate per stretch instead of one per interval."""
        for q in range(n):
            curq[q] = (hmu + hsig * rng.standard_normal()) * theta
        q = np.int64(0)
        while q < n:
            m = np.float64(a + q)
            sp = blind[h] if blind[h] > m else m
            if sp >= m + 1.0:
                q += 1
                continue
            if curq[q] < 0.0:
                _hot_crossing_interval(rng, xs, a + q, m0, l0 + sl * q, curq[q], h, g, theta, frh, 0.0, v, blind,
                                       dark_next, out, scratch)  # no dark events: dark_next stays +inf
                q += 1
                continue
            vv = v[h]
            D = theta - vv
            k = np.int64(0)
            tb[0] = sp
            lc[0] = 0.0
            zc[0] = 0.0
            r = q
            while r < n and curq[r] >= 0.0:
                t1 = np.float64(a + r + 1)
                ln = t1 - tb[k]
                lam = l0 + sl * r
                lamv[k] = lam
                curv[k] = curq[r]
                lc[k + 1] = lc[k] + lam * ln
                zc[k + 1] = zc[k] + curq[r] * ln
                tb[k + 1] = t1
                k += 1
                r += 1
                if zc[k] + g * lc[k] >= 1.15 * D:
                    break
            nph = _poisson(rng, xs, lc[k])
            if zc[k] + g * nph < D:  # no firing in the stretch
                v[h] = vv + zc[k] + g * nph
                q = r
                continue
            tau = _stretch_first_passage(rng, xs, nph, D, g, k, tb, lc, zc, lamv, curv)
            mi = np.int64(tau)
            if mi > a + r - 1:
                mi = a + r - 1
            out[mi - m0, h >> 3] |= np.uint8(1 << (h & 7))
            v[h] = 0.0
            blind[h] = tau + frh
            q = mi - a

    @_jit
    def crossing_tile(rng, xs, R, start, length, lo_, nk_, w, m0, p0, p1, hot_idx, gb, gc, fr, mu, gain,
                       hot_mu, hot_sigma, theta, rem, dark_next, blind, guard, v, out, dc, use_dc):
        """``elssim`` with the crossing reset (see ``ELSSimCrossingFast``): continuous firing times, no interval reset.

        Times are >= 0 and positions >= the piece start, so ``int()`` truncation is the floor throughout.

        Per non-hot pixel: ``rem`` is the light (expected photoelectrons) still to collect before the next firing,
        counted from the end of the last piece done, the target being a Gamma(k, 1) variate in the rescaled time
        Lambda(t) = int lambda (the time-rescaling of the photoelectron Poisson process); ``dark_next`` the time
        [intervals] of the next dark event; ``blind`` the end of the blind time after the last firing; ``guard``
        what pass 1 compares with the piece end: ``dark_next``, or -inf while the pixel is blind into the next
        piece (so pass 1 reads two arrays, as the interval kernel does).

        ``dc`` [e-/interval] is each pixel's dark current (``dark == "current"``, with ``use_dc``): it adds to the
        pixel's light in every interval (``l0``), so it is collected, shot-noise included, and lost in the blind
        time exactly as light is; ``mu`` is then zero.
        """
        for p in range(p0, p1):
            if rem[p] != rem[p]:  # NaN: not drawn yet (the stream starts reset, not blind, at interval m0)
                rem[p] = _gamma(rng, xs, gb[p], gc[p])
                dark_next[p] = m0 + _exp_gap(rng, mu[p])
                guard[p] = dark_next[p]
        for h in hot_idx:
            rem[h] = np.inf  # hot pixels never take the event path
            guard[h] = np.inf
        npc = start.size
        flag = np.zeros(SUB_PIXELS, np.uint8)
        idx = np.empty(SUB_PIXELS + 1, np.int64)
        for c0 in range(p0, p1, SUB_PIXELS):
            c1 = min(c0 + SUB_PIXELS, p1)
            nt = c1 - c0
            for i in range(npc):
                a = m0 + start[i]
                n = length[i]
                end = a + n
                fa = np.float64(a)
                fend = np.float64(end)
                lo = lo_[i]
                nk = nk_[i]
                # ---- pass 1 (vectorised): subtract the piece's light; flag pixels that may fire or start blind
                _subtract_and_flag(R, w, i, lo, nk, c0, nt, rem[c0:c1], guard[c0:c1], fend, flag, n, dc, use_dc)
                cnt = 0
                for t in range(nt):
                    idx[cnt] = t
                    cnt += flag[t]
                # ---- pass 2: the flagged pixels, firing by firing, in continuous time. Light is counted as
                # Lambda_rel(t), the expected photoelectrons from the piece start to t: C(j) = j l0 + sl j (j-1) / 2
                # at the start of interval j of the piece, linear inside it; G is the next firing's target.
                for c_ in range(cnt):
                    p = c0 + idx[c_]
                    if rem[p] == np.inf:
                        continue  # hot pixel
                    s, l0, sl = _piece_coeffs_dc(R, w, i, lo, nk, p, n, dc, use_dc)
                    G = rem[p] + s  # undo pass 1: the target, from the piece start
                    cn = n * l0 + sl * 0.5 * n * (n - 1)  # Lambda_rel(end)
                    dn = dark_next[p]
                    bp = blind[p]
                    if bp > fa:  # blind at the piece start
                        if dn < bp:  # a dark event while blind is lost: the next one after the blind time
                            dn = bp + _exp_gap(rng, mu[p])
                        if bp >= fend:  # blind through the whole piece: nothing collected
                            rem[p] = G
                            dark_next[p] = dn
                            guard[p] = -np.inf
                            continue
                        jb = np.int64(bp - fa)
                        G += jb * l0 + sl * 0.5 * jb * (jb - 1) + (bp - fa - jb) * (l0 + sl * jb)  # light lost
                    done = False
                    while True:
                        if G > cn:
                            if dn >= fend:  # no firing in the rest of the piece
                                break
                            tl = np.inf
                        else:  # the interval where Lambda_rel reaches G, and the time inside it
                            x = _crossing(G, l0, sl, n)
                            lx = l0 + sl * (x - 1)
                            fx = (G - ((x - 1) * l0 + sl * 0.5 * (x - 1) * (x - 2))) / lx
                            tl = fa + (x - 1) + (fx if fx < 1.0 else 1.0)
                        if dn < tl:  # a dark event first
                            tau = dn
                            jt = np.int64(tau - fa)
                            lt = jt * l0 + sl * 0.5 * jt * (jt - 1) + (tau - fa - jt) * (l0 + sl * jt)
                        else:
                            tau = tl
                            jt = x - 1
                            lt = G
                        mi = a + jt  # the interval of the firing
                        if mi >= end:
                            mi = end - 1
                        out[mi - m0, p >> 3] |= np.uint8(1 << (p & 7))
                        g_new = _gamma(rng, xs, gb[p], gc[p])  # the next target, counted from the end of blindness
                        pos = tau + fr[p]
                        blind[p] = pos
                        if dn <= pos:  # fired by it, or it falls in the blind time: lost, draw the next one
                            dn = pos + _exp_gap(rng, mu[p])
                        if pos >= fend:  # blind into the next piece: it counts the new target from there
                            rem[p] = g_new
                            done = True
                            break
                        jp = np.int64(pos - fa)
                        if jp == jt:  # the blind time ends in the same interval: f * lambda of it is lost
                            G = lt + fr[p] * (l0 + sl * jt) + g_new
                        else:
                            G = jp * l0 + sl * 0.5 * jp * (jp - 1) + (pos - fa - jp) * (l0 + sl * jp) + g_new
                    if not done:
                        rem[p] = G - cn
                    dark_next[p] = dn
                    guard[p] = -np.inf if blind[p] > fend else dn
        # ---- hot pixels: event by event in continuous time
        scratch = np.empty(256)
        if use_dc:  # per-stretch buffers (a stretch lies in one piece)
            nmax = np.int64(length.max()) + 1 if npc else np.int64(1)
            curq = np.empty(nmax)
            tb = np.empty(nmax)
            lc = np.empty(nmax)
            zc = np.empty(nmax)
            lamv = np.empty(nmax)
            curv = np.empty(nmax)
        for i in range(npc):
            a = m0 + start[i]
            n = length[i]
            lo = lo_[i]
            nk = nk_[i]
            for h in hot_idx:
                s, l0, sl = _piece_coeffs_dc(R, w, i, lo, nk, h, n, dc, use_dc)
                if use_dc:
                    _hot_crossing_piece_current(rng, xs, a, n, m0, l0, sl, h, gain[h], hot_mu[h], hot_sigma[h],
                                                theta, fr[h], v, blind, dark_next, out, scratch, curq, tb, lc, zc,
                                                lamv, curv)
                    continue
                for q in range(n):
                    cur = (hot_mu[h] + hot_sigma[h] * rng.standard_normal()) * theta
                    _hot_crossing_interval(rng, xs, a + q, m0, l0 + sl * q, cur, h, gain[h], theta, fr[h], mu[h],
                                           v, blind, dark_next, out, scratch)


if HAVE_NUMBA:
    @_jit
    def _draw_samples(kind, rng, xs, a, n):
        """n draws of one of the kernels' samplers (for tests): 0 uniform, 1 Gamma(a), 2 Geometric(p=a), 3 Poisson(a)."""
        out = np.empty(n)
        b = a - 1.0 / 3.0
        c = 1.0 / math.sqrt(9.0 * b) if b > 0 else 0.0
        inv = -1.0 / math.log1p(-a) if 0.0 < a < 1.0 else 0.0
        for i in range(n):
            if kind == 0:
                out[i] = _uniform(xs)
            elif kind == 1:
                out[i] = _gamma(rng, xs, b, c)
            elif kind == 2:
                out[i] = _geometric(rng, inv)
            else:
                out[i] = _poisson(rng, xs, a)
        return out


def sample(kind: str, a: float, n: int, seed: int = 0) -> np.ndarray:
    """Draw ``n`` variates with the samplers the kernels use (``uniform``, ``gamma``, ``geometric``, ``poisson``)."""
    rng = np.random.default_rng(seed)
    return _draw_samples(("uniform", "gamma", "geometric", "poisson").index(kind), rng, xoshiro_state(rng),
                         float(a), int(n))


def xoshiro_state(rng) -> np.ndarray:
    """Seed of the tile's inline uniform generator (xoshiro256+), drawn from the tile's numpy generator."""
    st = rng.integers(0, 2 ** 64 - 1, size=4, dtype=np.uint64, endpoint=True)
    if not st.any():  # pragma: no cover - probability 2^-256
        st[0] = 1
    return st

