"""Frames kept in memory: the sink :func:`.job.render_scene` renders into when no frames are to be written.

:class:`MemorySink` has the part of :class:`.folder.FramesFolder`'s interface the render job uses (state,
``saved`` / ``read_phi`` / ``write`` / ``keep_only``, the manifest made at the end) and holds each keyframe's
Phi as the float32 array a frames folder would store (EXR holds float32: the values are rounded exactly as
:func:`sensor.io.frames.write_frame` rounds them), nothing written to disk. When the render is done,
:attr:`MemorySink.frames` is a :class:`sensor.io.frames.MemoryFrameSequence` that the sensor stage reads like
a frames folder (:func:`sensor.io.stream.open_stream`): the same frames and seed give the same spikes bit for
bit as through the folder.

Memory: 4 H W bytes per keyframe for Phi (400 kB at 400 x 250, so a clip of 500 keyframes holds 200 MB), as
much again for the ``E`` channel [lux] with ``keep_lux``. The whole clip is held until the caller drops the
sink: the adaptive refinement may insert a keyframe between any two already made, so the keyframes are final,
and the simulator can start, only when the render is done. Nothing is resumable: a render that fails leaves
nothing behind, and a rerun renders every keyframe again.
"""

from __future__ import annotations

import contextlib
import json

import numpy as np

from sensor.io.fileio import json_bytes
from sensor.io.frames import MemoryFrameSequence, manifest_record

from .folder import FORMAT_VERSION, tick_filename


class MemorySink:
    """Keyframes rendered into memory (see the module docstring); :attr:`frames` once the render finished."""

    path = None  # no folder
    manifest = None  # no earlier render: nothing to resume
    scene_hash = launch = variant = None

    def __init__(self, keep_lux: bool = False, where: str = "frames in memory"):
        self.keep_lux = bool(keep_lux)
        self.where = where
        self.state = None
        self.n_resumed = 0
        self.wrote_any = False
        self.frames: MemoryFrameSequence | None = None
        self._phi: dict[int, np.ndarray] = {}
        self._lux: dict[int, np.ndarray] = {}
        self._final = None

    # ------------------------------------------------------------------ the folder's decisions: nothing held
    def resume(self, scene_hash: str, overwrite: bool, hint=lambda: "") -> None:
        """Nothing to keep or clear."""

    def up_to_date(self, scene_hash: str) -> None:
        return None

    def start(self, header: dict, overwrite: bool) -> None:
        """Begin the render state (in memory only)."""
        self.state = {"format_version": FORMAT_VERSION, **header, "frames": {}, "complete": False}

    def save_state(self) -> None:
        """Nothing to write."""

    # ------------------------------------------------------------------ frames
    def saved(self, tick: int) -> dict | None:
        """The record of the keyframe at ``tick`` made in this render, or None."""
        return self.state["frames"].get(str(tick))

    def read_phi(self, tick: int):
        """Phi of the keyframe at ``tick``, as float64 (the float32 values a folder would read back)."""
        return self._phi[int(tick)].astype(np.float64)

    @contextlib.contextmanager
    def writing(self):
        yield self

    def write(self, tick: int, time_s: float, phi, lux, ratio: float, attrs: dict) -> None:
        """Hold the keyframe at ``tick``: Phi (and with ``keep_lux`` E) rounded to float32 as a frame file holds
        them."""
        self._phi[int(tick)] = np.ascontiguousarray(phi, dtype=np.float32)
        if self.keep_lux:
            self._lux[int(tick)] = np.ascontiguousarray(lux, dtype=np.float32)
        self.state["frames"][str(tick)] = {"file": tick_filename(tick), "time_s": time_s,
                                           "render_noise_ratio": float(ratio)}
        self.wrote_any = True

    def stop_writing(self) -> None:
        """Nothing queued."""

    def keep_only(self, ticks) -> list[float]:
        """Drop the keyframes not at ``ticks``; -> each kept keyframe's ``render_noise_ratio``, in ``ticks``'
        order."""
        keep = {str(t) for t in ticks}
        frames = self.state["frames"]
        for k in [k for k in frames if k not in keep]:
            del frames[k]
            self._phi.pop(int(k), None)
            self._lux.pop(int(k), None)
        return [frames[str(t)].get("render_noise_ratio", float("nan")) for t in ticks]

    # ------------------------------------------------------------------ finish
    def prepare_finish(self, height: int, width: int, frames: list[dict], manifest: dict) -> dict:
        """The manifest a frames folder would get (its ``frames`` name the files a folder would hold)."""
        self._final = json.loads(json_bytes(manifest_record(height, width, frames, **manifest)))
        return self._final

    def finish(self) -> None:
        """Make :attr:`frames`, in the manifest's (time) order; the sink's own references are dropped."""
        m = self._final
        by_file = {rec["file"]: int(t) for t, rec in self.state["frames"].items()}
        ticks = [by_file[f["file"]] for f in m["frames"]]
        lux = [self._lux[t] for t in ticks] if self.keep_lux else None
        self.frames = MemoryFrameSequence([self._phi[t] for t in ticks], m, lux=lux, where=self.where)
        self._phi, self._lux = {}, {}
        self.state["complete"] = True
