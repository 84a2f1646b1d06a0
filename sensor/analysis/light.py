"""The light behind a recording: per-pixel light that makes a model fire at the recorded rate, and the
simulation of a model under that light after a warm-up."""

from __future__ import annotations

import numpy as np

from sensor.profile import SensorProfile


def _uses_gain(model: str) -> bool:
    # ``ideal`` ignores every fixed-pattern map (Algorithm 1); elssim and isi need ceil(theta / g) photoelectrons
    return model != "ideal"


def rate_light_curve(profile: SensorProfile, model: str, *, seed: int = 0, n_levels: int = 48, n_pixels: int = 16,
                     n_intervals: int = 8000):
    """The model's spike rate as a function of light, measured by simulation on a uniform sensor.

    A ``n_levels x n_pixels`` sensor with ``profile``'s threshold, reset,
    interval and median refractory time and dark rate, no PRNU and no hot
    pixels; row j receives ``lambda_j = theta * x_j`` photoelectrons per
    interval (``x`` = 0, then 1e-3 .. 4 log-spaced) for ``n_intervals``
    intervals. Returns (lambda [e-/interval] (n_levels,), rate [spikes/interval]
    (n_levels,), made non-decreasing).
    """
    from sensor.simulator import simulate
    kw = {"reset": profile.reset}
    # dark events at the median rate; a dark current is not put in the curve (it is per pixel: estimate_light
    # inverts to lambda + d and takes each pixel's d off)
    uni = SensorProfile.synthetic(n_levels, n_pixels, threshold_e=profile.threshold_e,
                                  dark_rate=float(np.median(profile.dark_rate)) if profile.dark == "events" else 0.0,
                                  refractory_s=float(np.median(profile.refractory_s)), interval_s=profile.interval_s,
                                  clock_hz=profile.clock_hz, name="rate-light-curve", **kw)
    lam = profile.threshold_e * np.concatenate([[0.0], np.geomspace(1e-3, 4.0, n_levels - 1)])
    rate_e = np.broadcast_to(np.repeat(lam[:, None], n_pixels, axis=1).astype(np.float32)[None],
                             (n_intervals, n_levels, n_pixels))
    s = simulate(rate_e, uni, model, seed=seed)
    # stationary rate without the start-up transient (the stream starts with an empty integrator): per row,
    # (spikes - 1) / (last - first spike time) pooled over its pixels; the plain fraction where that is undefined
    T = s.shape[0]
    any_ = s.any(axis=0)
    first = np.where(any_, s.argmax(axis=0), 0)
    last = np.where(any_, T - 1 - s[::-1].argmax(axis=0), 0)
    n = s.sum(axis=0, dtype=np.int64)
    span = np.where(n >= 2, last - first, 0).sum(axis=1)
    r = np.where(span > 0, np.maximum(n - 1, 0).sum(axis=1) / np.maximum(span, 1), s.mean(axis=(0, 2)))
    return lam, np.maximum.accumulate(r)


def estimate_light(rate, profile: SensorProfile, model: str, *, seed: int = 0, curve_intervals: int = 8000):
    """Per-pixel light [e-/interval] that makes ``model`` fire at ``rate`` [spikes/interval]; and how.

    * ``elssim`` with the interval reset: the exact renewal relation, inverted
      per pixel with its own k = ceil(theta / g), refractory fraction and dark
      probability (:func:`sensor.analysis.theory.invert_renewal_rate`).
    * any other model / reset: the model's rate-light curve measured by
      simulation on a uniform sensor (:func:`rate_light_curve`), inverted by
      linear interpolation; for models that use the PRNU gain the light is then
      divided by the pixel's gain (it needs ~theta/g photoelectrons). Per-pixel
      dark-rate differences are not removed (the curve has the median dark rate).

    With ``dark == "current"`` (every model but ``ideal``) the pixel's rate comes from ``lambda + d``: both
    inversions run without dark events and the pixel's dark current ``d`` is taken off (clipped at 0).

    Returns (lambda (H, W) float32, description str).
    """
    from sensor.models.effects import count_threshold, dark_event_probability
    from sensor.analysis.theory import invert_renewal_rate
    rate = np.asarray(rate, np.float64)
    current = profile.dark == "current" and _uses_gain(model)
    d = profile.dark_current_e.astype(np.float64)
    dc_note = "; minus the pixel's dark current (dark = current)" if current else ""
    if model == "elssim" and profile.reset == "interval":
        k = count_threshold(profile.threshold_e, profile.prnu_gain)
        lam = invert_renewal_rate(rate, k, profile.refractory_fraction, dark_event_probability(profile.dark_rate))
        if current:
            lam = np.maximum(lam - d, 0.0)
        return lam.astype(np.float32), ("exact renewal inversion per pixel (k = ceil(theta/g), refractory, dark "
                                        "probability; sensor.analysis.theory.invert_renewal_rate)" + dc_note)
    lam_c, r_c = rate_light_curve(profile, model, seed=seed, n_intervals=curve_intervals)
    # strictly increasing support for the interpolation (plateaus: take the first light level of each rate)
    r_u, first = np.unique(r_c, return_index=True)
    lam = np.interp(rate, r_u, lam_c[first])
    lam = np.where(rate <= r_u[0], 0.0, lam)
    if _uses_gain(model):
        lam = lam / np.asarray(profile.prnu_gain, np.float64)
    if current:
        lam = np.maximum(lam - d, 0.0)
    return lam.astype(np.float32), (f"rate-light curve of the model measured by simulation ({lam_c.size} levels x 16 "
                                    f"pixels x {curve_intervals} intervals, median dark and refractory, no PRNU), "
                                    "inverted by interpolation" + (", divided by the pixel's PRNU gain"
                                                                   if _uses_gain(model) else "") + dc_note)


def simulate_after_warmup(lam, T: int, warmup: int, profile, model: str, seed: int, chunk: int = 1024):
    """bool (T, H, W): ``model`` under constant light ``lam`` (H, W) after ``warmup`` discarded intervals.

    Streamed, so memory holds the kept T intervals plus one chunk.
    """
    from sensor.simulator import SpikeSimulator
    sim = SpikeSimulator(profile, model, seed, per_interval=True)
    lam = np.asarray(lam, np.float32)
    total = warmup + T
    kept: list[np.ndarray] = []
    n_kept = produced = fed = 0

    def take(block):
        nonlocal n_kept, produced
        kept.append(block)
        n_kept += block.shape[0]
        produced += block.shape[0]
        # the first block is not needed when the rest plus what is still to come covers the last T intervals
        while kept and n_kept - kept[0].shape[0] + (total - produced) >= T:
            n_kept -= kept.pop(0).shape[0]

    while fed < total:
        n = min(chunk, total - fed)
        for block in sim.iter_feed(np.broadcast_to(lam[None], (n,) + lam.shape)):
            take(block)
        fed += n
    take(sim.finish())
    s = np.concatenate(kept)
    return np.ascontiguousarray(s[s.shape[0] - T:])
