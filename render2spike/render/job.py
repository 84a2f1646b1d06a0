"""Render a scene to a frames folder: the noise budget, then each keyframe rendered, written and journalled.

:func:`render_scene` reads as the algorithm, in three parts:

* the frames folder (:class:`.folder.FramesFolder`): its lock, render state, journal and manifest, and what
  a rerun resumes;
* the launch (:mod:`.launch`): ``film`` or ``frozen``, chosen once (:func:`.launch.resolve_launch`), behind
  the renderer (:class:`.renderer.SceneRenderer`);
* the frame source (:class:`.source.FrameSource`): which keyframe ticks to render, refined adaptively.

Output (the frame contract of :mod:`sensor.io.frames`)
---------------------------------------------------
(Or, into a :class:`.memory.MemorySink`, the same keyframes held in memory, nothing written.)
``OUT/frame_TTTTTTTT.exr`` (float32 ``Phi`` [e-/(s m^2)] and ``E`` [lux], header
``time_s``, ``units``, ``spp``, ``render_noise_ratio``, ``render_noise_window_intervals``, ``variant``, ``launch``,
``scene_hash``, ``target_lux``, ``seeds``, ``made_by``, ``scene``; ``keyframe_block`` [block index, place in it]
for a base keyframe rendered in a block) and ``OUT/frames.json``, written
last, when every frame is done. ``TTTTTTTT`` is the frame's tick on the finest
time grid (``time_s = duration_s * tick / n_ticks``), zero-padded: file names
sort in time order.

Resume and reproducibility
--------------------------
Rerunning the same command keeps the finished frames, reuses the stored light-level measurement and spp, and
renders only the rest (:mod:`.folder`): a resumed folder holds exactly the frames an uninterrupted render
makes. The measurement itself is deterministic (see :meth:`.renderer.SceneRenderer.measure_reference`), so two
separate renders of one scene are identical too, to float round-off (the film launch's per-pixel sums are
atomic: at high spp a value may differ in its last bits run to run, rarely on the CPU, often on a GPU,
``benchmarks/repro_check.py``; the frozen launch sums each pixel's samples in a fixed order, see
:mod:`.frozen`). If the scene, a setting, the profile, the Mitsuba variant or the launch changed (a different
hash, :func:`.launch.settings_of`; ``launch="auto"`` takes the folder's own launch), the folder is refused, or
with ``overwrite=True`` emptied of our files and rendered anew: frames of two scenes are never mixed.
"""

from __future__ import annotations

import contextlib
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sensor.errors import InputError
from sensor.io.fileio import provenance

from . import backend
from .folder import FramesFolder
from .launch import DEFAULT_LAUNCH, check_launch, launch_record, launch_taken, refusal_hint, resolve_launch
from .noise import (VERIFY_EVERY, dark_current_mean_e, keyframes_per_window, level_k_factors, pilot_budget,
                    render_noise_ratio, tile_ratios, tile_summary, verify_ratios)
from .sampling import TimeGrid
from .scene import Scene
from .source import FrameSource


@dataclass
class RenderResult:
    """What :func:`render_scene` did: the folder (None for a :class:`.memory.MemorySink`), frame count, spp,
    timings and whether it was already done."""

    out: Path | None
    n_frames: int
    n_rendered: int
    spp: int
    scene_hash: str
    seconds: float
    up_to_date: bool
    manifest: dict


def render_scene(scene: Scene, out, *, overwrite: bool = False, progress: bool = True, variant: str | None = None,
                 log=print, launch: str = DEFAULT_LAUNCH) -> RenderResult:
    """Render ``scene`` into the frames folder ``out`` (resuming if possible). See the module docstring.

    ``launch``: how each render is launched (:data:`.launch.LAUNCHES`: ``auto``, the default, ``film``
    or ``frozen``; :func:`.launch.resolve_launch` says which ``auto`` takes); part of the folder's
    hash, so a folder is resumed only by the launch it was rendered with (``auto`` takes that one).
    The launch taken is in the manifest, the render state and every frame's header.

    ``out`` may also be a :class:`.memory.MemorySink`: the keyframes are then held in memory (float32, as a
    frame file holds them; nothing is written, nothing resumed) and, once the render is done, read like a
    folder from the sink's ``frames``.

    Raises :class:`sensor.errors.InputError` (before anything is written) for a folder of another scene
    (without ``overwrite``), a folder another render is writing into, or a scene with no usable light.
    """
    from .memory import MemorySink
    if isinstance(out, MemorySink):
        return _render_locked(scene, out, overwrite, progress, variant, log, launch)
    with FramesFolder.locked(out, log) as folder:
        return _render_locked(scene, folder, overwrite, progress, variant, log, launch)


