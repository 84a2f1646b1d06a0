"""Monte Carlo noise budget: choose spp so render noise stays well below photon shot noise.

Definitions (per pixel, rate in e-/interval)
--------------------------------------------
* ``r``: expected photoelectrons per interval, ``v``: the Monte Carlo variance
  of its rendered estimate. A render error is frozen over the frame, so over a
  reconstruction window of ``W`` intervals it contributes variance ``W^2 v``
  to the photoelectron count, whose shot-noise variance is ``W r``.
* render-noise ratio ``rho = sqrt(W * mean(v) / mean(r))``: the RMS render
  error over the RMS shot noise, averaged over the image (means over pixels).
* With single-sample variance ``v1`` (``v = v1 / spp``) the budget
  ``rho <= target`` needs ``spp >= W * mean(v1) / (target^2 * mean(r))``.

``v1`` is estimated from a pilot: two independent renders of ``pilot_spp``
samples at t = 0, ``v1 = pilot_spp * (a - b)^2 / 2``.
"""

from __future__ import annotations

import math

import numpy as np


def render_noise_ratio(rate_e, rate_var, window_intervals: int) -> float:
    """``sqrt(W mean(v) / mean(r))`` for rate_e [e-/interval] and its MC variance (same shape); nan if dark."""
    r = float(np.mean(rate_e))
    if not r > 0 or rate_var is None:
        return float("nan")
    return float(math.sqrt(window_intervals * float(np.mean(rate_var)) / r))


def single_sample_variance(a, b, pilot_spp: int) -> np.ndarray:
    """Per-pixel single-sample variance from two independent ``pilot_spp`` renders a, b."""
    return pilot_spp * (np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2 / 2.0


def choose_spp(rate_e, v1, window_intervals: int, target_ratio: float, min_spp: int, max_spp: int) -> dict:
    """The spp that meets the budget (clipped to [min_spp, max_spp]) and the ratio it is predicted to give."""
    r = float(np.mean(rate_e))
    mv1 = float(np.mean(v1))
    if not r > 0:
        need = min_spp
    else:
        need = math.ceil(window_intervals * mv1 / (target_ratio ** 2 * r))
    spp = int(min(max(need, min_spp), max_spp))
    pred = math.sqrt(window_intervals * mv1 / (spp * r)) if r > 0 else float("nan")
    return {"spp": spp, "spp_needed": int(max(need, 1)), "predicted_ratio": pred, "mean_rate_e": r,
            "mean_single_sample_var": mv1, "window_intervals": int(window_intervals),
            "target_ratio": float(target_ratio), "clipped": bool(need > max_spp)}
