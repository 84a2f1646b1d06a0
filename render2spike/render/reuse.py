"""Static-region reuse: pixels that nothing moving covers are rendered once and reused in every keyframe.

Why. With a still camera most of a frame often does not change: a wall behind a spinning disk, a floor
under a moving object. Rendering those pixels again in every keyframe spends samples on the same
irradiance; their noise budget is also another one (below). So a render with reuse splits each keyframe
into two regions:

* **dynamic** pixels, those a moving object covers at the keyframe's time (the coverage test below), are
  rendered at the keyframe, at the dynamic region's spp, with the frozen launch's pixel-list launch
  (:meth:`.frozen.FrozenLaunch.launch_pixels`);
* **static** pixels take their value from the *static frame*: one render at t = 0, made as two independent
  renders at the static spp and averaged (their difference gives each pixel's variance). The noise pilot
  renders such pairs of the whole frame at t = 0 anyway; its pair at its highest count is the static frame
  when it meets the static pixels' budget (no render and no kernel of its own), as it does on the bundled scenes.

Coverage test (:class:`Coverage`, per keyframe)
-----------------------------------------------
A pixel is dynamic at time ``t`` when any of ``SUBPIXEL x SUBPIXEL`` primary rays through it, or the
shadow ray from where such a ray hits toward any delta light (directional, point), first hits a moving
object; the set is then grown by :data:`DILATE_PX` pixels. A pixel that was dynamic at t = 0 (the moving
object stood in front of it when the static frame was made) has no static value and stays dynamic.
What the test does not see: light a moving object sends to a static pixel indirectly (an inter-reflection)
and the sky light it blocks there. Those are checked by measurement instead: at the clip's last base keyframe
(and at every verified keyframe after t = 0) the whole frame is also rendered, and the static pixels'
difference from the static frame, over its expected Monte Carlo variance, is averaged (``static_check``
in the manifest; about 1 when the static region did not change; a warning names the excess).

Noise budget (:func:`static_spp`, and :func:`.noise.pilot_budget` over the dynamic pixels)
------------------------------------------------------------------------------------------
The render-noise ratio (:mod:`.noise`) of a window of ``W`` intervals is ``sqrt(W mean(v_eff) /
mean(r + d))`` over a region, with ``v_eff`` the variance of the window's mean rate: ``v / K`` for a dynamic
pixel (the errors of ``K`` keyframes average), but ``v`` itself for a static one (every keyframe carries the
same error). The dynamic region's spp comes from the pilot pairs (:func:`.noise.pilot_budget`) with the
means taken over the dynamic pixels at t = 0; the static frame's from the same pilot pairs over the static
pixels, with ``K = 1`` and the pair's average (variance halved), no more than :data:`STATIC_MAX_FACTOR` x
``max_spp``. The pilot's own pair at its highest count is measured first (:func:`static_ratio`) and taken when it
is not above the band. Else the static frame is rendered at the budget's count, its own two renders measure its
ratio, and outside the band it is rendered again at another count (:func:`static_retry_spp`, at most
:data:`STATIC_ATTEMPTS` renders), because the pilot's levels are interpolated to its count and ``multijitter`` is
not smooth in the count.

A static pixel's error is one pattern for the whole clip: each window of ``W`` intervals meets the target, but
averages over many windows (a rate over the whole clip) do not shrink it as they shrink the errors of
independent keyframes.

Where it applies (:func:`reuse_obstacle`): the frozen launch, a camera that does not move (where nothing moves
at all, every keyframe is the static frame: the irradiance does not change), no object that emits light (an
area light's soft shadows are not covered), no XML scene, and ``render.static_reuse`` not false in the scene. Lights are the scene file's directional and point lights
(their shadows covered) and its environment (checked by measurement).
"""

from __future__ import annotations

import math

import numpy as np