def _render_locked(scene: Scene, folder: FramesFolder, overwrite: bool, progress: bool, variant, log,
                   asked: str) -> RenderResult:
    t_start = time.perf_counter()
    check_launch(asked)
    variant = backend.mitsuba(variant).variant()
    launch, scene_hash = _choose_launch(scene, folder, variant, asked, overwrite, log)
    done = folder.up_to_date(scene_hash)
    if done is not None:
        log(f"render: {folder.path} is up to date ({len(done['frames'])} frames, scene hash {scene_hash})")
        return RenderResult(folder.path, len(done["frames"]), 0, int(done.get("spp", 0)), scene_hash,
                            time.perf_counter() - t_start, True, done)
    folder.start({"scene_hash": scene_hash, "scene": str(scene.path), "variant": variant, "launch": launch,
                  **launch_record(launch)}, overwrite)

    from .renderer import SceneRenderer
    t_load = time.perf_counter()
    rnd = SceneRenderer(scene, variant, calibration=folder.state.get("calibration"), launch=launch)
    folder.state["calibration"] = rnd.calibration
    t_pilot = time.perf_counter()
    reuse = _Reuse(rnd, scene, launch)
    spp, budget, var_floor = _noise_budget(rnd, scene, folder, log, reuse)
    reuse.start(budget, var_floor, rnd, folder)
    t_frames = time.perf_counter()
    source = FrameSource(scene, var_floor, rnd.rate_scale(), progress, level_var=budget["level_var"])
    frames = _Keyframes(rnd, scene, folder, source, spp, launch, scene_hash, reuse)
    try:
        with folder.writing():
            ticks = source.walk(frames.at)  # each tick: the folder's frame, or rendered, written and journalled
            # the writer finishes the queued frames and closes (fsyncs) the journal, in its thread, while the
            # manifest is prepared here; both are done (the thread joined) before the manifest is written
            folder.stop_writing()
            source.close()
            listed = [{"file": folder.saved(t)["file"], "time_s": source.time(t)} for t in ticks]
            ratios = folder.keep_only(ticks)
            seconds = time.perf_counter() - t_start
            # [s]: the folder and launch checks; the scene loaded into Mitsuba (SceneRenderer.load_s); the rest of
            # the renderer's set-up, the light meter (none when resumed); the noise pilot; the keyframes
            # rendered, checked and written
            stages = {"start": t_load - t_start, "load": rnd.load_s, "meter": t_pilot - t_load - rnd.load_s,
                      "pilot": t_frames - t_pilot, "keyframes": t_start + seconds - t_frames}
            manifest = folder.prepare_finish(scene.profile.height, scene.profile.width, listed, _manifest(
                scene, rnd, folder, source, frames, ticks, ratios, budget, seconds, log, stages))
    finally:
        source.close()
    folder.finish()
    return RenderResult(folder.path, len(ticks), frames.n_rendered, spp, scene_hash, seconds, False, manifest)


def _choose_launch(scene: Scene, folder: FramesFolder, variant: str, asked: str, overwrite: bool,
                   log) -> tuple[str, str]:
    """The launch this render takes into ``folder`` and its scene hash; the folder's frames kept for it, or
    refused, or (``overwrite``) cleared (:meth:`.folder.FramesFolder.resume`)."""
    launch, scene_hash = launch_taken(scene, variant, asked, None if overwrite else folder.scene_hash,
                                      folder.launch)
    if asked == "auto" and folder.scene_hash == scene_hash and launch != resolve_launch(asked, variant, scene):
        log(f"render: {folder.path} holds frames of the {launch} launch: resuming with it (--launch auto)")
    folder.resume(scene_hash, overwrite, hint=lambda: refusal_hint(
        scene, variant, launch, asked, folder.scene_hash, folder.variant, folder.launch, folder.manifest or {},
        folder.state or {}))
    return launch, scene_hash


