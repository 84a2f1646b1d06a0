"""Monte Carlo noise budget: choose spp so render noise stays well below photon shot noise.

Definitions (per pixel, rate in e-/interval)
--------------------------------------------
* ``r``: expected photoelectrons per interval; ``v``: the Monte Carlo variance
  of its rendered estimate in one keyframe; ``d``: the profile's dark current
  as a charge [e-/interval] (``dark_current_e``, its mean over the pixels; zero
  for a profile with dark events), whose electrons the pixel counts with the
  light's and which have their own shot noise.
* Over a reconstruction window of ``W`` intervals the electron count has
  shot-noise variance ``W (r + d)``. The sensor integrates the rate interpolated
  between keyframes, so the render errors of the ``K = max(1, W T_r f_key)``
  keyframes in the window (base keyframe rate ``f_key``) add up independently:
  variance ``W^2 v / K``.
* render-noise ratio ``rho = sqrt(W mean(v) / (K mean(r + d)))``: RMS render
  error over RMS shot noise in the window, averaged over the image.
* The spp is chosen so that ``rho <= target_ratio`` (default 0.2: render
  variance <= 4 % of shot-noise variance), clipped to [min_spp, max_spp];
  where the sampler offers no count between the band's low edge and the
  target, the count just above the target but within the band ``[0.75, 1.25] x
  target`` is taken (see below).

How the variance falls with spp is measured, not assumed
--------------------------------------------------------
The stratified (``multijitter``) sampler converges faster than 1/spp where the
integrand is smooth in the pixel (texture edges, soft shadows: 1/spp^2 and
faster) and like 1/spp where it is not (light sampling after a bounce). So the
pilot (:func:`pilot_budget`) renders independent pairs at t = 0 at ``n1`` (the
pilot spp), ``n2 = 4 n1`` and, when the answer lies beyond ``n2``, ``n3 = 16 n1``;
``v(n)`` is the mean over pixels of ``(a - b)^2 / 2`` at each level, and

    V(n) = A / n + B / n^2,   A, B >= 0          (:func:`fit_convergence`)

is fitted to them (least squares in relative error). The model is exact for
pure 1/n and pure 1/n^2 convergence and over-estimates the variance of any
power law ``n^-alpha`` in between when extrapolated beyond the pilots, so its
answer ``c`` is conservative. A last pair is then rendered *at* ``c`` (the
variance is not smooth in n: ``multijitter`` strata change shape with the count)
and the final spp is solved on the measured points alone
(:class:`Measured`: power laws between neighbouring levels, ``(n1/n)^2`` below
the first, ``1/n`` beyond the last; both conservative), so it is interpolated,
never extrapolated, unless ``c`` itself missed. The spp is rounded up to a count
the sampler takes exactly.

Interpolation is not enough either: ``multijitter`` lays a count ``n = k m`` on
``k x m`` strata, and the variance jumps between neighbouring counts (rotating
disk, 5 lux: 49 spp -> ratio 0.209, 56 -> 0.145, 63 and 64 -> 0.170), so the
interpolated answer 56 was predicted at 0.187 and achieved 0.145. The answer is
therefore *snapped* on measured pairs (:func:`snap_to_measured`): the count
itself and the exact count below it are measured; the count steps up while it
misses the target and down while the one below meets it; and when the count
reached falls below the band (``< 0.75 x target``) while the one below is
within it (``<= 1.25 x target``), the cheaper count is taken. The predicted
ratio is then the ratio measured at the chosen count. Cost: pairs at 4, 16, 64
spp and at ``c``, plus usually two at the answer and its neighbour, once.

The budget is then *verified*: some frames (the first, then every
:data:`VERIFY_EVERY`-th base keyframe of the time grid, by its index: the same
frames whether or not the render was resumed) get a second, independent render whose
difference measures that frame's ``rho`` (the frame itself is the first render,
so it has exactly the asked spp; with a fixed spp, the first frame's second
render is the pilot's t = 0 render at that spp when there is one, see
:meth:`.renderer.SceneRenderer.keep_renders`); the ratio is recorded in the frame header and
summarised in the manifest, with a warning when it misses the band
``[0.75, 1.25] x target`` (:func:`verify_ratios`).
"""

from __future__ import annotations

import math

import numpy as np