#: primary rays per pixel side of the coverage test (a grid of SUBPIXEL^2, at the centres of its cells)
SUBPIXEL = 2
#: the dynamic region is grown by this many pixels (the test's rays see a pixel at a few points only)
DILATE_PX = 1
#: the static frame takes at most this many times the scene's max_spp (it is rendered once per clip)
STATIC_MAX_FACTOR = 8
#: the static frame is kept when its own pair measures its pixels' ratio within [BAND[0], STATIC_ACCEPT] x the
#: target; else it is rendered again (:func:`static_retry_spp`): the pilot's levels (4, 16, 64 ...) are interpolated
#: to the static count, and ``multijitter`` is not smooth in the count (on translating_object's static region 30
#: spp measured 1.9x the variance predicted); 1.1: a measured ratio over thousands of pixels is good to a few per
#: cent
STATIC_ACCEPT = 1.1
#: at most this many renders of the static frame
STATIC_ATTEMPTS = 4
#: the static check warns when its mean normalised squared difference exceeds 1 by this many of its own
#: standard errors (sqrt(2 / n) for n pixels of chi-square with one degree of freedom)
STATIC_CHECK_SIGMAS = 6.0
#: part of the frames' scene hash when reuse is on (:func:`.launch.settings_of`): a change to the coverage
#: test, the static frame or the budget split must bump it
REUSE_VERSION = 3


def reuse_obstacle(scene, launch: str) -> str | None:
    """Why static-region reuse does not apply to ``scene`` rendered with ``launch``, or None (it applies)."""
    from .builder import camera_motion, object_motion
    if launch != "frozen":
        return "the film launch renders whole frames only"
    if scene.render.get("static_reuse") is False:
        return "render.static_reuse is false in the scene"
    if not camera_motion(scene.camera).is_static:
        return "the camera moves, so no pixel stays still"
    movers = [obj for i, obj in enumerate(scene.data["objects"])
              if not object_motion(obj, f"objects.{i}.").is_static]
    if any("emitter" in obj for obj in movers):
        return "a moving object emits light, which reaches pixels the coverage test does not see"
    if any("emitter" in obj for obj in scene.data["objects"]):
        return ("an object emits light (an area light), whose soft shadows of the moving objects reach pixels the "
                "coverage test does not see")
    if "xml" in scene.data:
        return "the scene's lights come from its XML file, which the coverage test does not see"
    return None


def dilate(mask: np.ndarray, r: int = DILATE_PX) -> np.ndarray:
    """``mask`` (bool (H, W)) grown by ``r`` pixels (a square neighbourhood)."""
    if r <= 0:
        return np.asarray(mask, bool)
    from scipy.ndimage import binary_dilation
    return binary_dilation(np.asarray(mask, bool), structure=np.ones((2 * r + 1, 2 * r + 1), bool))


class Coverage:
    """The coverage test of a :class:`~.renderer.SceneRenderer` with the frozen launch: ``cov(t_s)`` -> bool
    (H, W), True where a moving object is seen or casts a shadow (from a delta light) at ``t_s``, dilated."""

    def __init__(self, rnd):
        self.rnd = rnd
        mi, dr = rnd.mi, rnd._dr
        self.mi, self.dr = mi, dr
        moving = set(rnd._moving) - {"camera"}
        self._static = [s for s in rnd.mi_scene.shapes() if s.id() not in moving]
        self._delta = [e for e in rnd.mi_scene.emitters()
                       if mi.has_flag(e.flags(), mi.EmitterFlags.Delta)]
        h, w = rnd.height, rnd.width
        sub = (np.arange(SUBPIXEL) + 0.5) / SUBPIXEL  # the rays' offsets inside a pixel
        shape = (h, w, SUBPIXEL, SUBPIXEL)
        py = np.broadcast_to(np.arange(h)[:, None, None, None] + sub[None, None, :, None], shape)
        px = np.broadcast_to(np.arange(w)[None, :, None, None] + sub[None, None, None, :], shape)
        self._pos = (mi.Float((px.ravel() / w).astype(np.float32)), mi.Float((py.ravel() / h).astype(np.float32)))
        self._n = SUBPIXEL * SUBPIXEL

    @property
    def anything_moves(self) -> bool:
        return bool(set(self.rnd._moving) - {"camera"})

    def _moving_hit(self, si):
        """True where ``si`` is a valid hit on none of the static shapes (so on a moving one)."""
        mi = self.mi
        hit = si.is_valid()
        for s in self._static:
            hit &= si.shape != mi.ShapePtr(s)
        return hit

    def __call__(self, t_s: float) -> np.ndarray:
        rnd, mi = self.rnd, self.mi
        if not self.anything_moves:  # a still scene: every pixel keeps its value
            return np.zeros((rnd.height, rnd.width), bool)
        rnd.set_time(t_s)
        fl = rnd.frame_launch
        m = mi.Float([float(x) for x in np.asarray(rnd._cam_m, np.float32).reshape(16)])
        o, d, maxt = fl.primary_rays(fl.pose(m), mi.Vector2f(*self._pos))
        si = rnd.mi_scene.ray_intersect(mi.Ray3f(o, d, maxt, 0.0))
        cov = self._moving_hit(si)
        for e in self._delta:
            ds, _ = e.sample_direction(si, mi.Point2f(0.5, 0.5), True)
            sh = rnd.mi_scene.ray_intersect(si.spawn_ray_to(ds.p))
            cov |= si.is_valid() & self._moving_hit(sh)
        h, w = rnd.height, rnd.width
        c = np.asarray(cov, bool).reshape(h, w, self._n).any(axis=2)
        return dilate(c)