def _box(img, r: int):
    from scipy.ndimage import uniform_filter
    return uniform_filter(np.asarray(img, np.float64), size=2 * r + 1, mode="nearest")


def _noise_budget(rnd, scene: Scene, folder: FramesFolder, log, reuse: "_Reuse"):
    """The render's spp and noise budget (pilot pairs at t = 0, convergence fitted: :func:`.noise.pilot_budget`;
    a resumed folder's own), saved in the render state; -> ``(spp, budget, var_floor)``, ``var_floor`` the
    noise floor of the change metric: the smoothed pilot variance, scaled to the chosen spp. With static-region
    reuse (:mod:`.reuse`) the spp is the dynamic region's and ``budget["static"]`` the static frame's."""
    rcfg = scene.render
    ncfg = rcfg["noise"]
    W = int(ncfg["window_intervals"])
    K = keyframes_per_window(W, scene.profile.interval_s, float(rcfg["keyframe_rate_hz"]))
    # with a fixed spp, a pilot render at t = 0 and that spp is the first frame's second (verification)
    # render: no launch added. Not with spp = auto: the snapping chose the spp on those very pairs, and the
    # verification is there to check that choice on renders it did not see
    keep = rnd.keep_renders() if rcfg["spp"] != "auto" else contextlib.nullcontext()
    pairs = {}
    acfg = rcfg["adaptive"]
    levels = TimeGrid.make(scene.duration_s, float(rcfg["keyframe_rate_hz"]), float(acfg["max_rate_hz"])).levels \
        if acfg["enabled"] else 0
    factors = level_k_factors(W, scene.profile.interval_s, float(rcfg["keyframe_rate_hz"]), levels)
    with keep:
        budget, pilot_var_px = pilot_budget(rnd, scene, W, K, rnd.rate_scale(), snap=rcfg["spp"] == "auto",
                                            dark_e=dark_current_mean_e(scene.profile), mask=reuse.budget_mask(),
                                            keep=pairs, level_factors=factors,
                                            keep_raw=reuse.pilot_raw if reuse.on and rcfg["spp"] == "auto" else None)
    if reuse.on:
        budget["static"] = reuse.static_budget(pairs, rnd, scene)
    state = folder.state
    if "spp" in state and "noise_budget" in state:  # resuming: the frames already made fix the spp
        budget = state["noise_budget"]
        spp = int(state["spp"])
    else:
        spp = int(rcfg["spp"]) if rcfg["spp"] != "auto" else budget["spp"]  # taken exactly (launch_counts)
        if rcfg["spp"] != "auto":  # a given spp is every keyframe's
            budget["spp_levels"], budget["level_var"] = [spp] * (levels + 1), [1.0] * (levels + 1)
        state["spp"], state["noise_budget"] = spp, budget
    # a folder begun before refined keyframes had their own spp holds the base spp at every level
    budget.setdefault("spp_levels", [spp] * (levels + 1))
    budget.setdefault("level_var", [1.0] * (levels + 1))
    folder.save_state()
    st = budget.get("static") or {}
    if rcfg["spp"] == "auto" and st.get("clipped"):
        log(f"render: note: the static frame's budget asks for {st['spp_needed']} spp, more than {st['max_spp']} "
            f"(8 x max_spp); its pixels' render noise will be ~{st['predicted_ratio']:.2f} of the shot noise")
    if rcfg["spp"] == "auto" and budget["clipped"]:
        log(f"render: note: the noise budget asks for {budget['spp_needed']} spp, more than max_spp = "
            f"{ncfg['max_spp']}; render noise will be ~{budget['predicted_ratio']:.2f} of the shot noise over "
            f"{W} intervals (recorded per frame as render_noise_ratio)")
    v_px = pilot_var_px(spp)
    return spp, budget, np.maximum(_box(v_px, 2), float(np.median(v_px)))