#: every how many base keyframes (by index on the time grid: ticks 0, 128 x step, ...) the achieved
#: render-noise ratio is measured (one extra launch each: at most 1/128 = 0.8 % of a long render's time).
#: Chosen by the frame's place in the clip, not by a count or a time budget, so that which frames carry a
#: measured ratio depends neither on the load nor on whether the render was resumed.
VERIFY_EVERY = 128
#: the achieved ratio should lie in [BAND[0], BAND[1]] x target (0.15-0.25 for the default target 0.2)
BAND = (0.75, 1.25)


def keyframes_per_window(window_intervals: int, interval_s: float, keyframe_rate_hz: float) -> float:
    """K: independent keyframes whose errors average inside a window (at least 1)."""
    return max(1.0, float(window_intervals) * float(interval_s) * float(keyframe_rate_hz))


#: window positions averaged over by :func:`level_k_factors` (evenly spread over one base spacing)
LEVEL_OFFSETS = 16


def _hat_weights(times, t0: float, length: float, n_grid: int) -> np.ndarray:
    """Each keyframe's weight in the mean over ``[t0, t0 + length]`` of the linear interpolation between
    keyframes at ``times`` (sorted): the mean of its hat function over the window (midpoint rule)."""
    t = t0 + (np.arange(n_grid) + 0.5) * (length / n_grid)
    j = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
    u = (t - times[j]) / (times[j + 1] - times[j])
    w = np.zeros(len(times))
    np.add.at(w, j, 1.0 - u)
    np.add.at(w, j + 1, u)
    return w / n_grid


def level_k_factors(window_intervals: int, interval_s: float, base_rate_hz: float, levels: int) -> list[float]:
    """How much more variance a keyframe of each refinement level may have than a base keyframe, window for window.

    The sensor integrates the rate interpolated linearly between keyframes, so a window of ``W`` intervals
    averages the keyframes' independent render errors with weights ``w_i`` (the mean of each keyframe's hat
    function over the window): its variance is ``sum w_i^2 v_i``. A base keyframe gets the variance that
    meets the target with base keyframes alone; a keyframe of level ``l`` (which halves a level ``l - 1``
    segment) gets ``a_l`` times that, chosen so that a window refined to level ``l`` everywhere has the same
    variance as a base-only one: ``a_l = (S_0 - sum_(j<l) a_j S_j) / S_l``, with ``S_j`` the mean over window
    positions (:data:`LEVEL_OFFSETS` over one base spacing) of ``sum w_i^2`` over the level-``j`` keyframes of
    the refined grid. For windows of many keyframes (``K_l = W T_r f 2^l``) this tends to
    ``(K_l + K_(l-1)) / K_0``: 3 for level 1, 6 for level 2, 12 for level 3. -> ``[1, a_1, ..., a_levels]``,
    each at least 1; a level's ``K`` to budget with is ``K_0 a_l`` (:func:`choose_spp_fit`)."""
    h0 = 1.0 / float(base_rate_hz)
    length = float(window_intervals) * float(interval_s)
    n_base = int(math.ceil(length / h0)) + 4
    out = [1.0]
    for top in range(1, levels + 1):
        step = 2 ** top
        times = (np.arange(n_base * step + 1) / step - 2.0) * h0  # from two base spacings before the window
        idx = np.arange(times.size)
        lvl = np.where(idx % step == 0, 0, top - (np.log2((idx & -idx) % step + (idx % step == 0)).astype(int)))
        n_grid = max(2048, 64 * int(math.ceil(length / (h0 / step))))
        s = np.zeros(top + 1)
        s_base = 0.0
        for k in range(LEVEL_OFFSETS):
            t0 = h0 * k / LEVEL_OFFSETS
            w2 = _hat_weights(times, t0, length, n_grid) ** 2
            s += np.bincount(lvl, weights=w2, minlength=top + 1)[:top + 1]
            if top == 1:
                s_base += float((_hat_weights(times[::step], t0, length, n_grid) ** 2).sum())
        if top == 1:
            var0 = s_base / LEVEL_OFFSETS
        s /= LEVEL_OFFSETS
        rest = var0 - sum(out[j] * s[j] for j in range(top))
        out.append(max(1.0, float(rest / s[top])) if s[top] > 0 else 1.0)
    return out


