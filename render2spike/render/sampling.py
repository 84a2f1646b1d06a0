"""Adaptive temporal sampling: keyframes at a base rate, refined where irradiance changes fast.

Like ESIM's adaptive sampling, keyframes are placed so that the irradiance
changes by less than a tolerance between neighbours: starting from a uniform
grid at ``base_rate_hz``, the interval between two neighbouring keyframes is
halved (its midpoint rendered) while their difference exceeds ``tolerance``
and the spacing is above ``1 / max_rate_hz``.

Change metric between frames A and B (Phi in any units)::

    d(A, B) = max_px  max(0, |A - B| - z * sqrt(var_A + var_B))  /  mean((A + B) / 2)

i.e. the largest per-pixel change beyond ``z`` Monte Carlo standard
deviations, relative to the mean irradiance of the pair. A static scene only
differs by render noise and is never refined.

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


def adaptive_ticks(grid: TimeGrid, get_frame, metric, tolerance: float, on_new=None, adaptive: bool = True):
    """Walk the grid, calling ``get_frame(tick)`` for every keyframe needed; return the sorted ticks.

    ``metric(frame_a, frame_b)`` returns the change between two frames;
    intervals with ``metric > tolerance`` are halved down to one tick.
    ``on_new(n)`` is told each time n more frames are scheduled (progress bars).
    """
    ticks = []
    base = grid.base_ticks()
    prev_tick, prev = base[0], get_frame(base[0])
    ticks.append(prev_tick)
    for nxt_tick in base[1:]:
        nxt = get_frame(nxt_tick)
        stack = [(prev_tick, prev, nxt_tick, nxt)]
        while stack:
            ta, fa, tb, fb = stack.pop()
            if not adaptive or tb - ta < 2 or metric(fa, fb) <= tolerance:
                continue
            tm = (ta + tb) // 2
            if on_new:
                on_new(1)
            fm = get_frame(tm)
            ticks.append(tm)
            # push the later half first so the earlier half is refined first (frames in time order)
            stack.append((tm, fm, tb, fb))
            stack.append((ta, fa, tm, fm))
        ticks.append(nxt_tick)
        prev_tick, prev = nxt_tick, nxt
    return sorted(ticks)


def interpolate(times_s, frames, t_s):
    """Piecewise-linear interpolation of frames (K, ...) at ``t_s`` (the sensor stage's convention)."""
    times_s = np.asarray(times_s, np.float64)
    i = int(np.clip(np.searchsorted(times_s, t_s, side="right") - 1, 0, len(times_s) - 2))
    u = (t_s - times_s[i]) / (times_s[i + 1] - times_s[i])
    return (1 - u) * np.asarray(frames[i], np.float64) + u * np.asarray(frames[i + 1], np.float64)