class _Keyframes:
    """The keyframe at a tick: read back from the folder, or rendered, checked and handed to its writer."""

    def __init__(self, rnd, scene: Scene, folder: FramesFolder, source: FrameSource, spp: int, launch: str,
                 scene_hash: str, reuse: "_Reuse"):
        self.rnd, self.scene, self.folder, self.source = rnd, scene, folder, source
        self.reuse = reuse
        self.spp, self.launch, self.scene_hash = int(spp), launch, scene_hash
        self.spp_levels = [int(n) for n in folder.state["noise_budget"]["spp_levels"]]
        self.W = int(scene.render["noise"]["window_intervals"])
        self.K = keyframes_per_window(self.W, scene.profile.interval_s, float(scene.render["keyframe_rate_hz"]))
        self.made_by = json.dumps({"stage": "render", "tool": "render2spike", "scene": scene.name,
                                   "variant": rnd.variant, "launch": launch})
        self.n_rendered = 0
        self.tiles = []  # the verified keyframes' noise.tile_ratios (this run's)
        # base keyframes in blocks of block_k, one launch each (frozen.block_obstacle: only the camera moves)
        from .frozen import block_obstacle
        self.block_why_not = block_obstacle(scene, launch)
        self.block_k = 0
        if self.block_why_not is None:
            self.block_k = rnd.frame_launch.block_size(self.spp_levels[0])
            counts = rnd.launch_counts(self.spp_levels[0])
            if len(counts) != 1:
                self.block_why_not = (f"a frame at {self.spp_levels[0]} spp takes {len(counts)} launches "
                                      f"({' + '.join(str(c) for c in counts)} spp), a block's frames one each")
            elif self.block_k < 2:
                self.block_why_not = (f"two frames at {self.spp_levels[0]} spp would take more than one launch's "
                                      "samples")
            if self.block_why_not is not None:
                self.block_k = 0
        self._block = {}  # tick -> (raw channels, block seed, block index, place in it) of the block rendered last
        self.n_blocks = 0

    def at(self, tick: int):
        """Phi (float64) of the keyframe at ``tick``: the folder's, else :meth:`render`'s."""
        return self.folder.read_phi(tick) if self.folder.saved(tick) is not None else self.render(tick)

    def render(self, tick: int):
        """Render the frame at ``tick``, check it, queue it for writing (and journalling); -> its Phi."""
        rnd, scene, t_s = self.rnd, self.scene, self.source.time(tick)
        # the achieved ratio is measured on the first and every VERIFY_EVERY-th (128th) base keyframe of the time
        # grid (one extra render each): chosen by the tick, so a resumed render verifies the frames an
        # uninterrupted one does and writes the same files
        verify = tick % (VERIFY_EVERY * self.source.grid.step) == 0
        seed = int(scene.render["seed"])
        spp = self.spp_levels[self.source.level(tick)]  # a refined keyframe's own (noise.level_k_factors)
        if self.block_k and self.source.level(tick) == 0:
            f = self._block_frame(tick, t_s, seed, spp, verify)
        elif self.reuse.on:
            f = self.reuse.frame(t_s, seed, spp, verify)
            if tick == self.source.grid.n_ticks or (verify and tick > 0):
                self.reuse.check(t_s, seed, spp, f)
        else:
            f = rnd.render_frame(t_s, seed, spp, variance=verify)
        if f["phi_var"] is None:
            ratio = float("nan")  # what render_noise_ratio gives without a variance
        else:
            rs = rnd.rate_scale()
            k = np.where(f["dynamic"], self.K, 1.0) if self.reuse.on else self.K
            ratio = render_noise_ratio(f["phi"] * rs, f["phi_var"] * rs ** 2, self.W, k,
                                       dark_current_mean_e(scene.profile))
            self.tiles.append(tile_ratios(f["phi"] * rs, f["phi_var"] * rs ** 2, self.W, k,
                                          dark_current_mean_e(scene.profile)))
        if not (np.isfinite(f["phi"]).all() and np.isfinite(f["lux"]).all()):
            bad = ~np.isfinite(f["phi"]) | ~np.isfinite(f["lux"])
            r, c = (int(x) for x in np.argwhere(bad)[0])
            raise InputError(f"the frame at t = {t_s:.6g} s has {int(bad.sum())} non-finite pixel(s), first at row "
                             f"{r}, column {c}: check the scene's light and material values", path=scene.path)
        attrs = {"spp": spp, "render_noise_ratio": float(ratio), "render_noise_window_intervals": self.W,
                 "variant": rnd.variant, "launch": self.launch, "scene_hash": self.scene_hash,
                 "target_lux": float(scene.illuminance_lux),
                 "seeds": f["seeds"], "made_by": self.made_by, "scene": scene.name}
        if "block" in f:  # [block index, place in it]: the frame's samples are that run of the block's launch
            attrs["keyframe_block"] = f["block"]
        # the float64 arrays are handed over as they are (nothing here changes them later): the writer thread
        # rounds them to the file's float32, off the render loop
        self.folder.write(tick, t_s, f["phi"], f["lux"], ratio, attrs)
        self.n_rendered += 1
        return f["phi"]

    def _block_frame(self, tick: int, t_s: float, seed: int, spp: int, verify: bool) -> dict:
        """The base keyframe at ``tick`` from its block: base ticks ``b K step ... ((b + 1) K - 1) step`` (``K`` =
        ``block_k``, ``step`` the base spacing in ticks) rendered in one launch, seeded by the render seed and
        ``b``, so a resumed render makes the same block and takes the frames it lacks. The dict of
        :meth:`.renderer.SceneRenderer.render_frame`; a verified keyframe's second render is the one
        ``render_frame`` takes: a kept pilot render at its time and spp, else a launch of its own with the seeds
        ``render_frame`` gives it."""
        from .photometry import apply_factors
        from .sampling import frame_seeds
        rnd, grid = self.rnd, self.source.grid
        if tick not in self._block:
            b = tick // (grid.step * self.block_k)
            ticks = [t for t in range(b * self.block_k * grid.step, (b + 1) * self.block_k * grid.step, grid.step)
                     if t <= grid.n_ticks]
            # a child of the render seed by its spawn key: numpy pads the seed's words apart from the key's, so no
            # keyframe's SeedSequence([seed, t_ns]) (.sampling.frame_seeds) can equal it, whatever t_ns is
            bseed = int(np.random.SeedSequence(int(seed), spawn_key=(0xB10C, int(b))).generate_state(1, np.uint32)[0])
            raws = rnd.render_block([self.source.time(t) for t in ticks], bseed, spp)
            # the frames this render still needs (a resumed one has some already): the others are let go now
            self._block = {t: (raw, bseed, b, i) for i, (t, raw) in enumerate(zip(ticks, raws))
                           if t == tick or self.folder.saved(t) is None}
            self.n_blocks += 1
        (raw_p, raw_e), bseed, b, place = self._block.pop(tick)
        phi, lux = apply_factors(raw_p, raw_e, rnd._factors)
        out = {"time_s": float(t_s), "phi": phi, "lux": lux, "seeds": [bseed], "spp": int(spp), "phi_var": None,
               "block": [int(b), int(place)]}
        if verify:
            reused = rnd._reused_render(t_s, spp, [bseed])  # a kept pilot render, as render_frame takes it
            if reused is not None:
                sb, pb = [reused[0]], reused[1]
            else:
                n = len(rnd.launch_counts(spp))
                sb = frame_seeds(seed, t_s, 2 * n)[n:]
                pb, _ = rnd.render_exact(t_s, sb, spp)
            out["phi_var"] = (raw_p - pb) ** 2 / 2.0 * rnd._factors[0] ** 2
            out["variance_seeds"] = list(sb)
        return out

    def block_record(self) -> dict:
        """The manifest's ``keyframe_blocks``."""
        if not self.block_k:
            return {"applied": False, "why_not": self.block_why_not}
        return {"applied": True, "keyframes_per_block": self.block_k, "n_blocks_this_run": self.n_blocks}