def dark_current_mean_e(profile) -> float:
    """A profile's mean dark current as a charge [e-/interval] (0 with dark events): shot noise that the render
    noise is held against beside the light's (``d`` above)."""
    return float(np.mean(profile.dark_current_e, dtype=np.float64))


def render_noise_ratio(rate_e, rate_var, window_intervals: int, k_frames: float = 1.0, dark_e: float = 0.0) -> float:
    """``sqrt(W mean(v) / (K mean(r + d)))`` for rate_e [e-/interval], its MC variance and the dark current
    ``dark_e`` [e-/interval]; nan if dark or unknown. ``k_frames`` may be an array of the rate's shape (the
    keyframes each pixel's error averages over): then ``sqrt(W mean(v / K) / mean(r + d))``."""
    r = float(np.mean(rate_e)) + float(dark_e)
    if not r > 0 or rate_var is None:
        return float("nan")
    if np.ndim(k_frames):  # per pixel (static-region reuse: K = 1 where a pixel reuses the static frame)
        return float(math.sqrt(window_intervals * float(np.mean(np.asarray(rate_var) / k_frames)) / r))
    return float(math.sqrt(window_intervals * float(np.mean(rate_var)) / (k_frames * r)))


#: side [pixels] of the square tiles over which :func:`tile_ratios` measures the ratio
TILE_PX = 8


