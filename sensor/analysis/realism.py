"""Realism report: a real spike recording against each spike model, statistic by statistic.

Each model is simulated for the recording's duration and shape, with each pixel's light estimated
from its recorded rate (:mod:`sensor.analysis.light`); the statistics of :mod:`sensor.analysis.statistics`
are computed alike on the recording and on every simulation, and the distance D sums up how far each
model is. :mod:`sensor.analysis.fit` fits the profile's dark rate and threshold to the recording;
:mod:`sensor.analysis.report` writes the result.
"""

from __future__ import annotations

import numpy as np

from sensor.analysis.fit import FIT_STATISTICS, FitResult, fit_profile, scaled_profile
from sensor.analysis.light import estimate_light, rate_light_curve, simulate_after_warmup
from sensor.analysis.report import RealismResult, write_report
from sensor.analysis.statistics import (DISTANCE_MEANING, checked_recording, distance, spike_statistics,
                                        stationary_pixels)
from sensor.models.spec import ModelSpec, parse_models
from sensor.profile import SensorProfile

DEFAULT_MODELS = ("elssim:interval", "elssim:crossing", "isi", "ideal")


def realism(spikes, profile: SensorProfile, models=DEFAULT_MODELS, *, seed: int = 0, segments: int = 4,
            alpha: float = 0.01, curve_intervals: int = 8000, max_warmup: int = 4000, progress=None,
            **stat_kw) -> RealismResult:
    """Compare a real recording with each model: statistics rows, distances and notes on what was done.

    Parameters
    ----------
    spikes : bool (T, H, W)
        The real recording (image orientation).
    profile : SensorProfile
        Sensor of the same H x W (use ``profile.window`` for a crop).
    models : sequence of str or ModelSpec
        ``name[:reset]`` (see :func:`parse_models`). Each model is simulated for
        the same T, H, W with light estimated per pixel from the recording.
    seed : int
        Seed of every simulation (child seeds per model and for the curves).
    segments, alpha : stationarity test (:func:`stationary_pixels`).
    curve_intervals : intervals of the rate-light curve simulation (:func:`rate_light_curve`).
    max_warmup : most intervals simulated and dropped before the compared stream (the recording starts with
        every pixel at a random phase, a simulation with empty integrators).
    """
    say = progress or (lambda msg: None)
    s, (T, H, W) = checked_recording(spikes, profile)
    specs = parse_models(",".join(m.label if isinstance(m, ModelSpec) else m for m in models))
    keep, st = stationary_pixels(s, segments, alpha)
    say(f"stationarity: {st['stationary']} of {H * W} pixels pass (neighbourhood counts in {segments} segments: "
        f"{st['fail_counts']} fail; ISI trend: {st['fail_isi_trend']} fail; alpha {alpha})")
    rows = spike_statistics(s, keep, source="real", **stat_kw)
    rate = s.sum(axis=0, dtype=np.int64) / T
    notes = {"recording": {"intervals": T, "height": H, "width": W, "mean_rate_per_interval": float(rate.mean())},
             "profile": profile.name, "seed": seed,
             "motion": (f"A pixel enters the ISI and Fano statistics only if (1) the spike counts of its 3x3 "
                        f"neighbourhood in {segments} equal segments pass a chi-square dispersion test and (2) its "
                        f"ISIs show no linear trend (t-test on the slope), both at alpha = {alpha}, and no pixel of "
                        f"its 3x3 neighbourhood fails either test (motion is spatially coherent): "
                        f"{st['stationary']} of {H * W} real pixels pass ({st['fail_counts']} fail the count test, "
                        f"{st['fail_isi_trend']} the trend test). Each simulated stream uses the real stationary "
                        "pixels that also pass the same tests on their own simulated spikes, so the selection acts "
                        "alike on both. The rate histogram and the dark/hot-pixel statistics use all pixels (the "
                        "simulation reproduces each pixel's mean rate). The tests miss changes that average out "
                        "within a segment and have little power for pixels with 1-3 spikes."),
             "stationarity": st,
             "mean_isi": "T / n_spikes of the pixel [intervals]", "models": {}}
    # the camera was running before the recording began, a simulation starts with empty integrators: simulate a
    # warm-up of several ISIs of the slowest firing pixel (at least T, at most max_warmup) and drop it
    n_min = int(rate[rate > 0].min() * T) if np.any(rate > 0) else 1
    warmup = int(min(max_warmup, max(T, 4 * int(np.ceil(T / max(n_min, 1))))))
    notes["warmup_intervals"] = warmup
    distances = {}
    for i, spec in enumerate(specs):
        prof = spec.profile(profile)
        child = np.random.SeedSequence(int(seed), spawn_key=(i,))  # one child seed per model
        sim_seed, curve_seed = (int(x) for x in child.generate_state(2))
        say(f"{spec.label}: estimating each pixel's light")
        lam, how = estimate_light(rate, prof, spec.name, seed=curve_seed, curve_intervals=curve_intervals)
        say(f"{spec.label}: simulating {warmup} + {T} intervals of {H} x {W}")
        sim = simulate_after_warmup(lam, T, warmup, prof, spec.name, sim_seed)
        keep_m = keep & stationary_pixels(sim, segments, alpha)[0]
        rows.extend(spike_statistics(sim, keep_m, source=spec.label, **stat_kw))
        distances[spec.label] = distance(rows, model=spec.label)
        notes["models"][spec.label] = {"model": spec.name, "reset": prof.reset, "light_estimate": how,
                                       "simulation_seed": sim_seed, "stationary_pixels": int(keep_m.sum()),
                                       "mean_rate_per_interval": float(sim.mean())}
    return RealismResult(rows, distances, notes)


