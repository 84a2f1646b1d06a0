"""Render a scene to a frames folder: noise budget, adaptive keyframes, resume, lock, progress.

Output (the frame contract of :mod:`sensor.io.frames`)
---------------------------------------------------
``OUT/frame_TTTTTTTT.exr`` (float32 ``Phi`` [e-/(s m^2)] and ``E`` [lux], header
``time_s``, ``units``, ``spp``, ``render_noise_ratio``, ``variant``, ``launch``,
``scene_hash``, ``target_lux``, ``made_by``) and ``OUT/frames.json``, written
last, when every frame is done. ``TTTTTTTT`` is the frame's tick on the finest
time grid (``time_s = duration_s * tick / n_ticks``), zero-padded: file names
sort in time order.

Resume and reproducibility
--------------------------
``OUT/render_state.json`` records the scene hash, the light-level measurement
(``calibration``: the irradiance meter's reading behind ``illuminance_lux``) and
the samples per pixel, written once when the render starts; each finished frame
appends one line to ``OUT/render_journal.jsonl`` (so a long render does not
rewrite a growing file per frame; fsync'd about once a second and at the end,
see :class:`Journal`). Frames and their journal lines are written
by a background thread while the next frame renders (:mod:`.writer`): a line is
appended only once its frame file is in place, and the writer's errors are
raised here. Rerunning the same command keeps the
finished frames, reuses the stored measurement and spp, and renders only the
rest: a resumed folder holds exactly the frames an uninterrupted render makes.
The measurement itself is deterministic (see
:meth:`.renderer.SceneRenderer.measure_reference`), so two separate renders of
one scene are identical too, to float round-off (at high spp, e.g. 121, Mitsuba's
LLVM backend was seen to differ in the last bit of 1 of 6,144 pixels in 2 of 10 frames,
run to run; at 16 spp no difference was seen; on an H100, 1.4-64 % of the values differed by up to
2-16 float32 ulps at 64-1024 spp, ``benchmarks/repro_check.py``; the frozen launch sums each pixel's samples
in a fixed order, see :mod:`.frozen`). If the scene, a setting, the profile,
the Mitsuba variant or the launch changed (a different hash; ``launch="auto"`` takes the folder's own
launch, :func:`launch_taken`), the folder is refused, or with
``overwrite=True`` emptied of our files and rendered anew: frames of two scenes
are never mixed.

Lock
----
While rendering, ``OUT/.render2spike.lock`` names the writer (pid, host, start
time); a second render into the same folder is refused with that name, and a
lock left by a dead process is taken over (:mod:`sensor.io.lock`). Unfinished temp
files of killed writers are swept on start.
"""

from __future__ import annotations

import contextlib
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sensor.errors import InputError
from sensor.io.fileio import json_bytes, provenance, write_bytes_atomic, write_json_atomic
from sensor.io.frames import MANIFEST_NAME, manifest_record, read_frame
from sensor.io.lock import FolderLock, sweep_parts

from . import backend
from . import frozen as _frozen
from .builder import carries_normals, moving_meshes
from .frozen import DEFAULT_LAUNCH, check_launch, frozen_obstacle, resolve_launch
from .noise import VERIFY_EVERY, keyframes_per_window, pilot_budget, render_noise_ratio, verify_ratios
from .sampling import TimeGrid, adaptive_ticks, interpolation_metric
from .scene import Scene
from .writer import FrameWriter

STATE_NAME = "render_state.json"
JOURNAL_NAME = "render_journal.jsonl"


def tick_filename(tick: int) -> str:
    """File name of the frame at grid tick ``tick`` (zero-padded: names sort in time order)."""
    return f"frame_{int(tick):08d}.exr"


@dataclass
class RenderResult:
    """What :func:`render_scene` did: the folder, frame count, spp, timings and whether it was already done."""

    out: Path
    n_frames: int
    n_rendered: int
    spp: int
    scene_hash: str
    seconds: float
    up_to_date: bool
    manifest: dict


def _box(img, r: int):
    from scipy.ndimage import uniform_filter
    return uniform_filter(np.asarray(img, np.float64), size=2 * r + 1, mode="nearest")


