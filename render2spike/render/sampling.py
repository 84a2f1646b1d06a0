"""Adaptive temporal sampling: keyframes at a base rate, refined where the sensor would see the difference.

Like ESIM's adaptive sampling, keyframes are placed so that the signal between
neighbours is well described by the interpolation the sensor stage uses
(piecewise-linear in time): starting from a uniform grid at ``base_rate_hz``,
the interval between two neighbouring keyframes is halved (its midpoint
rendered) while the estimated interpolation error exceeds ``tolerance`` and the
spacing is above ``1 / max_rate_hz``.

Criterion (:func:`interpolation_metric`), in the sensor's terms
----------------------------------------------------------------
A change that is linear in time costs nothing: linear interpolation
reproduces it (an edge crossing a pixel at constant speed is linear in time
while it is inside the pixel). What the sensor gets wrong is the *curvature*
of the per-pixel rate. From three equally spaced frames ``f0, f1, f2`` (spacing
``h``; rate ``r`` in e-/interval) the second difference
``D2 = f0 - 2 f1 + f2`` estimates the peak error of the linear interpolant
on the neighbouring segments as ``e = max(0, |D2| - z sigma) / 4`` (exact
``|D2| / 8`` for a parabola, up to ``|D2| / 2`` for a kink; ``sigma`` the Monte
Carlo standard deviation of ``D2``, so render noise never refines). Over the
sensor's window of ``W`` intervals the error in expected photoelectrons is
``(2/3) e min(W, h / T_r)`` (the error's mean over a segment is about 2/3 of its
peak), compared with the window's shot noise ``sqrt(W r)``::

    d = max over pixels of  (2/3) e min(W, h / T_r) / sqrt(W max(r, 1/W))

and a segment is halved while ``d > tolerance``. Base segments use the
curvature at both of their ends (their neighbours on the base grid); halves use
the curvature measured by their parent's midpoint (``fm - (fa + fb) / 2``, the
parent's actual interpolation error there). With a single base segment there
is no neighbour and the endpoint change ``|fb - fa| / 2`` bounds ``e``.

Times live on a dyadic grid: keyframe ``tick`` ``i`` is at
``t0 + duration * i / (n_base * 2^levels)``, so times are exact and
reproducible (which makes resuming exact).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class TimeGrid:
    """The dyadic time grid: ``n_base`` base intervals over ``[t0_s, t0_s + duration_s]``, ``levels`` halvings."""

    t0_s: float
    duration_s: float
    n_base: int
    levels: int

    @classmethod
    def make(cls, duration_s: float, base_rate_hz: float, max_rate_hz: float, t0_s: float = 0.0) -> "TimeGrid":
        n_base = max(1, int(math.ceil(duration_s * base_rate_hz - 1e-9)))
        levels = max(0, int(math.floor(math.log2(max(max_rate_hz / base_rate_hz, 1.0)) + 1e-9)))
        return cls(float(t0_s), float(duration_s), n_base, levels)

    @property
    def step(self) -> int:
        """Ticks per base interval."""
        return 2 ** self.levels

    @property
    def n_ticks(self) -> int:
        return self.n_base * self.step

    def time(self, tick: int) -> float:
        return self.t0_s + self.duration_s * tick / self.n_ticks

    def base_ticks(self) -> list[int]:
        return [i * self.step for i in range(self.n_base + 1)]


def frame_seeds(base_seed: int, t_s: float, n: int = 2) -> list[int]:
    """``n`` 32-bit render seeds for the frame at ``t_s`` [s], derived from the base seed and the time in ns."""
    ss = np.random.SeedSequence([int(base_seed), int(round(float(t_s) * 1e9)) & 0xFFFFFFFFFFFF])
    return [int(s) for s in ss.generate_state(n, dtype=np.uint32)]


def change_metric(a, b, var_a=None, var_b=None, z: float = 4.0) -> float:
    """d(A, B): largest per-pixel change beyond z MC sigmas, relative to the mean of the pair."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    mean = float(np.mean(0.5 * (a + b)))
    if not mean > 0:
        return 0.0
    diff = np.abs(a - b)
    if var_a is not None and var_b is not None:
        diff = np.maximum(0.0, diff - z * np.sqrt(np.asarray(var_a) + np.asarray(var_b)))
    return float(diff.max() / mean)