def tile_ratios(rate_e, rate_var, window_intervals: int, k_frames=1.0, dark_e: float = 0.0,
                tile_px: int = TILE_PX) -> np.ndarray:
    """:func:`render_noise_ratio` on each ``tile_px`` x ``tile_px`` tile of the frame (the last row and column of
    tiles may be smaller): -> float64 (ceil(H / tile_px), ceil(W / tile_px)). Where the ratio varies over the
    frame (bright and dark regions at one spp; the static frame beside the keyframes' pixels), this is its spread.
    A tile's ratio from one pair of renders has a relative standard error of about ``1 / sqrt(2 n)`` for ``n``
    pixels (9 % on a whole 8 x 8 tile) when its pixels' variances are alike."""
    r = np.asarray(rate_e, np.float64) + float(dark_e)
    v = np.asarray(rate_var, np.float64) / np.broadcast_to(np.asarray(k_frames, np.float64), r.shape)
    h, w = r.shape
    t = int(tile_px)
    ny, nx = -(-h // t), -(-w // t)
    pad = ((0, ny * t - h), (0, nx * t - w))
    rp = np.pad(r, pad, constant_values=np.nan).reshape(ny, t, nx, t)
    vp = np.pad(v, pad, constant_values=np.nan).reshape(ny, t, nx, t)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.sqrt(window_intervals * np.nanmean(vp, axis=(1, 3)) / np.nanmean(rp, axis=(1, 3)))
    return np.where(np.isfinite(out), out, np.nan)


def tile_summary(tiles: list, target_ratio: float) -> dict:
    """The manifest's summary of the verified frames' :func:`tile_ratios`: quantiles over every tile of every
    verified frame and the fraction within :data:`BAND` x the target (or above it)."""
    x = np.concatenate([np.ravel(a) for a in tiles]) if tiles else np.zeros(0)
    x = x[np.isfinite(x)]
    if not x.size:
        return {"tile_px": TILE_PX, "n_tiles": 0}
    lo, hi = BAND[0] * target_ratio, BAND[1] * target_ratio
    q = np.quantile(x, [0.1, 0.5, 0.9])
    return {"tile_px": TILE_PX, "n_tiles": int(x.size), "p10": float(q[0]), "p50": float(q[1]), "p90": float(q[2]),
            "max": float(x.max()), "fraction_in_band": float(np.mean((x >= lo) & (x <= hi))),
            "fraction_above_band": float(np.mean(x > hi))}


def pair_variance(a, b) -> np.ndarray:
    """Per-pixel variance of ONE of two independent estimates a, b: (a - b)^2 / 2."""
    return (np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2 / 2.0


class Convergence:
    """``V(n) = A/n + B/n^2`` for n >= n_min, ``V(n_min) (n_min/n)^2`` below; fitted by :func:`fit_convergence`."""

    def __init__(self, a: float, b: float, n_min: int):
        self.a, self.b, self.n_min = float(a), float(b), int(n_min)

    def __call__(self, n) -> float:
        n = float(n)
        if n < self.n_min:
            return self(self.n_min) * (self.n_min / n) ** 2
        return self.a / n + self.b / n ** 2

    def solve(self, allowed: float) -> float:
        """Smallest real n with V(n) <= allowed (allowed > 0)."""
        if self(self.n_min) <= allowed:
            # V(n_min) (n_min / n)^2 <= allowed below n_min
            return self.n_min * math.sqrt(self(self.n_min) / allowed)
        a, b = self.a, self.b
        return (a + math.sqrt(a * a + 4.0 * allowed * b)) / (2.0 * allowed)

    @property
    def alpha_local(self) -> float:
        """Local convergence exponent -dlog V/dlog n at n_min (1: like 1/n, 2: like 1/n^2)."""
        n = self.n_min
        v = self.a / n + self.b / n ** 2
        return float((self.a / n + 2 * self.b / n ** 2) / v) if v > 0 else 1.0


class Measured:
    """``V(n)`` through measured (n, v) points: power laws between neighbours, ``(n0/n)^2`` below, ``1/n`` above."""

    def __init__(self, ns, vs):
        order = np.argsort(ns)
        self.ns = np.asarray(ns, np.float64)[order]
        v = np.asarray(vs, np.float64)[order]
        self.vs = np.minimum.accumulate(np.maximum(v, 1e-300))  # non-increasing (pair noise can break it)
        self.n_min = int(self.ns[0])
        self.a, self.b = float(self.vs[-1] * self.ns[-1]), 0.0  # the 1/n tail, for the record

    def __call__(self, n) -> float:
        n = float(n)
        ns, vs = self.ns, self.vs
        if n <= ns[0]:
            return float(vs[0] * (ns[0] / n) ** 2)
        if n >= ns[-1]:
            return float(vs[-1] * ns[-1] / n)
        j = int(np.searchsorted(ns, n)) - 1
        u = math.log(n / ns[j]) / math.log(ns[j + 1] / ns[j])
        return float(math.exp((1 - u) * math.log(vs[j]) + u * math.log(vs[j + 1])))

    def solve(self, allowed: float) -> float:
        lo, hi = 1e-3, float(self.ns[-1])
        if self(hi) > allowed:
            return float(self.vs[-1] * self.ns[-1] / allowed)
        for _ in range(100):  # bisection in log n (V is non-increasing)
            mid = math.sqrt(lo * hi)
            lo, hi = (mid, hi) if self(mid) > allowed else (lo, mid)
        return hi

    @property
    def alpha_local(self) -> float:
        if self.ns.size < 2:
            return 1.0
        return float(math.log(self.vs[0] / self.vs[1]) / math.log(self.ns[1] / self.ns[0]))


def fit_convergence(ns, vs) -> Convergence:
    """Fit ``V(n) = A/n + B/n^2`` (A, B >= 0) to mean variances ``vs`` at spp ``ns`` (relative least squares)."""
    from scipy.optimize import nnls
    ns = np.asarray(ns, np.float64)
    vs = np.asarray(vs, np.float64)
    ok = vs > 0
    if not np.any(ok):
        return Convergence(0.0, 0.0, int(ns.min()))
    ns, vs = ns[ok], vs[ok]
    if ns.size == 1:
        return Convergence(vs[0] * ns[0], 0.0, int(ns[0]))  # one level: assume 1/n
    M = np.c_[1.0 / ns, 1.0 / ns ** 2] / vs[:, None]
    (a, b), _ = nnls(M, np.ones_like(vs))
    return Convergence(a, b, int(ns.min()))


def choose_spp_fit(rate_e, model: Convergence, window_intervals: int, k_frames: float, target_ratio: float,
                   min_spp: int, max_spp: int, exact=None) -> dict:
    """The least spp meeting the budget under the fitted convergence ``model`` (rate units).

    ``exact(n)`` rounds a count up to one the sampler takes exactly (identity if None).
    """
    exact = exact or (lambda n: int(n))
    r = float(np.mean(rate_e))
    allowed = target_ratio ** 2 * k_frames * r / window_intervals  # max per-keyframe variance
    if not r > 0 or model(model.n_min) <= 0:
        need = int(min_spp)
    else:
        need = max(1, int(math.ceil(model.solve(allowed) - 1e-9)))
    spp = exact(int(min(max(need, min_spp), max_spp)))
    if spp > max_spp:  # rounding up overshot the cap: the largest exact count within it
        spp = exact_below(exact, int(max_spp))

    def predicted(n):
        if not r > 0:
            return float("nan")
        return math.sqrt(window_intervals * model(n) / (k_frames * r))
    return {"spp": int(spp), "spp_needed": int(need), "predicted_ratio": predicted(spp),
            "model": {"form": "V(n) = A/n + B/n^2 [(e-/interval)^2]", "A": model.a, "B": model.b,
                      "alpha_at_pilot": model.alpha_local},
            "mean_rate_e": r, "window_intervals": int(window_intervals), "keyframes_per_window": float(k_frames),
            "target_ratio": float(target_ratio), "clipped": bool(need > max_spp),
            "at_min_spp": bool(need < min_spp)}


def choose_spp(rate_e, var_n1: float, n1: int, var_n2: float, n2: int, window_intervals: int, k_frames: float,
               target_ratio: float, min_spp: int, max_spp: int) -> dict:
    """The spp meeting the budget from pilot variances (mean over pixels, rate units) at n1 and n2 spp."""
    model = fit_convergence([n1, n2], [var_n1, var_n2])
    out = choose_spp_fit(rate_e, model, window_intervals, k_frames, target_ratio, min_spp, max_spp)
    out["pilot"] = {"spp": [int(n1), int(n2)], "mean_var_rate_e2": [float(var_n1), float(var_n2)]}
    return out


def exact_below(exact, n: int) -> int:
    """The largest count <= n that ``exact`` keeps unchanged (1 always is)."""
    for m in range(int(n), 0, -1):
        if exact(m) == m:
            return m
    return 1


#: at most this many extra pilot pairs when :func:`snap_to_measured` steps up or down from the model's answer
SNAP_STEPS = 3


def snap_to_measured(spp: int, measure, ratio_of, target_ratio: float, min_spp: int, max_spp: int, exact,
                     steps: int = SNAP_STEPS) -> tuple[int, dict]:
    """The sampler's own counts near ``spp``, checked on measured pairs: -> (spp, {count: measured ratio}).

    ``multijitter`` lays its samples on ``k x m`` strata, and the variance is not monotone in the
    count: on the rotating disk at 5 lux, 49 (7 x 7) spp gives a ratio 0.209, 56 (7 x 8) 0.145 and
    63, 64 again 0.170. Interpolating between measured levels can therefore land on a count whose
    noise is far from the prediction. So the model's answer is measured (``measure(n)``: one pilot
    pair at ``n``, returns its mean variance; ``ratio_of(v)``: the ratio it gives), and then

    * while its ratio is above the target, the next exact count up is measured (at most ``steps``);
    * while the exact count just below also meets the target, it is taken (at most ``steps``);
    * if the count reached is below the band (ratio < ``BAND[0] x target``, more samples than the
      budget needs) while the count just below is within it (ratio <= ``BAND[1] x target``), the
      cheaper one is taken: the sampler has no count in between, and the band is what the budget
      promises (its ratio may then exceed the target by up to ``BAND[1]``).

    The answer's ratio is a measurement, not an interpolation. ``exact(n)`` rounds up to a count the
    sampler takes.
    """
    lo, hi = BAND[0] * target_ratio, BAND[1] * target_ratio
    seen: dict[int, float] = {}

    def r(n):
        if n not in seen:
            seen[n] = float(ratio_of(measure(n)))
        return seen[n]
    s = int(spp)
    for _ in range(steps):  # up while the measured ratio misses the target
        if r(s) <= target_ratio:
            break
        up = exact(s + 1)
        if up > max_spp:
            break
        s = up
    r(s)
    for _ in range(steps):  # down while the count below meets it too
        below = exact_below(exact, s - 1) if s > 1 else 0
        if below < max(1, int(min_spp)):
            break
        if r(below) <= target_ratio:
            s = below
            continue
        if r(s) < lo and r(below) <= hi:
            s = below
        break
    return s, seen


def pilot_budget(rnd, scene, window_intervals: int, k_frames: float, rate_scale: float, snap: bool = True,
                 dark_e: float = 0.0, mask=None, keep: dict | None = None, level_factors=(1.0,),
                 keep_raw: dict | None = None):
    """Pilot renders at t = 0 -> (budget dict, per-pixel variance function ``v_px(spp)`` in Phi units^2).

    ``rnd`` is a :class:`~.renderer.SceneRenderer`. Levels ``n1 = pilot_spp``, ``4 n1`` and, if the
    two-level answer exceeds ``4 n1``, ``16 n1`` (rounded up to exact sampler counts), each an
    independent pair of renders with seeds derived from the scene seed. ``snap``: check the answer on
    the sampler's own counts (:func:`snap_to_measured`); off when the spp is fixed by the user (the
    budget is then only a record, and the snapping's pairs would be spent for nothing). ``dark_e``: the
    profile's mean dark current [e-/interval], added to the light in the shot noise (``r + d``). ``mask``
    (bool (H, W)): the means are taken over these pixels only (the dynamic region of :mod:`.reuse`); ``keep``:
    a dict that receives the pilot pairs, ``{spp: (Phi a, Phi b)}``; ``keep_raw``: one that receives the pair at the
    highest count as rendered, ``{spp: (seeds, (Phi_raw a, E_raw a), (Phi_raw b, E_raw b))}`` (the static frame of
    :mod:`.reuse` may be it). ``level_factors`` (:func:`level_k_factors`): the budget's ``spp_levels`` holds the spp of each refinement level, the base
    one (``spp``) first; a refined level's is solved on the measured levels with ``K`` times its factor (not
    snapped: no pairs are spent on it), and ``level_var`` the variance of each level's keyframe over the
    base one's.
    """
    from .photometry import to_physical
    rcfg = scene.render
    ncfg = rcfg["noise"]
    exact = rnd.effective_spp
    n1 = exact(int(ncfg["pilot_spp"]))
    # a pair of seeds per level: 4 levels, then the snapping's (2 SNAP_STEPS + 1 at most); the words of a
    # SeedSequence's state do not depend on how many are drawn, so the levels' seeds do not depend on SNAP_STEPS
    seeds = np.random.SeedSequence([int(rcfg["seed"]), 0x9110]).generate_state(2 * (5 + 2 * SNAP_STEPS),
                                                                                dtype=np.uint32)
    pil, levels, var_means = ({} if keep is None else keep), [], []
    sel = slice(None) if mask is None else np.asarray(mask, bool)

    def level(j, n):
        if n in pil:
            return var_means[levels.index(n)]
        pair, raw = [], []
        for s in seeds[2 * j:2 * j + 2]:
            raw_p, raw_e = rnd.render_raw(0.0, int(s), n)
            raw.append((raw_p, raw_e))
            pair.append(to_physical(raw_p, raw_e, rnd.k, rnd.f_number, rnd.transmission, rnd.cos4)[0])
        pil[n] = pair
        if keep_raw is not None and all(n > m for m in keep_raw):  # the highest count's pair only
            keep_raw.clear()
            keep_raw[n] = ([int(s) for s in seeds[2 * j:2 * j + 2]], raw[0], raw[1])
        levels.append(n)
        var_means.append(float(pair_variance(*pair)[sel].mean()) * rate_scale ** 2)
        return var_means[-1]

    args = (window_intervals, k_frames, float(ncfg["target_ratio"]), int(ncfg["min_spp"]), int(ncfg["max_spp"]),
            exact)
    level(0, n1)
    level(1, exact(4 * n1))
    rate = lambda: (0.5 * (pil[levels[-1]][0] + pil[levels[-1]][1]) * rate_scale + dark_e)[sel]  # noqa: E731
    budget = choose_spp_fit(rate(), fit_convergence(levels, var_means), *args)
    if budget["spp_needed"] > levels[-1]:  # extrapolating: measure one level further out
        level(2, exact(16 * n1))
        budget = choose_spp_fit(rate(), fit_convergence(levels, var_means), *args)
    fitted = budget
    if budget["spp"] not in pil and not budget["at_min_spp"]:
        # measure the candidate itself (the sampler's variance is not smooth in n: multijitter's
        # strata change shape), then solve on measured points only
        level(3, budget["spp"])
    model = Measured(levels, var_means) if len(levels) > 1 else fit_convergence(levels, var_means)
    budget = choose_spp_fit(rate(), model, *args)
    if snap and not budget["clipped"] and not budget["at_min_spp"]:
        # the answer and its neighbours measured: multijitter's variance is not monotone in the count
        r_mean = float(np.mean(rate()))
        ratio_of = lambda v: math.sqrt(window_intervals * v / (k_frames * r_mean))  # noqa: E731
        model_spp = budget["spp"]
        js = iter(range(4, 5 + 2 * SNAP_STEPS))  # seed pairs after the four levels above
        spp, seen = snap_to_measured(model_spp, lambda n: level(next(js), n), ratio_of,
                                     float(ncfg["target_ratio"]), int(ncfg["min_spp"]), int(ncfg["max_spp"]), exact)
        budget.update(spp=int(spp), predicted_ratio=seen[spp], model_spp=int(model_spp),
                      snapped={str(n): seen[n] for n in sorted(seen)})
    spp_levels = [int(budget["spp"])]
    v0 = model(spp_levels[0])
    for a in level_factors[1:]:
        # the variance the base keyframes reached (the target's, or max_spp's when clipped) times the level's
        # factor: every window, refined or not, then has the base-only window's ratio
        n = max(1, int(math.ceil(model.solve(v0 * float(a)) - 1e-9))) if v0 > 0 else spp_levels[-1]
        n = exact(int(min(max(n, int(ncfg["min_spp"])), spp_levels[-1])))
        spp_levels.append(int(min(n, spp_levels[-1])))  # never more than the level above
    budget["spp_levels"] = spp_levels
    budget["level_var"] = [float(model(n) / v0) if v0 > 0 else 1.0 for n in spp_levels]
    budget["level_k_factors"] = [float(a) for a in level_factors]
    budget["model"] = {"form": "power laws between the measured pilot levels", "fit_A_over_n_B_over_n2":
                       fitted["model"], "alpha_at_pilot": model.alpha_local}
    budget["fit_candidate_spp"] = fitted["spp"]
    budget["dark_e"] = float(dark_e)
    budget["pilot"] = {"spp": [int(n) for n in levels], "mean_var_rate_e2": var_means}
    near = min(levels, key=lambda n: abs(math.log(n / max(budget["spp"], 1))))
    v_near = pair_variance(*pil[near])
    v_ref = model(near)

    def v_px(spp: int) -> np.ndarray:
        """Per-pixel variance [Phi units^2] of one frame at ``spp``: the nearest pilot level scaled by the model."""
        return v_near * (model(spp) / v_ref if v_ref > 0 else near / float(spp))
    return budget, v_px


def verify_ratios(ratios, target_ratio: float, auto: bool, budget: dict | None = None) -> tuple[dict, str | None]:
    """Summary of the measured per-frame ratios and a warning if they miss the band around the target.

    Below the band is only a miss when the budget could have used fewer samples (``auto`` and
    not held up by ``min_spp``); above it, whenever ``auto`` and the budget was not capped by ``max_spp``.
    """
    r = np.asarray([x for x in ratios if x is not None and np.isfinite(x)], np.float64)
    lo, hi = BAND[0] * target_ratio, BAND[1] * target_ratio
    out = {"n_verified": int(r.size), "band": [lo, hi]}
    if not r.size:
        return out, None
    out.update(verified_mean=float(r.mean()), verified_min=float(r.min()), verified_max=float(r.max()))
    mean = float(r.mean())
    out["in_band"] = bool(lo <= mean <= hi)
    if not auto or out["in_band"]:
        return out, None
    budget = budget or {}
    if mean > hi and not budget.get("clipped"):
        return out, (f"the measured render-noise ratio {mean:.3f} (mean of {r.size} verified frames) is above "
                     f"{hi:.3f} = {BAND[1]} x the target {target_ratio}; the noise budget under-estimated the variance")
    if mean < lo and not budget.get("at_min_spp"):
        return out, (f"the measured render-noise ratio {mean:.3f} (mean of {r.size} verified frames) is below "
                     f"{lo:.3f} = {BAND[0]} x the target {target_ratio}; the noise budget spent more samples "
                     "than needed")
    return out, None