def region_means(frames: list[np.ndarray], mask: np.ndarray) -> float:
    """Mean over the pixels of ``mask`` of the variance of one of two independent renders ``frames``."""
    a, b = (np.asarray(f, np.float64)[mask] for f in frames)
    return float(np.mean((a - b) ** 2 / 2.0)) if a.size else 0.0


#: the dynamic region's budget is measured on the pixels dynamic at t = 0 when there are at least this many (fewer
#: would give a pair variance of a handful of pixels); else on the whole frame
MIN_BUDGET_PIXELS = 64


def square_count(n: int, cap: int, exact) -> int:
    """The least square count ``k^2 >= n`` (``multijitter`` then lays ``k x k`` strata, as at the pilot's levels 4,
    16, 64 ...), as the sampler takes it, at most ``cap`` (then the largest exact count below). A retry's counts are
    taken on this grid so that a few renders span a wide range; whether a count meets the band is measured, not
    assumed (on translating_object's static region 25 and 30 spp gave 2.3x the variance of 36 and 64 per
    n^1.5)."""
    from .noise import exact_below
    k = math.isqrt(max(1, int(n)) - 1) + 1  # ceil(sqrt(n))
    m = exact(k * k)
    return m if m <= cap else exact_below(exact, cap)


def static_spp(pilot: dict, mask: np.ndarray, rate_e: np.ndarray, rate_scale: float, window_intervals: int,
               target_ratio: float, max_spp: int, exact) -> dict:
    """The static frame's spp: each of its two renders at this count, averaged, gives the static pixels a
    ratio ``sqrt(W mean(v / 2) / mean(r + d)) <= target`` (``K = 1``), from the pilot pairs ``pilot``
    (``{spp: (Phi a, Phi b)}``) over ``mask``; ``rate_e`` (H, W) the rate plus dark current [e-/interval].
    Capped at :data:`STATIC_MAX_FACTOR` x ``max_spp``."""
    from .noise import Measured, exact_below
    ns = sorted(pilot)
    vs = [region_means(pilot[n], mask) * rate_scale ** 2 for n in ns]
    r = float(np.mean(rate_e[mask])) if mask.any() else 0.0
    cap = STATIC_MAX_FACTOR * int(max_spp)
    if not r > 0 or not any(v > 0 for v in vs):
        n = exact(1)
        need = n
    else:
        allowed = 2.0 * target_ratio ** 2 * r / window_intervals
        model = Measured(ns, vs)
        need = max(1, int(math.ceil(model.solve(allowed) - 1e-9)))
        n = exact(min(need, cap))
        if n > cap:
            n = exact_below(exact, cap)
    model = Measured(ns, vs) if any(v > 0 for v in vs) else None
    pred = math.sqrt(window_intervals * model(n) / 2.0 / r) if model is not None and r > 0 else float("nan")
    return {"spp": int(n), "spp_needed": int(need), "clipped": bool(need > cap), "predicted_ratio": pred,
            "n_pixels": int(mask.sum()), "mean_rate_e": r, "max_spp": cap}


