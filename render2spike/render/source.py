"""The frames a render makes: keyframe ticks on the time grid, refined adaptively, with a progress bar.

:class:`FrameSource` holds the scene's dyadic time grid (:class:`.sampling.TimeGrid`: base keyframes at
``render.keyframe_rate_hz``, halvings down to ``render.adaptive.max_rate_hz``) and the refinement criterion
(:func:`.sampling.interpolation_metric`, with the noise floor of the render's spp), and walks them
(:func:`.sampling.adaptive_ticks`): it asks for the frame at each tick it needs, in the order the refinement
needs them, and returns the ticks of the finished clip.
"""

from __future__ import annotations

from .sampling import TimeGrid, adaptive_ticks, interpolation_metric, tick_level


class FrameSource:
    """The keyframe ticks of a render of ``scene``, and its progress bar (``progress``).

    ``var_floor``: the per-pixel Monte Carlo variance of one keyframe at the render's spp [Phi units^2],
    below which a change between keyframes is render noise; ``rate_scale``: e-/interval per unit Phi;
    ``level_var``: each refinement level's keyframe variance over a base keyframe's (None: all equal).
    """

    def __init__(self, scene, var_floor, rate_scale: float, progress: bool = True, level_var=None):
        rcfg = scene.render
        acfg = rcfg["adaptive"]
        self.base_rate_hz = float(rcfg["keyframe_rate_hz"])
        self.max_rate_hz = float(acfg["max_rate_hz"])
        self.tolerance = float(acfg["tolerance"])
        self.adaptive = bool(acfg["enabled"])
        self.grid = TimeGrid.make(scene.duration_s, self.base_rate_hz, self.max_rate_hz)
        self.metric = interpolation_metric(var_floor, rate_scale, int(rcfg["noise"]["window_intervals"]),
                                           scene.profile.interval_s, z=4.0)
        self.level_var = list(level_var) if level_var else None  # each refinement level's variance / the base's
        self._bar = _progress_bar(scene, progress)
        self._dur_ms = scene.duration_s * 1e3
        self._seen = {"tick": 0, "frames": 0, "refined": 0}

    def time(self, tick: int) -> float:
        """The time of ``tick`` [s]."""
        return self.grid.time(tick)

    def walk(self, frame_at) -> list[int]:
        """Call ``frame_at(tick)`` (-> the frame's Phi) for every keyframe needed; -> the sorted ticks."""
        def counted(tick: int):
            phi = frame_at(tick)
            self._advance(tick)
            return phi

        def refined(n: int) -> None:
            self._seen["refined"] += n

        lv = self.level_var
        return adaptive_ticks(self.grid, counted, self.metric, self.tolerance, on_new=refined,
                              adaptive=self.adaptive, var_scale=(lambda level: lv[level]) if lv else None)

    def level(self, tick: int) -> int:
        """The refinement level of ``tick`` (0: a base keyframe)."""
        return tick_level(self.grid, tick)

    def _advance(self, tick: int) -> None:
        # progress in camera time [ms]: the furthest keyframe time asked for so far (base keyframes are rendered
        # one ahead, refinements fall before it), so the bar only moves forward and its total never changes;
        # the frame counts (base and refined) are shown beside it
        seen = self._seen
        seen["frames"] += 1
        bar = self._bar
        if bar is None:
            return
        seen["tick"] = max(seen["tick"], tick)
        target = round(self._dur_ms * seen["tick"] / self.grid.n_ticks, 3)
        # the counts are set without a redraw: the bar redraws them at its own pace (tqdm's mininterval) as it
        # moves, and at close; a redraw per frame would cost 25 us (to a file) to ~0.1 ms (a terminal), 1-3 %
        # of a small frame
        bar.set_postfix_str(f"{seen['frames']} frames, {seen['refined']} refined", refresh=False)
        if target > bar.n:
            bar.update(target - bar.n)

    def close(self) -> None:
        """Close the progress bar (idempotent)."""
        if self._bar:
            self._bar.close()

    def record(self, ticks: list[int]) -> dict:
        """The manifest's ``temporal_sampling`` of a clip of keyframes ``ticks``."""
        g = self.grid
        return {"base_rate_hz": self.base_rate_hz, "max_rate_hz": self.max_rate_hz, "tolerance": self.tolerance,
                "adaptive": self.adaptive, "n_base": g.n_base + 1, "n_keyframes": len(ticks),
                "n_refined": len(ticks) - g.n_base - 1}


def _progress_bar(scene, progress: bool):
    try:
        from tqdm.auto import tqdm
    except ImportError:  # pragma: no cover
        return None
    return tqdm(total=round(scene.duration_s * 1e3, 3), unit="ms", desc=f"render {scene.name}",
                disable=not progress, dynamic_ncols=True,
                bar_format="{l_bar}{bar}| {n:.1f}/{total:.1f} ms camera time [{elapsed}<{remaining}{postfix}]")