def interpolation_metric(var_floor, rate_scale: float, window_intervals: int, interval_s: float, z: float = 4.0):
    """The refinement criterion ``metric(f0, f1, f2, spacing_s)`` (module docstring) for frames in Phi units.

    ``var_floor``: per-pixel Monte Carlo variance of one keyframe [Phi units^2] (scalar or (H, W));
    ``rate_scale``: e-/interval per unit Phi; ``window_intervals``: the sensor window W;
    ``f2=None``: only two frames (f0, f1), the endpoint bound is used. ``scales``: each frame's variance over
    ``var_floor`` (a refined keyframe may have fewer samples: :func:`.noise.level_k_factors`).
    """
    W = float(window_intervals)
    sd = np.sqrt(np.asarray(var_floor, np.float64)) * float(rate_scale)

    def metric(f0, f1, f2, spacing_s: float, scales=(1.0, 1.0, 1.0)) -> float:
        a = np.asarray(f0, np.float64) * rate_scale
        b = np.asarray(f1, np.float64) * rate_scale
        s0, s1, s2 = (float(x) for x in scales)
        if f2 is None:
            e = np.maximum(0.0, np.abs(b - a) - z * np.sqrt(s0 + s1) * sd) / 2.0
            r = 0.5 * (a + b)
        else:
            c = np.asarray(f2, np.float64) * rate_scale
            e = np.maximum(0.0, np.abs(a - 2.0 * b + c) - z * np.sqrt(s0 + 4.0 * s1 + s2) * sd) / 4.0
            r = (a + b + c) / 3.0
        seg = min(W, float(spacing_s) / float(interval_s))
        err = (2.0 / 3.0) * e * seg
        return float(np.max(err / np.sqrt(W * np.maximum(r, 1.0 / W))))
    return metric


def tick_level(grid: TimeGrid, tick: int) -> int:
    """The refinement level of ``tick``: 0 on the base grid, ``l`` where it halves a level ``l - 1`` segment."""
    tick = int(tick)
    if tick % grid.step == 0:
        return 0
    return grid.levels - ((tick & -tick).bit_length() - 1)


def adaptive_ticks(grid: TimeGrid, get_frame, metric, tolerance: float, on_new=None, adaptive: bool = True,
                   var_scale=None):
    """Walk the grid, calling ``get_frame(tick)`` for every keyframe needed; return the sorted ticks.

    ``metric(f0, f1, f2, spacing_s)`` estimates the interpolation error next to three equally
    spaced frames (``f2=None``: two frames); segments with ``metric > tolerance`` are halved
    down to one tick. Base frames are rendered one ahead (a segment's decision needs the base
    frame after it). ``on_new(n)`` is told each time n more frames are scheduled (progress bars).
    ``var_scale(level)``: the Monte Carlo variance of a keyframe of that refinement level over a base one's,
    handed to the metric (``scales``) when a refined keyframe is among its frames.
    """
    def scales(*ticks):
        if var_scale is None:
            return (1.0, 1.0, 1.0)
        return tuple(float(var_scale(tick_level(grid, t))) for t in ticks) + (1.0,) * (3 - len(ticks))

    base = grid.base_ticks()
    nb = len(base)
    h = grid.time(grid.step) - grid.time(0)
    held = {}  # base frames still needed

    def frame(k):
        if base[k] not in held:
            held[base[k]] = get_frame(base[k])
        return held[base[k]]

    ticks = [base[0]]
    frame(0)
    for i in range(nb - 1):
        ta, tb = base[i], base[i + 1]
        fa, fb = frame(i), frame(i + 1)
        if adaptive and tb - ta >= 2:
            ds = []
            if i > 0:
                ds.append(metric(frame(i - 1), fa, fb, h))
            if i + 2 < nb:
                ds.append(metric(fa, fb, frame(i + 2), h))
            d = max(ds) if ds else metric(fa, fb, None, h)
            stack = [(ta, fa, tb, fb, d)]
            while stack:
                a, f_a, b, f_b, d = stack.pop()
                if d <= tolerance or b - a < 2:
                    continue
                m = (a + b) // 2
                if on_new:
                    on_new(1)
                f_m = get_frame(m)
                ticks.append(m)
                dc = metric(f_a, f_m, f_b, 0.5 * (grid.time(b) - grid.time(a)), scales(a, m, b))
                # the later half first on the stack, so the earlier half is refined first (time order)
                stack.append((m, f_m, b, f_b, dc))
                stack.append((a, f_a, m, f_m, dc))
        ticks.append(tb)
        if i > 0:
            held.pop(base[i - 1], None)
    return sorted(ticks)


def interpolate(times_s, frames, t_s):
    """Piecewise-linear interpolation of frames (K, ...) at ``t_s`` (the sensor stage's convention)."""
    times_s = np.asarray(times_s, np.float64)
    i = int(np.clip(np.searchsorted(times_s, t_s, side="right") - 1, 0, len(times_s) - 2))
    u = (t_s - times_s[i]) / (times_s[i + 1] - times_s[i])
    return (1 - u) * np.asarray(frames[i], np.float64) + u * np.asarray(frames[i + 1], np.float64)