def _clean(out: Path, state: dict | None, manifest: dict | None) -> None:
    names = set()
    for rec in (state or {}).get("frames", {}).values():
        names.add(rec["file"])
    for rec in (manifest or {}).get("frames", []):
        if isinstance(rec, dict) and isinstance(rec.get("file"), str):
            names.add(rec["file"])
    for nm in names:
        if "/" not in nm and "\\" not in nm:
            (out / nm).unlink(missing_ok=True)
    for nm in (STATE_NAME, JOURNAL_NAME, MANIFEST_NAME):
        (out / nm).unlink(missing_ok=True)


def _read_json(p: Path):
    try:
        return json.loads(p.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def load_state(out) -> dict | None:
    """The render state of a frames folder: the header (render_state.json) with ``frames`` from the journal.

    ``frames`` maps the tick (a string) to ``{"file", "time_s", "render_noise_ratio"}``. A journal line cut
    short by a kill is ignored (its frame is rendered again).
    """
    out = Path(out)
    state = _read_json(out / STATE_NAME)
    if not isinstance(state, dict):
        return None
    frames = dict(state.get("frames") or {})  # states written before the journal existed
    try:
        lines = (out / JOURNAL_NAME).read_text().splitlines()
    except OSError:
        lines = []
    for line in lines:
        try:
            rec = json.loads(line)
            frames[str(int(rec["tick"]))] = {k: rec[k] for k in ("file", "time_s", "render_noise_ratio") if k in rec}
        except (ValueError, KeyError, TypeError):
            continue
    state["frames"] = frames
    return state


#: the journal is fsync'd at most this often while frames come in [s] (and always when it is closed)
JOURNAL_FSYNC_S = 1.0


class Journal:
    """``OUT/render_journal.jsonl``, appended one line per finished frame (by the writer thread).

    Each line is written and flushed to the operating system at once, after its frame file was renamed
    into place (:mod:`.writer`): a killed process (SIGKILL, OOM, Ctrl-C, SIGTERM) leaves every
    flushed line and every renamed file in the page cache, so a resumed render is exact whatever the
    fsync schedule. ``fsync`` only guards against the *machine* stopping (power loss, kernel crash):
    it runs when a line comes in at least :data:`JOURNAL_FSYNC_S` after the last one, and on
    :meth:`close` (every exit path of :func:`render_scene`, errors and interruptions included), instead
    of once per frame (0.1 ms to several ms each on a busy disk, a fixed cost of every frame). After a
    machine crash at most the last second of lines is lost, and their frames are rendered again: the
    lost lines are the newest ones, so what is left still names only complete files. (The frame files
    themselves were never fsync'd; after a machine crash resume trusts what the file system kept.)
    """

    def __init__(self, path: Path, fsync_every_s: float = JOURNAL_FSYNC_S):
        self.path = Path(path)
        self.fsync_every_s = float(fsync_every_s)
        self._f = None
        self._dirty = False
        self._last_sync = time.monotonic()
        self.n_fsync = 0

    def append(self, rec: dict) -> None:
        if self._f is None:
            self._f = open(self.path, "a")
        self._f.write(json.dumps(rec) + "\n")
        self._f.flush()
        self._dirty = True
        if time.monotonic() - self._last_sync >= self.fsync_every_s:
            self.sync()

    def sync(self) -> None:
        """fsync the lines appended so far (if any are not yet)."""
        if self._f is not None and self._dirty:
            os.fsync(self._f.fileno())
            self._dirty = False
            self.n_fsync += 1
        self._last_sync = time.monotonic()

    def close(self) -> None:
        """fsync and close (idempotent)."""
        if self._f is not None:
            try:
                self.sync()
            finally:
                self._f.close()
                self._f = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


def _write_state(out: Path, state: dict) -> None:
    write_json_atomic(out / STATE_NAME, {k: v for k, v in state.items() if k != "frames"})



def settings_of(scene: Scene, variant: str, launch: str = "film") -> dict:
    """Everything besides the scene data that changes the frames (part of the hash)."""
    # variant_family keeps GPU (cuda) and CPU (llvm/scalar) frames apart; procedure 2: exact spp in one
    # launch per frame, fitted noise budget, curvature-based keyframes (frames of procedure 1 are not resumed);
    # frames_format 2: frames named by tick, light level stored in the render state; procedure 3 (auto spp
    # only): the budget's answer snapped on measured pairs (noise.snap_to_measured), which can choose another
    # spp than procedure 2 did, so a folder of the older budget is not taken for this one's output
    # launch (frozen.LAUNCHES): the frozen launch makes other Monte Carlo estimates than the film's, so its
    # frames get their own hash, with its estimator's version; the film launch adds nothing (the hashes of
    # folders made before it stay valid) except for a scene with a moving mesh given its own normals (a cube,
    # a mesh file with normals: builder.carries_normals): since 2026-11-26 the film launch's vertex rewrites
    # carry those normals (renderer.carried_normals) where Mitsuba had recomputed them, which changes such
    # frames (inside-out negative scales, lost authored normals; round-off elsewhere), so folders of the older
    # frames are not resumed ("mesh_normals"; every film-launch render state and manifest records it since)
    from .frozen import ESTIMATOR_VERSION, check_launch
    if check_launch(launch) == "auto":
        raise ValueError("settings_of takes the launch a render takes (frozen.resolve_launch), not 'auto'")
    auto = scene.render.get("spp") == "auto"
    out = {"variant": variant, "variant_family": backend.variant_family(variant), "frames_format": 2,
           "procedure": 3 if auto else 2}
    if launch != "film":
        out["launch"] = launch
        out["launch_estimator"] = ESTIMATOR_VERSION
    elif _carries_moving_normals(scene):
        out["mesh_normals"] = FILM_MESH_NORMALS
    return out


def _carries_moving_normals(scene: Scene) -> bool:
    return any(carries_normals(scene, obj) for _, obj, _ in moving_meshes(scene))


#: how the film launch moves a mesh's normals with its vertex rewrites (:func:`settings_of`): ``carried`` by the
#: inverse transpose of the pose (:func:`.renderer.carried_normals`); before 2026-11-26 (unrecorded) Mitsuba
#: recomputed them from the triangles
FILM_MESH_NORMALS = "carried"


def _film_mesh_normals(launch: str) -> dict:
    """``{"mesh_normals": ...}`` for the render state and manifest of a film-launch render (of any scene: a
    refused folder without it was made before the change, see :func:`settings_of`)."""
    return {"mesh_normals": FILM_MESH_NORMALS} if launch == "film" else {}


def launch_taken(scene: Scene, variant: str, launch: str, old_hash: str | None = None,
                 old_launch: str | None = None) -> tuple[str, str]:
    """The launch a render of ``scene`` with ``variant`` takes when ``launch`` is asked for, and its scene hash.

    ``film`` and ``frozen`` are taken as named; ``auto`` as :func:`.frozen.resolve_launch` says, except
    that a folder already holding frames (its ``old_hash``, rendered with ``old_launch``) that differ
    from this run's by the launch alone keeps its launch: a folder rendered before ``auto`` was the
    default, or with the other launch, is resumed, not refused (but never with the frozen launch for a
    scene it cannot render, :func:`.frozen.frozen_obstacle`).
    """
    taken = resolve_launch(launch, variant, scene)
    h = scene.content_hash(settings_of(scene, variant, taken))
    if (launch == "auto" and old_hash and old_hash != h and old_launch in ("film", "frozen") and old_launch != taken
            and not (old_launch == "frozen" and frozen_obstacle(scene))):  # (never a launch the scene cannot take)
        h_old = scene.content_hash(settings_of(scene, variant, old_launch))
        if h_old == old_hash:
            return old_launch, h_old
    return taken, h


def render_scene(scene: Scene, out, *, overwrite: bool = False, progress: bool = True, variant: str | None = None,
                 log=print, launch: str = DEFAULT_LAUNCH) -> RenderResult:
    """Render ``scene`` into the frames folder ``out`` (resuming if possible). See the module docstring.

    ``launch``: how each render is launched (:data:`.frozen.LAUNCHES`: ``auto``, the default, ``film``
    or ``frozen``, :mod:`.frozen`; :func:`launch_taken` says which ``auto`` takes); part of the folder's
    hash, so a folder is resumed only by the launch it was rendered with (``auto`` takes that one).
    The launch taken is in the manifest, the render state and every frame's header.

    Raises :class:`sensor.errors.InputError` (before anything is written) for a folder of another scene
    (without ``overwrite``), a folder another render is writing into, or a scene with no usable light.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError("output path exists and is not a folder", path=out)
    created = not out.exists()
    lock = FolderLock(out, "a render", log=log)
    lock.acquire()
    wrote = {"any": False}
    try:
        sweep_parts(out, log=log)
        return _render_locked(scene, out, overwrite, progress, variant, log, wrote, launch)
    except BaseException:
        lock.release()
        if created and not wrote["any"]:  # nothing of ours to keep: leave no empty folder behind
            for nm in (STATE_NAME, JOURNAL_NAME):
                (out / nm).unlink(missing_ok=True)
            with contextlib.suppress(OSError):
                out.rmdir()
        raise
    finally:
        lock.release()


def _refusal_hint(scene: Scene, variant: str, launch: str, asked: str, old_hash: str, old_variant,
                  old_launch: str, manifest: dict, state: dict) -> str:
    """What to do about a folder whose frames' hash (``old_hash``) is not this run's: a command is suggested
    only where it would resume the folder (the folder's hash recomputed with that variant and launch), the
    fewest switches first; and the film launch's change of 2026-11-26 (:data:`FILM_MESH_NORMALS`) is named
    where the hash without it (with this run's variant or the folder's) is the folder's."""
    def h(v: str, lnch: str, no_mesh_normals: bool = False):
        try:
            d = settings_of(scene, v, lnch)
        except (AttributeError, TypeError, ValueError):  # (a variant that is no name)
            return None
        if no_mesh_normals and d.pop("mesh_normals", None) is None:
            return None  # (no moving mesh whose normals the film launch carries: not the cause)
        return scene.content_hash(d)

    if not isinstance(old_hash, str) or not old_hash:  # (a summary without a hash: nothing to match against)
        return ""
    old_v = old_variant if isinstance(old_variant, str) else None  # (a name no variant has matches no hash)
    old_l = old_launch if old_launch in ("film", "frozen") else None
    tries = []  # (switches, variant, launch): the commands that would resume it, fewest switches first
    if old_v and old_v != variant:
        tries.append((f"--variant {old_v}", old_v, launch))
    if old_l and old_l != launch and asked != "auto":  # (auto would have taken the folder's launch)
        tries.append((f"--launch {old_l}", variant, old_l))
    if old_v and old_v != variant and old_l and old_l != launch:
        tries.append((f"--variant {old_v} --launch {old_l}", old_v, old_l))
    hint = ""
    for switches, v, lnch in tries:
        if h(v, lnch) == old_hash:
            what = " and ".join(x for x in (f"Mitsuba '{v}'" if v != variant else "",
                                            f"the {lnch} launch" if lnch != launch else "") if x)
            where = ""
            if v != variant and v not in (backend.GPU_VARIANT, backend.PREFERRED_VARIANT, backend.FALLBACK_VARIANT):
                where = f" (a variant the CLI does not offer: set RENDER2SPIKE_VARIANT={v} instead of --variant)"
            elif v != variant and backend.variant_family(v) == "cuda":
                where = " on a machine with a CUDA GPU"
            hint = f" It was rendered with {what}: pass {switches} to resume it{where}."
            break
    old_est = manifest.get("launch_estimator", state.get("launch_estimator"))
    if old_launch == launch == "frozen" and old_est != _frozen.ESTIMATOR_VERSION and not hint:
        was = f"estimator {old_est}" if old_est is not None else "an estimator before 3, unrecorded"
        hint += (f" If nothing else changed, its frames were made by an earlier version of the frozen "
                 f"launch ({was}; now {_frozen.ESTIMATOR_VERSION}), which is not resumed: --overwrite "
                 "renders them again.")
    old_normals = manifest.get("mesh_normals", state.get("mesh_normals"))
    if old_launch == "film" and old_normals != FILM_MESH_NORMALS:
        on = next((v for v in (variant, old_v) if v and h(v, "film", no_mesh_normals=True) == old_hash), None)
        if on:
            hint += (f" Its frames were made{'' if on == variant else f' with Mitsuba {on!r}'} by the film launch "
                     "before it carried its moving meshes' normals along (2026-11-26; Mitsuba had recomputed "
                     "them, which turned a mesh with a negative scale inside out and lost a mesh file's own "
                     "normals), and are not resumed: --overwrite renders them again.")
    return hint


def _render_locked(scene: Scene, out: Path, overwrite: bool, progress: bool, variant, log, wrote,
                   launch: str = DEFAULT_LAUNCH) -> RenderResult:
    t_start = time.perf_counter()
    asked = check_launch(launch)
    mi = backend.mitsuba(variant)
    variant = mi.variant()
    manifest = _read_json(out / MANIFEST_NAME)
    manifest = manifest if isinstance(manifest, dict) else None
    state = load_state(out)
    old_hash = (manifest or {}).get("scene_hash") or (state or {}).get("scene_hash")
    old_launch = (manifest or {}).get("launch") or (state or {}).get("launch") or "film"
    launch, scene_hash = launch_taken(scene, variant, asked, None if overwrite else old_hash, old_launch)
    if asked == "auto" and old_hash == scene_hash and launch != resolve_launch(asked, variant, scene):
        log(f"render: {out} holds frames of the {launch} launch: resuming with it (--launch auto)")
    if old_hash is not None and old_hash != scene_hash:
        if not overwrite:
            old_variant = (manifest or {}).get("variant") or (state or {}).get("variant")
            hint = _refusal_hint(scene, variant, launch, asked, old_hash, old_variant, old_launch,
                                 manifest or {}, state or {})
            raise InputError(f"this folder holds frames of a different scene or settings (hash {old_hash}, now "
                             f"{scene_hash}); rerun with --overwrite to replace them, or choose another --out."
                             + hint, path=out)
        _clean(out, state, manifest)
        manifest = state = None
    elif (manifest or state) and overwrite:
        _clean(out, state, manifest)
        manifest = state = None
    if manifest is not None and manifest.get("complete") and old_hash == scene_hash:
        if all((out / f["file"]).is_file() for f in manifest["frames"]):
            log(f"render: {out} is up to date ({len(manifest['frames'])} frames, scene hash {scene_hash})")
            return RenderResult(out, len(manifest["frames"]), 0, int(manifest.get("spp", 0)), scene_hash,
                                time.perf_counter() - t_start, True, manifest)
    if manifest is None and state is None and not overwrite and any(
            not p.name.startswith(".") for p in out.iterdir()):
        raise InputError("this folder is not empty and holds no render2spike frames; choose an empty or new "
                         "folder for --out (or pass --overwrite to render into it anyway)", path=out)
    if state is not None and state.get("format_version") != 2:
        _clean(out, state, manifest)  # a state from before the journal: its frames are named differently
        state = None
    if state is None:
        state = {"format_version": 2, "scene_hash": scene_hash, "scene": str(scene.path), "variant": variant,
                 "launch": launch, **_film_mesh_normals(launch),
                 **({"launch_estimator": _frozen.ESTIMATOR_VERSION} if launch == "frozen" else {}),
                 "frames": {}, "complete": False}
    # keep only frames whose files exist
    state["frames"] = {k: v for k, v in state["frames"].items() if (out / v["file"]).is_file()}
    n_resumed = len(state["frames"])

    from .renderer import SceneRenderer
    rnd = SceneRenderer(scene, variant, calibration=state.get("calibration"), launch=launch)
    state["calibration"] = rnd.calibration
    rcfg = scene.render
    ncfg = rcfg["noise"]
    W = int(ncfg["window_intervals"])
    rate_scale = rnd.rate_scale()

    # ---- noise budget: pilot pairs at t = 0, convergence fitted (noise.pilot_budget) -----------
    K = keyframes_per_window(W, scene.profile.interval_s, float(rcfg["keyframe_rate_hz"]))
    # with a fixed spp, a pilot render at t = 0 and that spp is the first frame's second (verification)
    # render: no launch added. Not with spp = auto: the snapping chose the spp on those very pairs, and the
    # verification is there to check that choice on renders it did not see
    keep = rnd.keep_renders() if rcfg["spp"] != "auto" else contextlib.nullcontext()
    with keep:
        budget, pilot_var_px = pilot_budget(rnd, scene, W, K, rate_scale, snap=rcfg["spp"] == "auto")
    if "spp" in state and "noise_budget" in state:  # resuming: the frames already made fix the spp
        budget = state["noise_budget"]
        spp = int(state["spp"])
    else:
        spp = int(rcfg["spp"]) if rcfg["spp"] != "auto" else budget["spp"]  # taken exactly (launch_counts)
        state["spp"], state["noise_budget"] = spp, budget
    _write_state(out, state)
    if rcfg["spp"] == "auto" and budget["clipped"]:
        log(f"render: note: the noise budget asks for {budget['spp_needed']} spp, more than max_spp = "
            f"{ncfg['max_spp']}; render noise will be ~{budget['predicted_ratio']:.2f} of the shot noise over "
            f"{W} intervals (recorded per frame as render_noise_ratio)")
    # noise floor of the change metric: smoothed pilot variance, scaled to the chosen spp
    v_px = pilot_var_px(spp)
    var_floor = np.maximum(_box(v_px, 2), float(np.median(v_px)))

    # ---- adaptive keyframes ---------------------------------------------------------
    acfg = rcfg["adaptive"]
    grid = TimeGrid.make(scene.duration_s, float(rcfg["keyframe_rate_hz"]), float(acfg["max_rate_hz"]))
    try:
        from tqdm.auto import tqdm
    except ImportError:  # pragma: no cover
        tqdm = None
    # progress in camera time [ms]: the furthest keyframe time asked for so far (base keyframes are rendered
    # one ahead, refinements fall before it), so the bar only moves forward and its total never changes; the
    # frame counts (base and refined) are shown beside it
    dur_ms = scene.duration_s * 1e3
    bar = tqdm(total=round(dur_ms, 3), unit="ms", desc=f"render {scene.name}", disable=not progress,
               dynamic_ncols=True, bar_format="{l_bar}{bar}| {n:.1f}/{total:.1f} ms camera time "
               "[{elapsed}<{remaining}{postfix}]") if tqdm else None
    seen = {"tick": 0, "frames": 0, "refined": 0}

    def advance(tick: int) -> None:
        seen["frames"] += 1
        if bar is None:
            return
        seen["tick"] = max(seen["tick"], tick)
        target = round(dur_ms * seen["tick"] / grid.n_ticks, 3)
        # the counts are set without a redraw: the bar redraws them at its own pace (tqdm's mininterval) as it
        # moves, and at close; a redraw per frame cost 25 us (to a file) to ~0.1 ms (a terminal), 1-3 % of a
        # small frame
        bar.set_postfix_str(f"{seen['frames']} frames, {seen['refined']} refined", refresh=False)
        if target > bar.n:
            bar.update(target - bar.n)
    n_rendered = 0
    ratios = []
    made_by = json.dumps({"stage": "render", "tool": "render2spike", "scene": scene.name, "variant": variant,
                          "launch": launch})

    def get_frame(tick: int):
        nonlocal n_rendered
        key = str(tick)
        t_s = grid.time(tick)
        rec = state["frames"].get(key)
        if rec is not None:
            fr = read_frame(out / rec["file"])
            advance(tick)
            return fr.phi.astype(np.float64)
        # the achieved ratio is measured on the first and every VERIFY_EVERY-th (128th) frame (one extra render each)
        f = rnd.render_frame(t_s, int(rcfg["seed"]), spp, variance=n_rendered % VERIFY_EVERY == 0)
        if f["phi_var"] is None:
            ratio = float("nan")  # what render_noise_ratio gives without a variance
        else:
            ratio = render_noise_ratio(f["phi"] * rate_scale, f["phi_var"] * rate_scale ** 2, W, K)
        ratios.append(ratio)
        if not (np.isfinite(f["phi"]).all() and np.isfinite(f["lux"]).all()):
            bad = ~np.isfinite(f["phi"]) | ~np.isfinite(f["lux"])
            r, c = (int(x) for x in np.argwhere(bad)[0])
            raise InputError(f"the frame at t = {t_s:.6g} s has {int(bad.sum())} non-finite pixel(s), first at row "
                             f"{r}, column {c}: check the scene's light and material values", path=scene.path)
        name = tick_filename(tick)
        attrs = {"spp": int(spp), "render_noise_ratio": float(ratio), "render_noise_window_intervals": W,
                 "variant": variant, "launch": launch, "scene_hash": scene_hash,
                 "target_lux": float(scene.illuminance_lux),
                 "seeds": f["seeds"], "made_by": made_by, "scene": scene.name}
        state["frames"][key] = {"file": name, "time_s": t_s, "render_noise_ratio": float(ratio)}
        # written in the background while the next frame renders; its journal line follows the file. The
        # float64 arrays are handed over as they are (nothing here changes them later): the writer thread
        # rounds them to the file's float32, off the render loop
        writer.submit(out / name, f["phi"], f["lux"], time_s=t_s,
                      attrs=attrs, record={"tick": int(tick), **state["frames"][key]})
        n_rendered += 1
        advance(tick)
        return f["phi"]

    metric = interpolation_metric(var_floor, rate_scale, W, scene.profile.interval_s, z=4.0)

    def on_new(n):
        seen["refined"] += n

    journal_file = Journal(out / JOURNAL_NAME)

    def journal(rec: dict) -> None:  # writer thread: the frame file is in place
        journal_file.append(rec)
        wrote["any"] = True

    try:
        # the writer finishes the queued frames and closes (fsyncs) the journal, in its thread, while the
        # manifest is prepared here; both are done (the thread joined) before the manifest is written
        with journal_file, FrameWriter(on_written=journal, on_stop=journal_file.close) as writer:
            ticks = adaptive_ticks(grid, get_frame, metric, float(acfg["tolerance"]), on_new=on_new,
                                   adaptive=bool(acfg["enabled"]))
            writer.stop()
            if bar:
                bar.close()
            frames = [{"file": state["frames"][str(t)]["file"], "time_s": grid.time(t)} for t in ticks]
            # frames rendered in a run that refined differently are not part of the result: drop them
            keep = {str(t) for t in ticks}
            for k in [k for k in state["frames"] if k not in keep]:
                (out / state["frames"][k]["file"]).unlink(missing_ok=True)
                del state["frames"][k]
            all_ratios = [state["frames"][str(t)].get("render_noise_ratio", float("nan")) for t in ticks]
            verified, warn = verify_ratios(all_ratios, float(ncfg["target_ratio"]), rcfg["spp"] == "auto", budget)
            if warn:
                log(f"render: warning: {warn}")
            seconds = time.perf_counter() - t_start
            prof = scene.profile
            extra = {
                "complete": True,
                "scene_hash": scene_hash,
                "scene": {"name": scene.name, "path": str(scene.path), "description": scene.data.get("description", "")},
                "scene_data": scene.data,
                "illuminance_lux": scene.illuminance_lux,
                "reference": rnd.calibration,
                "emitter_scale_w_per_raw": rnd.k,
                "camera": {"focal_length_mm": scene.camera["focal_length_mm"], "f_number": rnd.f_number,
                           "transmission": rnd.transmission, "pixel_pitch_m": prof.pixel_pitch_m,
                           "fill_factor": prof.fill_factor},
                "profile": {"name": prof.name, "spec": scene.camera["profile"], "height": prof.height, "width": prof.width},
                "variant": variant,
                "launch": launch,
                **({"launch_estimator": _frozen.ESTIMATOR_VERSION} if launch == "frozen" else {}),
                **_film_mesh_normals(launch),
                "spp": spp,
                "noise_budget": budget,
                "render_noise_ratio": {"mean": float(np.nanmean(all_ratios)) if np.any(np.isfinite(all_ratios)) else None,
                                       "max": float(np.nanmax(all_ratios)) if np.any(np.isfinite(all_ratios)) else None,
                                       "window_intervals": W, "keyframes_per_window": K, **verified},
                "temporal_sampling": {"base_rate_hz": float(rcfg["keyframe_rate_hz"]), "max_rate_hz": float(acfg["max_rate_hz"]),
                                      "tolerance": float(acfg["tolerance"]), "adaptive": bool(acfg["enabled"]),
                                      "n_base": grid.n_base + 1, "n_keyframes": len(ticks),
                                      "n_refined": len(ticks) - grid.n_base - 1},
                "n_rendered_this_run": n_rendered,
                "n_resumed": n_resumed,
                "render_seconds": seconds,
                "provenance": provenance(stage="render"),
            }
            manifest = json.loads(json.dumps(extra, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))
            # the two files' text, written once the writer is done (the manifest first, then the state)
            manifest_text = json_bytes(manifest_record(prof.height, prof.width, frames, **manifest))
            state_text = json_bytes({**{k: v for k, v in state.items() if k != "frames"}, "complete": True})
    finally:
        if bar:
            bar.close()
    write_bytes_atomic(out / MANIFEST_NAME, manifest_text)
    write_bytes_atomic(out / STATE_NAME, state_text)
    state["complete"] = True
    return RenderResult(out, len(frames), n_rendered, spp, scene_hash, seconds, False, json.loads(manifest_text))
