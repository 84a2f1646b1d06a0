"""Fitting the global dark rate and threshold of a profile to a real recording (elssim, its own reset).

The dark term is fitted in the profile's own dark mode (``profile.dark``) or in the one asked for
(``dark_mode``): ``events`` scales the dark-event map ``dark_rate``; ``current`` scales the dark current
``dark_current_e`` (see :func:`scaled_profile` and :func:`as_dark_mode`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sensor.analysis.light import simulate_after_warmup
from sensor.analysis.statistics import checked_recording, distance, spike_statistics, stationary_pixels
from sensor.errors import InputError
from sensor.profile import SensorProfile

#: statistics the fit matches (the rate histogram and the outliers are reproduced by the per-pixel light estimate
#: whatever the parameters, so they carry no information on them)
FIT_STATISTICS = ("isi_cv", "isi_lag1", "fano")
#: grids of the fit: multipliers of the profile's dark-rate map (0 = no dark events) and of its threshold theta
DARK_SCALES = (0.0, 0.05, 0.1, 0.2, 0.35, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0)
THRESHOLD_SCALES = (0.125, 0.18, 0.25, 0.35, 0.5, 0.7, 1.0, 1.4, 2.0, 2.8, 4.0, 5.6, 8.0)
#: how far the grids grow when the minimum sits on their edge: threshold scales within these bounds (steps of
#: sqrt 2), dark scales up to this multiple (steps of x1.5)
THRESHOLD_SCALE_LIMITS = (1.0 / 64.0, 64.0)
DARK_SCALE_LIMIT = 20.0


def grow_grid(grid, dsc, tsc, objective, t_limits=THRESHOLD_SCALE_LIMITS, d_limit=DARK_SCALE_LIMIT):
    """Extend the (dark, threshold) grid while its minimum sits on an open edge; returns (grid, dsc, tsc).

    ``grid`` (len(dsc), len(tsc)) holds ``objective(d, t)``. A minimum on the largest or smallest threshold
    scale adds three geometric steps (sqrt 2) beyond it, within ``t_limits``; one on the largest dark scale
    adds three steps of x1.5, up to ``d_limit`` (the dark scale's lower edge, 0, is the no-dark model, not an
    edge to grow past). So a minimum is interior, or on a limit that the notes report.
    """
    grid, dsc, tsc = np.asarray(grid, float), list(dsc), list(tsc)
    while True:
        i, j = np.unravel_index(int(np.nanargmin(grid)), grid.shape)
        if j == len(tsc) - 1 and tsc[-1] < t_limits[1]:
            new = [x for x in (tsc[-1] * 2 ** (k / 2) for k in (1, 2, 3)) if x <= t_limits[1] * (1 + 1e-9)]
            cols = np.array([[objective(d, t) for t in new] for d in dsc])
            grid, tsc = np.concatenate([grid, cols], axis=1), tsc + new
        elif j == 0 and tsc[0] > t_limits[0]:
            new = [x for x in (tsc[0] / 2 ** (k / 2) for k in (3, 2, 1)) if x >= t_limits[0] * (1 - 1e-9)]
            cols = np.array([[objective(d, t) for t in new] for d in dsc])
            grid, tsc = np.concatenate([cols, grid], axis=1), new + tsc
        elif i == len(dsc) - 1 and 0 < dsc[-1] < d_limit:
            new = [x for x in (dsc[-1] * 1.5 ** k for k in (1, 2, 3)) if x <= d_limit * (1 + 1e-9)]
            rows = np.array([[objective(d, t) for t in tsc] for d in new])
            grid, dsc = np.concatenate([grid, rows], axis=0), dsc + new
        else:
            return grid, dsc, tsc


@dataclass
class FitResult:
    """Result of :func:`fit_profile`: scales of the dark-rate map and the threshold, their spread and the profile."""

    profile: SensorProfile
    dark_scale: float
    dark_scale_sd: float
    threshold_scale: float
    threshold_scale_sd: float
    per_seed: list
    notes: dict = field(default_factory=dict)
    #: the profile the scales apply to (``profile`` in the fitted dark mode, before scaling)
    base_profile: SensorProfile | None = None

    def summary(self) -> dict:
        hm = self.profile.hot_mask
        return {"dark_scale": self.dark_scale, "dark_scale_sd": self.dark_scale_sd,
                "threshold_scale": self.threshold_scale, "threshold_scale_sd": self.threshold_scale_sd,
                "threshold_e": float(self.profile.threshold_e), "dark": self.profile.dark,
                "dark_rate_mean_per_interval": float(self.profile.dark_rate[~hm].mean()) if (~hm).any() else 0.0,
                "dark_current_e_mean": float(self.profile.dark_current_e[~hm].mean()) if (~hm).any() else 0.0,
                "per_seed": self.per_seed, **self.notes}


def scaled_profile(profile: SensorProfile, dark_scale: float, threshold_scale: float,
                   name: str | None = None) -> SensorProfile:
    """``profile`` with its dark firing rate multiplied by ``dark_scale`` and its threshold [e-] by ``threshold_scale``.

    ``dark == "events"``: the dark-rate map times ``dark_scale``. ``dark == "current"``: the dark current [e-]
    times ``dark_scale * threshold_scale``, so that ``dark_scale`` multiplies the dark firing rate ``d / theta``
    in both modes (a dark current fixed in e- would fire 8x less at 8x the threshold). The hot-pixel charge
    (``hot_mu``, ``hot_sigma``) is stored in threshold units, so it scales with theta.
    """
    ds, ts = float(dark_scale), float(threshold_scale)
    if profile.dark == "current":
        dark = {"dark_current_e": (profile.dark_current_e * (ds * ts)).astype(np.float32)}
    else:
        dark = {"dark_rate": (profile.dark_rate * ds).astype(profile.dark_rate.dtype)}
    return profile.replace(threshold_e=float(profile.threshold_e) * ts, name=name or profile.name, **dark)


def as_dark_mode(profile: SensorProfile, mode: str | None) -> SensorProfile:
    """``profile`` with dark current as ``mode`` (``"events"`` or ``"current"``; None: unchanged), same dark firing rate.

    events -> current: ``d = mu_DC theta / g`` [e-/interval] (a pixel that fires every theta / g dark electrons
    fires mu_DC times per interval on average, as its dark events did); current -> events: the inverse.
    """
    if mode is None or mode == profile.dark:
        return profile
    g = profile.prnu_gain.astype(np.float64)
    zero = np.zeros(profile.shape, np.float32)
    if mode == "current":
        d = profile.dark_rate.astype(np.float64) * profile.threshold_e / g
        return profile.replace(dark="current", dark_rate=zero, dark_current_e=d.astype(np.float32),
                               name=f"{profile.name}-dark-current")
    if mode == "events":
        mu = profile.dark_current_e.astype(np.float64) * g / profile.threshold_e
        return profile.replace(dark="events", dark_current_e=zero, dark_rate=mu.astype(np.float32),
                               name=f"{profile.name}-dark-events")
    raise InputError(f"unknown dark mode '{mode}'; valid choices: events, current", field="dark_mode")


def _pixel_profile(profile: SensorProfile, idx) -> SensorProfile:
    """A 1 x N profile of the pixels ``idx`` (flat indices) of ``profile``."""
    from dataclasses import replace as _replace
    from sensor.profile import MAP_NAMES
    maps = {nm: getattr(profile, nm).reshape(-1)[idx][None, :].copy() for nm in MAP_NAMES}
    return _replace(profile, name=f"{profile.name}[{len(idx)} pixels]", height=1, width=len(idx), raw_width=None,
                    **maps)


def _parabola_min(xs, ds, i):
    """Abscissa of the vertex of the parabola through the grid point ``i`` and its two neighbours (clipped)."""
    if i == 0 or i == len(xs) - 1:
        return float(xs[i])
    x, y = np.asarray(xs[i - 1:i + 2], float), np.asarray(ds[i - 1:i + 2], float)
    a = np.polyfit(x, y, 2)
    if a[0] <= 0:
        return float(xs[i])
    return float(np.clip(-a[1] / (2 * a[0]), x[0], x[2]))


def fit_profile(spikes, profile: SensorProfile, *, seed: int = 0, n_seeds: int = 3, n_pixels: int = 1500,
                dark_scales=DARK_SCALES, threshold_scales=THRESHOLD_SCALES, segments: int = 4, alpha: float = 0.01,
                max_warmup: int = 4000, dark_mode: str | None = None, progress=None, **stat_kw) -> FitResult:
    """Fit the global dark rate and threshold of ``profile`` (elssim, its own reset) to a real recording.

    The recording fixes each pixel's light only through its rate, so what it can
    identify is the *shape* of the spike trains: the ISI coefficient of
    variation, lag-1 ISI correlation and Fano factors per mean-ISI bin
    (:data:`FIT_STATISTICS`). Dark events (a Poisson process at ``dark_rate``
    per interval) cut ISIs short and raise the CV; the threshold sets how many
    photoelectrons make a spike (CV ~ 1/sqrt(k) from photon noise).

    Method: ``n_pixels`` stationary, non-hot real pixels with >= 3 spikes are
    drawn at random (seeded; the draws are disjoint while the candidates last).
    At each grid point the pixels' light is the exact inversion of their rate
    for that profile (:func:`sensor.calibration.vidar.light_for_rate`), elssim simulates
    them (same T, a warm-up dropped, one fixed seed for every grid point: common
    random numbers) and the objective is the distance D (:func:`distance`)
    restricted to :data:`FIT_STATISTICS`. The whole grid of both scales is
    searched (they trade off: more dark events and a higher threshold can give
    a similar CV); the grid minimum is refined along each axis by a parabola
    through its neighbours. This is repeated for ``n_seeds`` independent pixel
    draws and simulation seeds; the estimate is the mean over draws and its
    uncertainty their standard deviation (the spread of one draw's estimate,
    which includes the choice of pixels).

    ``dark_mode``: fit the dark term as dark events (``"events"``) or as a dark current
    (``"current"``); None (default) keeps the profile's own. A profile of the other mode is first
    converted at the same dark firing rate (:func:`as_dark_mode`); the dark scale multiplies that
    rate in both modes (:func:`scaled_profile`).

    Returns a :class:`FitResult` whose ``profile`` is ``profile`` (in the fitted dark mode) scaled
    (:func:`scaled_profile`) by the mean scales.
    """
    import time

    from sensor.calibration.vidar import light_for_rate
    say = progress or (lambda msg: None)
    t0 = time.perf_counter()
    profile = as_dark_mode(profile, dark_mode)
    s, (T, H, W) = checked_recording(spikes, profile)
    if n_seeds < 1:
        raise InputError(f"n_seeds must be >= 1; got {n_seeds}", field="n_seeds")
    keep, _ = stationary_pixels(s, segments, alpha)
    counts = s.sum(axis=0, dtype=np.int64)
    cand = np.flatnonzero((keep & ~profile.hot_mask & (counts >= 3)).reshape(-1))
    if cand.size < 20:
        raise InputError(f"only {cand.size} stationary pixels with >= 3 spikes; the fit needs at least 20")
    flat = s.reshape(T, -1)
    dsc0, tsc0 = [float(x) for x in dark_scales], [float(x) for x in threshold_scales]
    per_seed = []
    # disjoint pixel draws while the candidates last (then they wrap round and share pixels)
    order = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(999,))).permutation(cand)
    n_pix = min(n_pixels, cand.size)
    disjoint = n_pix * n_seeds <= cand.size
    for r in range(n_seeds):
        sim_seed = int(np.random.SeedSequence(int(seed), spawn_key=(1000 + r,)).generate_state(1)[0])
        idx = np.sort(np.take(order, np.arange(r * n_pix, (r + 1) * n_pix), mode="wrap"))
        real = np.ascontiguousarray(flat[:, idx])[:, None, :]
        rate = counts.reshape(-1)[idx][None, :] / T
        base = _pixel_profile(profile, idx)
        n_min = max(int(counts.reshape(-1)[idx].min()), 1)
        warmup = int(min(max_warmup, max(T, 4 * int(np.ceil(T / n_min)))))
        real_rows = [q for q in spike_statistics(real, None, source="real", **stat_kw)
                     if q["statistic"].split("_w")[0] in FIT_STATISTICS]
        cache: dict = {}

        def objective(d, t):
            key = (d, t)
            if key not in cache:
                prof = scaled_profile(base, d, t)
                lam = light_for_rate(rate, prof).astype(np.float32)
                sim = simulate_after_warmup(lam, T, warmup, prof, "elssim", sim_seed)
                rows = real_rows + [q for q in spike_statistics(sim, None, source="model", **stat_kw)
                                    if q["statistic"].split("_w")[0] in FIT_STATISTICS]
                cache[key] = distance(rows)["D"]
            return cache[key]

        grid = np.array([[objective(d, t) for t in tsc0] for d in dsc0])  # (dark, threshold)
        grid, dsc, tsc = grow_grid(grid, dsc0, tsc0, objective)
        i, j = np.unravel_index(int(np.nanargmin(grid)), grid.shape)
        d_grid, t_grid = dsc[i], tsc[j]
        d_best = _parabola_min(dsc, grid[:, j], i)
        t_best = float(np.exp(_parabola_min(np.log(tsc), grid[i, :], j)))
        d_fit = objective(d_grid, t_grid)
        d_start = objective(1.0, 1.0) if (1.0 in dsc and 1.0 in tsc) else float("nan")
        per_seed.append({"seed": r, "pixels": int(idx.size), "warmup_intervals": warmup, "dark_scale": d_best,
                         "threshold_scale": t_best, "D_fit_statistics_at_start": float(d_start),
                         "D_fit_statistics_at_grid_min": float(d_fit), "evaluations": len(cache),
                         "at_grid_edge": bool(i in (0, len(dsc) - 1) and dsc[i] > 0 or j in (0, len(tsc) - 1)),
                         "grid_D": grid.round(3).tolist(), "dark_grid": dsc, "threshold_grid": tsc})
        say(f"fit seed {r}: dark x{d_best:.3g}, threshold x{t_best:.3g} (D on {'/'.join(FIT_STATISTICS)}: "
            f"{d_start:.2f} at x1, x1 -> {d_fit:.2f})")
    dv = np.array([p["dark_scale"] for p in per_seed])
    tv = np.log([p["threshold_scale"] for p in per_seed])
    d_mean, t_mean = float(dv.mean()), float(np.exp(tv.mean()))
    d_sd = float(dv.std(ddof=1)) if dv.size > 1 else float("nan")
    t_sd = float(t_mean * tv.std(ddof=1)) if tv.size > 1 else float("nan")
    fitted = scaled_profile(profile, d_mean, t_mean, name=f"{profile.name}-fitted")
    what = "dark-current scale (of the dark firing rate d / theta)" if profile.dark == "current" else \
        "dark-rate scale"
    notes = {"method": (f"grid search of the {what} (grid " + ", ".join(f"{x:g}" for x in dsc0)
                        + ") and threshold scale (grid " + ", ".join(f"{x:g}" for x in tsc0) + ", geometric; "
                        f"both grown while the minimum sits on an edge, threshold within x{THRESHOLD_SCALE_LIMITS[0]:g}"
                        f"-x{THRESHOLD_SCALE_LIMITS[1]:g}, dark up to x{DARK_SCALE_LIMIT:g}) "
                        f"minimising D over {', '.join(FIT_STATISTICS)} of elssim (reset {profile.reset}) "
                        f"on {min(n_pixels, cand.size)} random stationary pixels, refined by a parabola; mean "
                        f"over {n_seeds} pixel draws / simulation seeds, uncertainty = their standard deviation "
                        "(threshold: geometric mean, sd of the log times the mean)"),
             "reset": profile.reset, "dark_mode": profile.dark, "candidate_pixels": int(cand.size),
             "disjoint_draws": bool(disjoint),
             "seconds": time.perf_counter() - t0,
             "base_threshold_e": float(profile.threshold_e)}
    return FitResult(fitted, d_mean, d_sd, t_mean, t_sd, per_seed, notes, base_profile=profile)