def static_ratio(static: "StaticFrame", rnd, window_intervals: int, dark_e: float) -> float:
    """The render-noise ratio of the static frame's own pixels, ``sqrt(W mean(v) / mean(r + d))`` with ``v``
    the variance of its average (``K = 1``), measured by its two renders; nan without static pixels."""
    from .noise import render_noise_ratio
    m = static.valid
    if not m.any():
        return float("nan")
    from .photometry import apply_factors
    phi = apply_factors(static.raw_p, static.raw_e, rnd._factors)[0]  # as a keyframe's (render_frame_reused)
    phi_var = static.var_p * rnd._factors[0] ** 2
    return render_noise_ratio(rnd.rate_e(phi)[m], phi_var[m] * rnd.rate_scale() ** 2, window_intervals, 1.0,
                              dark_e)


def static_retry_spp(measured: list[tuple[int, float]], target_ratio: float, cap: int, exact) -> int | None:
    """The count to render the static frame again at, from the ``(spp, ratio)`` pairs measured so far (the last
    one missed the band); None when there is no new count to try.

    Between a count measured above the target and one below it: the power law through the nearest such pair,
    solved for the target. Above every count measured: the variance taken to fall like 1/n (the slowest the
    sampler converges, so conservative). Below every one: the ratio taken to grow like 1/n as the count falls (the
    variance like 1/n^2, the fastest). The answer at a square count (:func:`square_count`; the nearest one, and
    the nearest count the sampler takes below 4), within ``[1, cap]``, not one measured already; None too when no
    ratio measured is a number (static pixels without light or dark current)."""
    from .noise import exact_below
    seen = {int(n) for n, _ in measured}
    measured = [(n, r) for n, r in measured if math.isfinite(r)]
    if not measured:
        return None
    hi = [(n, r) for n, r in measured if r > target_ratio]  # counts that missed above
    lo = [(n, r) for n, r in measured if r <= target_ratio]
    if hi and lo and max(n for n, _ in hi) < min(n for n, _ in lo):
        (n1, r1), (n2, r2) = max(hi), min(lo)
        slope = math.log(r1 / r2) / math.log(n2 / n1) if r2 > 0 and r1 > r2 else 1.0  # ratio ~ n^-slope
        want = n1 * (r1 / target_ratio) ** (1.0 / max(slope, 1e-6))
        # the square count strictly between the two nearest the answer (in log), else the nearest exact count
        sq = [exact(k * k) for k in range(math.isqrt(n1) + 1, math.isqrt(max(n2 - 1, 0)) + 1)]
        sq = [m for m in sq if n1 < m < n2] or [exact(int(round(min(max(want, n1 + 1), n2 - 1))))]
        m = min(sq, key=lambda c: abs(math.log(c / want)))
        return None if m in seen or not n1 < m < n2 else int(m)
    elif not lo:  # every count so far too noisy
        n1, r1 = max(hi)
        want = max(n1 * (r1 / target_ratio) ** 2, n1 + 1)
    else:  # every count so far below the band
        n2, r2 = min(lo)
        want = max(1.0, n2 * r2 / target_ratio)
    k = max(1, int(round(math.sqrt(want))))
    m = exact(k * k) if want >= 4 else exact(max(1, int(round(want))))
    if not lo and m < want:  # going up: at least the conservative count
        m = square_count(int(math.ceil(want - 1e-9)), cap, exact)
    m = min(m, exact_below(exact, cap)) if m > cap else m
    return None if m in seen else int(m)


class StaticFrame:
    """The static frame: raw channels (H, W) averaged over two renders at ``spp``, their per-pixel variance
    (raw Phi units^2, of the average) and which pixels hold a static value (``valid``: not dynamic at t = 0).
    ``renders``: the two renders ``((Phi_raw, E_raw), (Phi_raw, E_raw))`` at t = 0 when they exist already (a pair
    of the noise pilot's, made with ``seeds``); else they are rendered here."""

    def __init__(self, rnd, spp: int, seeds, valid: np.ndarray, renders=None):
        if renders is None:
            a = rnd.render_exact(0.0, seeds[:len(rnd.launch_counts(spp))], spp)
            b = rnd.render_exact(0.0, seeds[len(rnd.launch_counts(spp)):], spp)
        else:
            a, b = renders
        self.spp = int(spp)
        self.seeds = [int(s) for s in seeds]
        self.raw_p = 0.5 * (a[0] + b[0])
        self.raw_e = 0.5 * (a[1] + b[1])
        self.var_p = (a[0] - b[0]) ** 2 / 4.0  # variance of the average of two independent renders
        self.valid = np.asarray(valid, bool)