def add_fitted_models(result: RealismResult, spikes, profile: SensorProfile, fit: FitResult, models, *,
                      seed: int = 0, segments: int = 4, alpha: float = 0.01, progress=None, **kw) -> dict:
    """Simulate the ``elssim`` models of ``models`` again with ``fit``'s scales; add them to ``result``.

    ``profile`` is the one ``result`` was made with (same H x W as ``spikes``).
    Rows and distances are added as ``"LABEL (fitted)"``; ``result.notes["fit"]``
    gets the fit's summary and the distance D of each elssim model before and
    after, which is also returned ({"before_D": {...}, "after_D": {...}}).
    """
    specs = parse_models(",".join(m.label if isinstance(m, ModelSpec) else m for m in models))
    elssim = [s for s in specs if s.name == "elssim"]
    from sensor.analysis.fit import as_dark_mode
    profile = as_dark_mode(profile, fit.base_profile.dark if fit.base_profile is not None else None)
    fitted = scaled_profile(profile, fit.dark_scale, fit.threshold_scale, name=f"{profile.name}-fitted")
    label = {s.label: f"{s.label} (fitted)" for s in elssim}
    if elssim:
        again = realism(spikes, fitted, elssim, seed=seed, segments=segments, alpha=alpha, progress=progress, **kw)
        result.rows.extend(dict(r, source=label[r["source"]]) for r in again.rows if r["source"] in label)
        for m, d in again.distances.items():
            result.distances[label[m]] = d
        result.notes.setdefault("models", {}).update({label[m]: v for m, v in again.notes["models"].items()})
    change = {"before_D": {s.label: result.distances[s.label]["D"] for s in elssim if s.label in result.distances},
              "after_D": {s.label: result.distances[label[s.label]]["D"] for s in elssim}}
    result.notes["fit"] = {**fit.summary(), **change}
    return change


__all__ = ["realism", "spike_statistics", "stationary_pixels", "estimate_light", "rate_light_curve",
           "simulate_after_warmup", "parse_models", "write_report", "fit_profile", "add_fitted_models",
           "scaled_profile", "FitResult", "RealismResult", "ModelSpec", "DEFAULT_MODELS", "DISTANCE_MEANING",
           "FIT_STATISTICS"]
