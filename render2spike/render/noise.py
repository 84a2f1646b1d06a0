"""Monte Carlo noise budget: choose spp so render noise stays well below photon shot noise.

Definitions (per pixel, rate in e-/interval)
--------------------------------------------
* ``r``: expected photoelectrons per interval; ``v``: the Monte Carlo variance
  of its rendered estimate in one keyframe.
* Over a reconstruction window of ``W`` intervals the photoelectron count has
  shot-noise variance ``W r``. The sensor integrates the rate interpolated
  between keyframes, so the render errors of the ``K = max(1, W T_r f_key)``
  keyframes in the window (base keyframe rate ``f_key``) add up independently:
  variance ``W^2 v / K``.
* render-noise ratio ``rho = sqrt(W mean(v) / (K mean(r)))``: RMS render
  error over RMS shot noise in the window, averaged over the image.
* The spp is chosen so that ``rho <= target_ratio`` (default 0.2: render
  variance <= 4 % of shot-noise variance), clipped to [min_spp, max_spp].

The per-keyframe variance's dependence on spp is measured, not assumed: the
stratified sampler converges faster than 1/spp, so a pilot renders two
independent pairs at ``n1 = pilot_spp`` and ``n2 = 4 n1`` samples at t = 0,
estimates ``v(n) = mean over pixels of (a - b)^2 / 2`` at both and reports the
convergence exponent ``alpha`` of ``v ~ n^-alpha`` (clipped to [1, 2]). The
spp is then solved from ``v(n) = v(n2) n2 / n`` (alpha = 1 beyond n2): with
stratified sampling ``n v(n)`` does not grow with n, so this is conservative
(the measured per-frame ratio is at most the predicted one, up to noise).
Every frame then measures its own ``rho`` from its two independent halves
(recorded in the frame header as ``render_noise_ratio``).
"""

from __future__ import annotations

import math

import numpy as np


def keyframes_per_window(window_intervals: int, interval_s: float, keyframe_rate_hz: float) -> float:
    """K: independent keyframes whose errors average inside a window (at least 1)."""
    return max(1.0, float(window_intervals) * float(interval_s) * float(keyframe_rate_hz))


def render_noise_ratio(rate_e, rate_var, window_intervals: int, k_frames: float = 1.0) -> float:
    """``sqrt(W mean(v) / (K mean(r)))`` for rate_e [e-/interval] and its MC variance; nan if dark or unknown."""
    r = float(np.mean(rate_e))
    if not r > 0 or rate_var is None:
        return float("nan")
    return float(math.sqrt(window_intervals * float(np.mean(rate_var)) / (k_frames * r)))


def pair_variance(a, b) -> np.ndarray:
    """Per-pixel variance of ONE of two independent estimates a, b: (a - b)^2 / 2."""
    return (np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2 / 2.0


def choose_spp(rate_e, var_n1: float, n1: int, var_n2: float, n2: int, window_intervals: int, k_frames: float,
               target_ratio: float, min_spp: int, max_spp: int) -> dict:
    """The spp meeting the budget from pilot variances (mean over pixels, rate units) at n1 and n2 spp."""
    r = float(np.mean(rate_e))
    if var_n2 > 0 and var_n1 > 0:
        alpha = float(np.clip(math.log(var_n1 / var_n2) / math.log(n2 / n1), 1.0, 2.0))
    else:
        alpha = 1.0
    allowed = target_ratio ** 2 * k_frames * r / window_intervals  # max per-keyframe variance
    if not r > 0 or var_n2 <= 0:
        need = min_spp
    else:
        need = math.ceil(n2 * var_n2 / allowed)
    spp = int(min(max(need, min_spp), max_spp))

    def predicted(n):
        if not r > 0:
            return float("nan")
        v = var_n2 * n2 / n
        return math.sqrt(window_intervals * v / (k_frames * r))
    return {"spp": spp, "spp_needed": int(max(need, 1)), "predicted_ratio": predicted(spp), "alpha": alpha,
            "mean_rate_e": r, "pilot": {"spp": [int(n1), int(n2)], "mean_var_rate_e2": [float(var_n1), float(var_n2)]},
            "window_intervals": int(window_intervals), "keyframes_per_window": float(k_frames),
            "target_ratio": float(target_ratio), "clipped": bool(need > max_spp)}