def render_frame_reused(rnd, static: StaticFrame, cov: Coverage, t_s: float, base_seed: int, spp: int,
                        variance: bool) -> dict:
    """The keyframe at ``t_s`` with static-region reuse: its dynamic pixels (``cov(t_s)``, and those without a
    static value) rendered at ``spp``, the rest from ``static``. The dict of
    :meth:`.renderer.SceneRenderer.render_frame`, plus ``dynamic`` (bool (H, W)); with ``variance`` a second
    render of the dynamic pixels gives their variance, and ``phi_var`` holds the static frame's variance
    elsewhere."""
    from .frozen import max_padded_pixels
    from .photometry import apply_factors
    from .sampling import frame_seeds
    dyn = cov(t_s) | ~static.valid
    pix = np.flatnonzero(dyn)
    n = len(rnd.launch_counts(spp, n_pixels=max_padded_pixels(pix.size)))
    seeds = frame_seeds(base_seed, t_s, 2 * n)
    raw_p, raw_e = static.raw_p.copy(), static.raw_e.copy()
    a_p = None
    if pix.size:
        a_p, a_e = rnd.render_pixels(t_s, seeds[:n], spp, pix)
        raw_p.flat[pix] = a_p
        raw_e.flat[pix] = a_e
    phi, lux = apply_factors(raw_p, raw_e, rnd._factors)
    out = {"time_s": float(t_s), "phi": phi, "lux": lux, "seeds": list(seeds[:n]), "spp": int(spp),
           "phi_var": None, "dynamic": dyn}
    if variance:
        var = static.var_p.copy()
        if pix.size:
            b_p, _ = rnd.render_pixels(t_s, seeds[n:], spp, pix)
            var.flat[pix] = (a_p - b_p) ** 2 / 2.0
        out["phi_var"] = var * rnd._factors[0] ** 2
        out["variance_seeds"] = list(seeds[n:])
    return out


def static_check(rnd, static: StaticFrame, dynamic: np.ndarray, t_s: float, base_seed: int, spp: int,
                 floor_raw: np.ndarray) -> dict:
    """The whole frame rendered at ``t_s`` and ``spp``, against the static frame on the pixels static at
    ``t_s``: the mean of ``(full - static)^2 / (v_full + v_static)`` (each variance smoothed over 5 x 5
    pixels; ``floor_raw`` is one keyframe's, raw Phi units^2). About 1 where the static region did not change
    (less where the variances are over-estimated); ``limit``: 1 + :data:`STATIC_CHECK_SIGMAS` standard errors."""
    from scipy.ndimage import uniform_filter
    counts = rnd.launch_counts(spp)
    seeds = np.random.SeedSequence([int(base_seed), 0xC4EC, int(round(float(t_s) * 1e9))]).generate_state(
        len(counts), np.uint32)
    full_p, _ = rnd.render_exact(t_s, [int(s) for s in seeds], spp)
    m = static.valid & ~np.asarray(dynamic, bool)
    n = int(m.sum())
    if not n:
        return {"time_s": float(t_s), "n_pixels": 0, "z2_mean": None, "limit": None}
    v = np.asarray(floor_raw, np.float64) + uniform_filter(static.var_p, size=5, mode="nearest")
    z2 = (full_p - static.raw_p) ** 2 / np.maximum(v, 1e-300)
    return {"time_s": float(t_s), "n_pixels": n, "z2_mean": float(z2[m].mean()),
            "limit": float(1.0 + STATIC_CHECK_SIGMAS * math.sqrt(2.0 / n))}


def check_warning(checks: list[dict]) -> str | None:
    """A warning naming the static checks whose difference exceeds their limit, or None."""
    bad = [c for c in checks if c.get("z2_mean") is not None and c["z2_mean"] > c["limit"]]
    if not bad:
        return None
    c = max(bad, key=lambda c: c["z2_mean"] / c["limit"])
    return (f"the static region changed: at t = {c['time_s']:.6g} s its pixels differ from the static frame by "
            f"{c['z2_mean']:.2f} times their expected variance (limit {c['limit']:.2f}; {len(bad)} of "
            f"{len(checks)} checks): light from a moving object reaches pixels the coverage test counts as static "
            "(an inter-reflection, blocked sky light); render with render.static_reuse: false")