def _manifest(scene: Scene, rnd, folder: FramesFolder, source: FrameSource, frames: _Keyframes, ticks, ratios,
              budget, seconds: float, log, stages: dict) -> dict:
    """The finished render's manifest (besides the frames list); warns when the measured render noise misses
    its target."""
    rcfg = scene.render
    ncfg = rcfg["noise"]
    verified, warn = verify_ratios(ratios, float(ncfg["target_ratio"]), rcfg["spp"] == "auto", budget)
    if warn:
        log(f"render: warning: {warn}")
    prof = scene.profile
    finite = np.any(np.isfinite(ratios))
    extra = {
        "complete": True,
        "scene_hash": frames.scene_hash,
        "scene": {"name": scene.name, "path": str(scene.path), "description": scene.data.get("description", "")},
        "scene_data": scene.data,
        "illuminance_lux": scene.illuminance_lux,
        "reference": rnd.calibration,
        "emitter_scale_w_per_raw": rnd.k,
        "camera": {"focal_length_mm": scene.camera["focal_length_mm"], "f_number": rnd.f_number,
                   "transmission": rnd.transmission, "pixel_pitch_m": prof.pixel_pitch_m,
                   "fill_factor": prof.fill_factor},
        "profile": {"name": prof.name, "spec": scene.camera["profile"], "height": prof.height, "width": prof.width},
        "variant": rnd.variant,
        "launch": frames.launch,
        **launch_record(frames.launch),
        "spp": frames.spp,
        "spp_by_level": frames.spp_levels,
        "noise_budget": budget,
        "render_noise_ratio": {"mean": float(np.nanmean(ratios)) if finite else None,
                               "max": float(np.nanmax(ratios)) if finite else None,
                               "window_intervals": frames.W, "keyframes_per_window": frames.K, **verified,
                               "tiles": tile_summary(frames.tiles, float(ncfg["target_ratio"]))},
        "temporal_sampling": source.record(ticks),
        "static_reuse": frames.reuse.record(log),
        "keyframe_blocks": frames.block_record(),
        "n_rendered_this_run": frames.n_rendered,
        "n_resumed": folder.n_resumed,
        "render_seconds": seconds,
        "render_stage_seconds": stages,
        "provenance": provenance(stage="render"),
    }
    return json.loads(json.dumps(extra, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))


class _Reuse:
    """Static-region reuse (:mod:`.reuse`) for one render: on when :func:`.reuse.reuse_obstacle` finds nothing
    against it. Holds the coverage test, the static frame, and the static checks made."""

    def __init__(self, rnd, scene: Scene, launch: str):
        from .reuse import Coverage, reuse_obstacle
        self.why_not = reuse_obstacle(scene, launch)
        self.on = self.why_not is None
        self.cov = Coverage(rnd) if self.on else None
        self.dynamic_t0 = self.cov(0.0) if self.on else None
        if self.on and self.dynamic_t0.all():  # no pixel would ever take a static value (reuse.StaticFrame)
            self.on, self.why_not, self.cov, self.dynamic_t0 = False, "moving objects cover every pixel at t = 0", \
                None, None
        self.static = None
        self.checks = []
        self.dyn_fractions = []
        self.pilot_raw = {}  # the noise pilot's pair at its highest count, as rendered (pilot_budget's keep_raw)

    def budget_mask(self):
        """The pixels the dynamic region's budget is measured on: those dynamic at t = 0, or every pixel when
        fewer than :data:`.reuse.MIN_BUDGET_PIXELS` are (a moving object that enters the view later, or covers a
        handful of pixels: the whole frame stands in for it)."""
        from .reuse import MIN_BUDGET_PIXELS
        if not self.on or self.dynamic_t0.sum() < MIN_BUDGET_PIXELS:
            return None
        return self.dynamic_t0

    def static_budget(self, pairs: dict, rnd, scene: Scene) -> dict:
        """The static frame's spp from the pilot pairs (:func:`.reuse.static_spp`); a given spp (``--spp``) is
        the static frame's too (each of its two renders)."""
        from .reuse import static_spp
        ncfg = scene.render["noise"]
        rs = rnd.rate_scale()
        top = pairs[max(pairs)]
        rate = 0.5 * (top[0] + top[1]) * rs + dark_current_mean_e(scene.profile)
        out = static_spp(pairs, ~self.dynamic_t0, rate, rs, int(ncfg["window_intervals"]),
                         float(ncfg["target_ratio"]), int(ncfg["max_spp"]), rnd.effective_spp)
        if scene.render["spp"] != "auto":
            out.update(spp=int(scene.render["spp"]), given=True)
        return out

    def _pilot_frame(self, rnd, spp: int, seeds):
        """The static frame made of the noise pilot's pair at ``spp`` (rendered again with its ``seeds`` when the
        pilot did not keep it: the same two renders)."""
        from .reuse import StaticFrame
        got = self.pilot_raw.get(int(spp))
        if got is not None and got[0] == [int(s) for s in seeds]:
            renders = (got[1], got[2])
        else:
            renders = tuple(rnd.render_raw(0.0, int(s), int(spp)) for s in seeds)
        return StaticFrame(rnd, spp, seeds, ~self.dynamic_t0, renders=renders)

    def start(self, budget: dict, var_floor, rnd, folder) -> None:
        """Make the static frame. With ``spp: auto`` it is first the noise pilot's pair at its highest count (two
        independent renders at t = 0, made already), kept when its measured ratio (:func:`.reuse.static_ratio`)
        is not above ``STATIC_ACCEPT`` x the target, or not defined (no light and no dark current in the static
        pixels): no render and no kernel of its own. Else it is rendered (seeds
        from the render seed and the attempt, so a resumed render makes the same one) and its own pair measures its
        pixels' ratio; outside ``[BAND[0], STATIC_ACCEPT]`` x the target it is rendered again at more or fewer
        samples (:func:`.reuse.static_retry_spp`), at most :data:`.reuse.STATIC_ATTEMPTS` renders in all, and the
        one in the band (else nearest the target without being above it) is kept. What was kept (count, attempt or
        the pilot's pair and seeds) is saved in the render state: a resumed render makes that frame directly."""
        if not self.on:
            return
        from .noise import BAND
        from .reuse import STATIC_ACCEPT, STATIC_ATTEMPTS, StaticFrame, static_ratio, static_retry_spp
        scene = rnd.scene
        ncfg = scene.render["noise"]
        st = budget["static"]
        kept = folder.state.get("static_frame")
        if kept is None and folder.n_resumed:  # a render state without the kept frame: its frames were made with
            kept = {"spp": int(st["spp"]), "attempt": 0}  # the budget's count, first attempt
        target = float(ncfg["target_ratio"])
        lo, hi = BAND[0] * target, STATIC_ACCEPT * target
        W, dark = int(ncfg["window_intervals"]), dark_current_mean_e(scene.profile)
        self.measured, made = [], {}
        auto = scene.render["spp"] == "auto"
        if (kept and kept.get("source") == "pilot") or (not kept and auto and self.pilot_raw):
            n_p = int(kept["spp"]) if kept else max(self.pilot_raw)
            frame = self._pilot_frame(rnd, n_p, kept["seeds"] if kept else self.pilot_raw[n_p][0])
            ratio = static_ratio(frame, rnd, W, dark)
            self.measured.append({"spp": n_p, "attempt": None, "source": "pilot", "ratio": ratio})
            # below the band too: it costs nothing; nan (no light and no dark current in the static pixels, or none
            # of them): no count can miss a band there
            if kept or not (np.isfinite(ratio) and ratio > hi):
                self._keep(frame, {"spp": n_p, "attempt": None, "source": "pilot", "seeds": frame.seeds}, rnd,
                           folder, var_floor)
                return
        spp, attempt = (int(kept["spp"]), int(kept["attempt"])) if kept else (int(st["spp"]), 0)
        if self.measured and spp <= self.measured[0]["spp"]:  # the pilot's pair, at more samples, missed above
            spp = static_retry_spp([(m["spp"], m["ratio"]) for m in self.measured], target, int(st["max_spp"]),
                                   rnd.effective_spp) or spp
        while True:
            n = len(rnd.launch_counts(spp))
            # a child of the render seed by its spawn key, as a block's (_Keyframes._block_frame)
            seeds = np.random.SeedSequence(int(scene.render["seed"]), spawn_key=(0x57A71C, attempt)).generate_state(
                2 * n, np.uint32)
            made[attempt] = StaticFrame(rnd, spp, seeds, ~self.dynamic_t0)
            ratio = static_ratio(made[attempt], rnd, W, dark)
            self.measured.append({"spp": int(spp), "attempt": attempt, "source": "render", "ratio": ratio})
            if kept or scene.render["spp"] != "auto" or not np.isfinite(ratio) or lo <= ratio <= hi \
                    or attempt + 1 >= STATIC_ATTEMPTS:
                break
            nxt = static_retry_spp([(m["spp"], m["ratio"]) for m in self.measured], target, int(st["max_spp"]),
                                   rnd.effective_spp)
            if nxt is None:
                break
            spp, attempt = nxt, attempt + 1
        if not kept:  # the attempt kept: in the band, else the one nearest the target that is not above it
            rendered = [m for m in self.measured if m["source"] == "render"]
            ok = [m for m in rendered if np.isfinite(m["ratio"]) and m["ratio"] <= hi]
            best = min(ok, key=lambda m: abs(m["ratio"] - target)) if ok else rendered[-1]
            spp, attempt = best["spp"], best["attempt"]
        self._keep(made[attempt], {"spp": int(spp), "attempt": int(attempt), "source": "render"}, rnd, folder,
                   var_floor)

    def _keep(self, frame, state: dict, rnd, folder, var_floor) -> None:
        self.pilot_raw = {}  # (the pilot's renders are not needed after this)
        self.static = frame
        folder.state["static_frame"] = state
        folder.save_state()
        self.rnd = rnd
        self._floor_raw = var_floor / rnd._factors[0] ** 2  # one keyframe's variance [raw Phi units^2], smoothed

    def frame(self, t_s: float, seed: int, spp: int, variance: bool) -> dict:
        from .reuse import render_frame_reused
        f = render_frame_reused(self.rnd, self.static, self.cov, t_s, seed, spp, variance)
        self.dyn_fractions.append(float(f["dynamic"].mean()))
        return f

    def check(self, t_s: float, seed: int, spp: int, f: dict) -> None:
        """Render the whole frame at ``t_s`` and compare its static pixels with the static frame."""
        from .reuse import static_check
        self.checks.append(static_check(self.rnd, self.static, f["dynamic"], t_s, seed, spp, self._floor_raw))

    def record(self, log) -> dict:
        """The manifest's ``static_reuse``; warns when a static check finds the static region changed."""
        if not self.on:
            return {"applied": False, "why_not": self.why_not}
        from .reuse import check_warning
        warn = check_warning(self.checks)
        if warn:
            log(f"render: warning: {warn}")
        st = self.static
        return {"applied": True, "static_spp": st.spp, "static_seeds": st.seeds,
                "static_source": (self.measured[-1]["source"] if self.measured else "render"),
                "static_measured": self.measured,
                "static_pixels": int(st.valid.sum()),
                "dynamic_fraction": {"t0": float(self.dynamic_t0.mean()),
                                     "mean": float(np.mean(self.dyn_fractions)) if self.dyn_fractions else None,
                                     "max": float(np.max(self.dyn_fractions)) if self.dyn_fractions else None},
                "static_check": self.checks}


def spp_text(manifest: dict, spp: int) -> str:
    """The frames' samples per pixel as the summary says them: by refinement level, the static frame's, and how many
    keyframes share a launch."""
    levels = manifest.get("spp_by_level") or [spp]
    text = f"{spp} spp" if len(set(levels)) == 1 else f"{' / '.join(map(str, levels))} spp by refinement level"
    sr = manifest.get("static_reuse") or {}
    if sr.get("applied"):
        frac = (sr.get("dynamic_fraction") or {}).get("mean")  # None when this run rendered no keyframe
        where = "the pixels" if frac is None else f"the {100 * frac:.0f} % of pixels"
        text += f" on {where} something moving covers, the rest from one static frame at {sr['static_spp']} spp"
        if sr.get("static_source") == "pilot":
            text += " (the noise pilot's pair)"
    kb = manifest.get("keyframe_blocks") or {}
    if kb.get("applied"):
        text += f", base keyframes up to {kb['keyframes_per_block']} to a launch"
    return text
