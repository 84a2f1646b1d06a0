"""Spike datasets from scene files: ``render2spike dataset SPEC.yaml --out DIR``, on one machine or a Dask cluster.

Spec (YAML or JSON; every key optional except ``scenes``)::

    format: render2spike-dataset
    seed: 0                  # master seed: random draws and derived simulation seeds
    mode: grid               # grid: every combination of the lists; random: `samples` seeded draws
    samples: 16              # random mode: how many samples
    scenes:                  # bundled names, scene files, {scene: NAME, set: [KEY=VALUE, ...]} or {frames: DIR}
      - translating_object
      - {scene: rotating_disk, set: ["render.spp=16"]}
    set: ["render.spp=16"]   # overrides for every scene file (docs/render.md)
    duration_s: 0.05         # each axis: a value, a list, or (random mode) {uniform: [a, b]} / {log_uniform: [a, b]}
    lux: [5, 50]             # scene illuminance at the reference [lux]
    params:                  # any numeric scene key (dotted path) or named scene parameter
      speed_px_per_ms: [0.1, 0.5]
    profiles: [scene]        # sensor profiles: `scene` (the scene's camera), a bundled name or a file
    models: [elssim, isi]    # spike models; MODEL:RESET (e.g. elssim:crossing) where the profile has `reset`
    seeds: [0, 1]            # simulation seeds (random mode: drawn from the list; default: derived per sample)
    window: 320              # intervals of the clean window average stored with the truth
    centers: 3               # window centres per sample
    preroll: 2000            # intervals simulated and dropped before the clip (render2spike.studies.common)

Output::

    DIR/manifest.json                    spec, its hash, every sample's status (done / failed + error + attempts)
    DIR/summary.md                       counts, failures, timings
    DIR/renders/<render_key>/            one render per scene + parameters (+ duration): every lux reuses it
    DIR/samples/<sample_id>/frames.json  the clean irradiance of this sample (frames contract, scaled to its lux)
    DIR/samples/<sample_id>/frame_*.exr
    DIR/samples/<sample_id>/spikes.npz   the spike stream (render2spike-spikes container, bit-packed)
    DIR/samples/<sample_id>/truth.npz    rate_e (K, H, W) [e-/interval] at times_s (K,) [s]; centers (C,);
                                         clean (C, H, W) and clean_window_average (C, H, W) [ideal spikes/interval]
    DIR/samples/<sample_id>/sample.json  how it was made (scene, overrides, lux, profile, model, seed, keys)

``render2spike train --data rendered:DIR`` reads the samples' frames folders
(``:spikes=spikes.npz`` to train on the stored streams instead of fresh
simulations).

Keys, idempotence, resume
-------------------------
A render is keyed by the content hash of the loaded scene (overrides and
duration included, the light level excluded: light is linear, so the frames
are rescaled exactly to each lux). A sample is keyed by the hash of its render
key and its own parameters. Each sample is written to a temporary folder and
renamed when complete; a sample whose folder exists is skipped, so a killed
run resumes where it stopped. Sample files hold no timestamps or machine
names (those go to the manifest): the same spec and seeds give byte-identical
samples on any number of workers.

Failures are retried (``retries``), then recorded in the manifest and the
summary with their error; never dropped silently.
"""

from __future__ import annotations

import copy
import hashlib
import io
import itertools
import json
import os
import shutil
import threading
import time
import uuid
import zipfile
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from sensor.errors import DependencyError, InputError, UnknownMethodError
from sensor.io.fileio import atomic_path, package_version, provenance, write_json_atomic, write_text_atomic

DATASET_FORMAT = "render2spike-dataset"
DATASET_VERSION = 1
MANIFEST = "manifest.json"
#: environment variable: SIGKILL this process after this many samples were recorded (to test resume)
KILL_AFTER_ENV = "RENDER2SPIKE_DATASET_KILL_AFTER"

_AXIS = {"oneOf": [{"type": "number"}, {"type": "array", "items": {"type": "number"}, "minItems": 1},
                   {"type": "object", "additionalProperties": False, "minProperties": 1, "maxProperties": 1,
                    "properties": {"uniform": {"type": "array", "items": {"type": "number"}, "minItems": 2,
                                               "maxItems": 2},
                                   "log_uniform": {"type": "array", "items": {"type": "number",
                                                                              "exclusiveMinimum": 0},
                                                   "minItems": 2, "maxItems": 2}}}]}
_WORDS = {"oneOf": [{"type": "string"}, {"type": "array", "items": {"type": "string"}, "minItems": 1}]}
SPEC_SCHEMA = {
    "type": "object", "additionalProperties": False, "required": ["scenes"],
    "properties": {
        "format": {"const": DATASET_FORMAT}, "version": {"const": 1},
        "seed": {"type": "integer", "minimum": 0},
        "mode": {"enum": ["grid", "random"]},
        "samples": {"type": "integer", "minimum": 1},
        "scenes": {"type": "array", "minItems": 1, "items": {"oneOf": [
            {"type": "string"},
            {"type": "object", "additionalProperties": False, "required": ["scene"],
             "properties": {"scene": {"type": "string"}, "set": {"type": "array", "items": {"type": "string"}}}},
            {"type": "object", "additionalProperties": False, "required": ["frames"],
             "properties": {"frames": {"type": "string"}, "profile": {"type": "string"}}}]}},
        "set": {"type": "array", "items": {"type": "string"}},
        "duration_s": _AXIS, "lux": _AXIS,
        "params": {"type": "object", "additionalProperties": _AXIS},
        "profiles": _WORDS, "models": _WORDS,
        "seeds": {"oneOf": [{"type": "integer", "minimum": 0},
                            {"type": "array", "items": {"type": "integer", "minimum": 0}, "minItems": 1}]},
        "window": {"type": "integer", "minimum": 1},
        "centers": {"type": "integer", "minimum": 1},
        "preroll": {"type": "integer", "minimum": 0},
    },
}
SPEC_DEFAULTS = {"seed": 0, "mode": "grid", "set": [], "params": {}, "profiles": ["scene"], "models": ["elssim"],
                 "window": 320, "centers": 3, "preroll": 2000}

_RENDER_LOCK = threading.Lock()  # Mitsuba: one render at a time per process


# ------------------------------------------------------------------------------------------------ the spec
def load_spec(spec) -> tuple[dict, Path | None]:
    """Read (a path) or take (a dict) a dataset spec, validate it, fill defaults. Returns (spec, its path)."""
    from render2spike.render.scene import _yaml
    path = None
    if not isinstance(spec, dict):
        path = Path(spec)
        if not path.is_file():
            raise InputError("dataset spec not found", path=path)
        try:
            spec = _yaml().safe_load(path.read_text())
        except Exception as exc:
            raise InputError(f"not valid YAML: {exc}", path=path) from exc
    if not isinstance(spec, dict):
        raise InputError("a dataset spec must be a mapping of keys", path=path)
    validate_spec(spec, path)
    out = copy.deepcopy(SPEC_DEFAULTS)
    out.update(copy.deepcopy(spec))
    for key in ("profiles", "models"):
        if isinstance(out[key], str):
            out[key] = [out[key]]
    if out["mode"] == "random" and "samples" not in out:
        raise InputError("random mode needs 'samples' (how many draws)", path=path, field="samples")
    if out["mode"] == "grid":
        if "samples" in spec:
            raise InputError("'samples' is for random mode; a grid makes every combination", path=path,
                             field="samples")
        for key, value in [("duration_s", out.get("duration_s")), ("lux", out.get("lux"))] + \
                [(f"params.{k}", v) for k, v in out["params"].items()]:
            if isinstance(value, dict):
                raise InputError(f"{next(iter(value))} draws need mode: random; a grid takes a value or a list",
                                 path=path, field=key)
    from render2spike.studies.common import parse_model_spec
    for i, m in enumerate(out["models"]):
        try:
            parse_model_spec(m)
        except (InputError, UnknownMethodError) as exc:
            raise InputError(str(exc), path=path, field=f"models.{i}") from None
    from render2spike.render.scene import resolve_scene_path
    base = path.parent if path else Path.cwd()
    for i, sc in enumerate(out["scenes"]):
        if isinstance(sc, dict) and "frames" in sc:
            f = Path(sc["frames"])
            f = f if f.is_absolute() else base / f
            if not (f / "frames.json").is_file():
                raise InputError(f"no frames.json in {f}", path=path, field=f"scenes.{i}.frames")
            sc["frames"] = str(f.resolve())
            continue
        name = sc["scene"] if isinstance(sc, dict) else sc
        cand = Path(name) if Path(name).is_absolute() else base / name
        try:
            resolved = resolve_scene_path(cand if cand.is_file() else name)
        except InputError as exc:
            raise InputError(str(exc), path=path, field=f"scenes.{i}") from None
        out["scenes"][i] = {"scene": str(resolved.resolve()), "set": list(sc.get("set", [])) if isinstance(sc, dict)
                            else []}
    return out, path


def validate_spec(spec: dict, path=None) -> None:
    """jsonschema check of a dataset spec; errors name the key."""
    try:
        import jsonschema
    except ImportError as exc:  # pragma: no cover
        raise DependencyError("jsonschema is not installed: pip install jsonschema") from exc
    from render2spike.render.scene import _describe, _error_path
    v = jsonschema.Draft202012Validator(SPEC_SCHEMA)
    errs = sorted(v.iter_errors(spec), key=lambda e: (len(list(e.absolute_path)), str(e.message)))
    if errs:
        e = errs[-1] if errs[0].validator == "oneOf" and len(errs) > 1 else errs[0]
        raise InputError(_describe(e), path=path, field=_error_path(e))


def _values(v):
    return v if isinstance(v, list) else [v]


def _draw(rng, v):
    if isinstance(v, dict):
        (kind, (lo, hi)), = v.items()
        if kind == "uniform":
            return float(rng.uniform(lo, hi))
        return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
    vals = _values(v)
    return vals[int(rng.integers(len(vals)))]


@dataclass(frozen=True)
class SampleSpec:
    """Everything that makes one sample (hashed into its id)."""

    index: int
    source: dict                # {"scene": path, "set": [...]} or {"frames": DIR}
    sets: tuple                 # spec-wide overrides + parameter values (KEY=VALUE)
    duration_s: float | None
    lux: float | None
    profile: str
    model: str
    seed: int
    window: int
    centers: int
    preroll: int

    def render_request(self) -> dict:
        """What the render depends on (not the light level)."""
        return {"source": self.source, "sets": list(self.sets), "duration_s": self.duration_s}


def plan(spec: dict) -> list[SampleSpec]:
    """The samples of a (loaded) spec, in a fixed order."""
    params = sorted(spec["params"].items())
    seeds = spec.get("seeds")
    common = dict(window=int(spec["window"]), centers=int(spec["centers"]), preroll=int(spec["preroll"]))
    out = []
    if spec["mode"] == "grid":
        axes = [spec["scenes"], _values(spec.get("duration_s")), _values(spec.get("lux"))] + \
               [_values(v) for _, v in params] + [spec["profiles"], spec["models"],
                                                  _values(seeds if seeds is not None else 0)]
        for i, combo in enumerate(itertools.product(*axes)):
            src, dur, lux = combo[:3]
            pv = combo[3:3 + len(params)]
            prof, model, seed = combo[3 + len(params):]
            sets = tuple(spec["set"]) + tuple(f"{k}={v!r}" for (k, _), v in zip(params, pv))
            out.append(SampleSpec(i, src, sets, None if dur is None else float(dur), None if lux is None else float(lux),
                                  str(prof), str(model), int(seed), **common))
        return out
    for i in range(int(spec["samples"])):
        rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence(int(spec["seed"]), spawn_key=(i, 0))))
        src = spec["scenes"][int(rng.integers(len(spec["scenes"])))]
        dur = spec.get("duration_s")
        dur = None if dur is None else float(_draw(rng, dur))
        lux = spec.get("lux")
        lux = None if lux is None else float(_draw(rng, lux))
        pv = [_draw(rng, v) for _, v in params]
        prof = _draw(rng, spec["profiles"])
        model = _draw(rng, spec["models"])
        if seeds is None:
            seed = int(np.random.SeedSequence(int(spec["seed"]), spawn_key=(i, 1)).generate_state(1)[0])
        else:
            seed = int(_draw(rng, _values(seeds)))
        sets = tuple(spec["set"]) + tuple(f"{k}={v!r}" for (k, _), v in zip(params, pv))
        out.append(SampleSpec(i, src, sets, dur, lux, str(prof), str(model), seed, **common))
    return out


def _hash(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _load_source_scene(s: SampleSpec):
    from render2spike.render.scene import load_scene
    try:
        return load_scene(s.source["scene"], list(s.source.get("set", [])) + list(s.sets), duration_s=s.duration_s)
    except InputError as exc:
        raise InputError(f"sample {s.index}: {exc}", field="scenes") from None


def render_key(s: SampleSpec) -> str:
    """Content hash of what the frames depend on (scene data and files, overrides, duration; not the lux)."""
    if "frames" in s.source:
        return "f" + _hash({"frames": (Path(s.source["frames"]) / "frames.json").read_bytes().hex()})[:15]
    return _load_source_scene(s).content_hash({"dataset_render": 1})


def sample_id(s: SampleSpec, rkey: str) -> str:
    d = asdict(s)
    d.pop("index")
    d.pop("source")
    d.pop("sets")
    d.pop("duration_s")
    return _hash({"render": rkey, "sample": d, "format": DATASET_VERSION})


# ------------------------------------------------------------------------------------------------ the tasks
def render_task(s: SampleSpec, rkey: str, out_root: str) -> str:
    """Render (or find) the frames of ``s``'s scene; returns the frames folder. Idempotent."""
    if "frames" in s.source:
        return s.source["frames"]
    from render2spike.render.job import render_scene
    folder = Path(out_root) / "renders" / rkey
    with _RENDER_LOCK:
        sc = _load_source_scene(s)
        render_scene(sc, folder, progress=False, log=lambda *a, **k: None)
    return str(folder)


def _det_provenance() -> dict:
    """Provenance without time or machine (sample files must be byte-identical wherever they are made)."""
    return {"tool": "render2spike dataset", "version": package_version()}


def write_npz_deterministic(path, arrays: dict) -> Path:
    """An ``.npz`` (zip of .npy, deflated) with fixed timestamps, written atomically: same arrays, same bytes."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, arr in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            b = io.BytesIO()
            np.lib.format.write_array(b, np.asanyarray(arr), allow_pickle=False)
            zf.writestr(info, b.getvalue())
    with atomic_path(Path(path)) as tmp:
        tmp.write_bytes(buf.getvalue())
    return Path(path)


def _scene_profile_spec(frames_folder: Path, s: SampleSpec):
    if s.profile != "scene":
        return s.profile
    if "frames" in s.source and s.source.get("profile"):
        return s.source["profile"]
    man = json.loads((frames_folder / "frames.json").read_text())
    spec = (man.get("profile") or {}).get("spec")
    if spec is None:
        raise InputError(f"the frames in {frames_folder} do not say which sensor they were rendered for; give "
                         "'profiles' (or 'profile' next to 'frames') in the spec", field="profiles")
    return spec


def sample_task(s: SampleSpec, sid: str, frames_folder: str, out_root: str) -> dict:
    """Make sample ``sid`` (simulate, store spikes, truth, frames, metadata) unless it exists. Idempotent."""
    from render2spike.render.scene import build_profile
    from render2spike.studies.common import (clean_image, clean_window_average, parse_model_spec, profile_for,
                                             simulate_clip, window_centers)
    from sensor import photoelectron_rate
    from sensor.io.frames import read_frames, write_frames
    from sensor.io.spikefile import SPIKES_FORMAT, SPIKES_VERSION, pack_frames

    t0 = time.perf_counter()
    final = Path(out_root) / "samples" / sid
    if (final / "sample.json").is_file():
        return {"id": sid, "status": "done", "skipped": True, "seconds": 0.0}
    frames_folder = Path(frames_folder)
    fs = read_frames(frames_folder)
    man = fs.manifest
    ref_lux = float(man.get("illuminance_lux", man.get("target_lux", 0)) or 0)
    lux = ref_lux if s.lux is None else s.lux
    if ref_lux <= 0:
        raise InputError("the frames do not say at which illuminance they were rendered", path=frames_folder,
                         field="illuminance_lux")
    spec = _scene_profile_spec(frames_folder, s)
    base = build_profile(spec) if isinstance(spec, dict) else spec
    prof = profile_for(base, fs.shape, s.model)
    scale = np.float32(lux / ref_lux)
    phi = fs.phi_stack().astype(np.float32) * scale
    t = np.asarray(fs.times_s, np.float64)
    rate = photoelectron_rate(phi, prof).astype(np.float32)
    spikes = simulate_clip(rate, t, prof, s.model, s.seed, s.preroll)
    T = spikes.shape[0]
    centers = window_centers(T, min(s.window, T), s.centers)
    clean = np.stack([clean_image(rate, t, c, prof) for c in centers])
    avg = np.stack([clean_window_average(rate, t, c, min(s.window, T), prof) for c in centers])

    tmp = final.parent / f".tmp-{sid}-{uuid.uuid4().hex[:8]}"
    tmp.mkdir(parents=True)
    try:
        lux_frames = None
        try:
            lux_frames = np.stack([fs.read(i).illuminance_lux for i in range(len(fs))]).astype(np.float32) * scale
        except Exception:  # frames without an E channel
            lux_frames = None
        model, reset = parse_model_spec(s.model)
        info = {"format": DATASET_FORMAT + "-sample", "version": DATASET_VERSION, "id": sid, "index": s.index,
                "render_key": Path(frames_folder).name, "source": s.source, "sets": list(s.sets),
                "duration_s": s.duration_s, "illuminance_lux": lux, "rendered_at_lux": ref_lux,
                "profile": spec, "profile_id": prof.name, "model": model,
                "reset": getattr(prof, "reset", reset),  # the effective reset (a bare model follows the profile)
                "model_spec": s.model,
                "seed": s.seed, "preroll_intervals": s.preroll, "window_intervals": min(s.window, T),
                "centers": list(centers), "n_intervals": int(T), "interval_s": prof.interval_s,
                "threshold_e": prof.threshold_e, "height": prof.height, "width": prof.width,
                "spikes_total": int(spikes.sum()), "mean_rate_e_per_interval": float(rate.mean()),
                "files": {"frames": "frames.json", "spikes": "spikes.npz", "truth": "truth.npz"},
                "provenance": _det_provenance()}
        write_frames(tmp, phi, t, focal_lux=lux_frames,
                     manifest={"illuminance_lux": lux, "dataset_sample": sid, "provenance": _det_provenance()})
        meta = {"format": SPIKES_FORMAT, "version": SPIKES_VERSION, "height": prof.height, "width": prof.width,
                "n_intervals": int(T), "interval_s": prof.interval_s, "model": model, "implementation": "fast",
                "profile_id": prof.name, "seed": s.seed, "source": "frames.json",
                "reset": getattr(prof, "reset", reset),
                "preroll_intervals": s.preroll, "illuminance_lux": lux, "dataset_sample": sid,
                "provenance": _det_provenance()}
        write_npz_deterministic(tmp / "spikes.npz", {
            "packed": pack_frames(spikes),
            "meta_json": np.frombuffer(json.dumps(meta, sort_keys=True, default=str).encode(), np.uint8)})
        write_npz_deterministic(tmp / "truth.npz", {"rate_e": rate, "times_s": t, "centers": np.asarray(centers),
                                                    "clean": clean, "clean_window_average": avg})
        write_json_atomic(tmp / "sample.json", info)
        try:
            os.rename(tmp, final)
        except OSError:
            if not (final / "sample.json").is_file():  # someone else finished it? else a real error
                raise
            shutil.rmtree(tmp, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return {"id": sid, "status": "done", "skipped": False, "seconds": time.perf_counter() - t0}


# ------------------------------------------------------------------------------------------------ the run
@dataclass
class DatasetResult:
    out: Path
    n_samples: int
    n_done: int
    n_made: int
    n_skipped: int
    failed: list = field(default_factory=list)
    seconds: float = 0.0


def _client_for(scheduler: str | None, workers: int | None, resources: dict | None = None):
    try:
        from dask.distributed import Client, LocalCluster
    except ImportError as exc:
        raise DependencyError("datasets run on Dask: pip install 'dask[distributed]'") from exc
    if scheduler:
        return Client(scheduler)
    n = int(workers) if workers else max(1, (os.cpu_count() or 1))
    extra = {"resources": resources} if resources else {}
    return Client(LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None, **extra))


def parse_resources(text) -> dict | None:
    """``GPU=1,MEM=4e9`` -> {"GPU": 1.0, "MEM": 4e9} (Dask worker resources each task claims)."""
    if not text:
        return None
    out = {}
    for tok in str(text).split(","):
        k, sep, v = tok.partition("=")
        try:
            out[k.strip()] = float(v)
        except ValueError:
            sep = ""
        if not sep or not k.strip():
            raise InputError(f"expected NAME=AMOUNT[,NAME=AMOUNT], got '{text}'", field="--resources")
    return out


def build_dataset(spec, out, *, client=None, scheduler: str | None = None, workers: int | None = None,
                  retries: int = 2, resources: dict | None = None, progress: bool = True,
                  log=print) -> DatasetResult:
    """Make every sample of ``spec`` in ``out`` (see the module docstring); returns counts and failures.

    ``client``: a ``dask.distributed.Client`` to use; else ``scheduler`` (an address) or a LocalCluster of
    ``workers`` processes; ``workers=0`` runs in this process without Dask. ``resources`` (e.g.
    ``{"GPU": 1}``) is claimed by every task, so workers started with ``--resources GPU=1`` run one at a time.
    """
    from tqdm import tqdm
    t0 = time.perf_counter()
    spec, spec_path = load_spec(spec)
    out = Path(out)
    (out / "samples").mkdir(parents=True, exist_ok=True)
    for stale in (out / "samples").glob(".tmp-*"):  # a killed run's half-written samples
        shutil.rmtree(stale, ignore_errors=True)
    samples = plan(spec)
    rkeys, sids = {}, []
    for s in samples:
        rk = rkeys.setdefault(json.dumps(s.render_request(), sort_keys=True), render_key(s))
        sids.append(sample_id(s, rk))
    rk_of = [rkeys[json.dumps(s.render_request(), sort_keys=True)] for s in samples]
    old = {}
    if (out / MANIFEST).is_file():
        try:
            old = json.loads((out / MANIFEST).read_text()).get("samples", {})
        except (OSError, json.JSONDecodeError):
            old = {}
    records = {}
    for s, sid, rk in zip(samples, sids, rk_of):
        rec = {"index": s.index, "render_key": rk, "params": asdict(s), "status": "pending", "attempts": 0}
        prev = old.get(sid, {})
        rec["attempts"] = int(prev.get("attempts", 0))
        if (out / "samples" / sid / "sample.json").is_file():
            rec["status"] = "done"
            rec["seconds"] = prev.get("seconds")
        records[sid] = rec
    manifest = {"format": DATASET_FORMAT, "version": DATASET_VERSION, "spec": spec,
                "spec_file": str(spec_path) if spec_path else None, "spec_hash": _hash(spec),
                "n_samples": len(samples), "n_renders": len(set(rk_of)), "samples": records,
                "provenance": provenance(stage="dataset")}

    def save():
        manifest["n_done"] = sum(r["status"] == "done" for r in records.values())
        manifest["n_failed"] = sum(r["status"] == "failed" for r in records.values())
        write_json_atomic(out / MANIFEST, manifest)

    save()
    todo = [(s, sid, rk) for s, sid, rk in zip(samples, sids, rk_of) if records[sid]["status"] != "done"]
    n_skipped = len(samples) - len(todo)
    if n_skipped:
        log(f"dataset: {n_skipped} of {len(samples)} samples already done in {out}; making the other {len(todo)}")
    kill_after = int(os.environ.get(KILL_AFTER_ENV, "0") or 0)
    n_made = 0
    bar = tqdm(total=len(samples), initial=n_skipped, desc="dataset", unit="sample", disable=not progress,
               dynamic_ncols=True)

    def record(sid, result=None, error=None, attempts=1):
        nonlocal n_made
        rec = records[sid]
        rec["attempts"] += attempts
        if error is None:
            rec["status"] = "done"
            rec["seconds"] = result.get("seconds")
            rec.pop("error", None)
            n_made += 0 if result.get("skipped") else 1
        else:
            rec["status"] = "failed"
            rec["error"] = f"{type(error).__name__}: {error}"
        save()
        bar.update(1)
        if kill_after and n_made >= kill_after:
            import signal
            os.kill(os.getpid(), signal.SIGKILL)

    own_client = None
    try:
        if client is None and workers == 0 and not scheduler:
            frames_of = {}
            for s, sid, rk in todo:
                last = None
                for attempt in range(retries + 1):
                    try:
                        if rk not in frames_of:
                            frames_of[rk] = render_task(s, rk, str(out))
                        record(sid, sample_task(s, sid, frames_of[rk], str(out)), attempts=attempt + 1)
                        last = None
                        break
                    except Exception as exc:  # noqa: BLE001 - reported in the manifest, never dropped
                        last = exc
                if last is not None:
                    record(sid, error=last, attempts=retries + 1)
        elif todo:
            from dask.distributed import as_completed
            if client is None:
                client = own_client = _client_for(scheduler, workers, resources)
            rfut = {}
            futs, flist = {}, []
            for s, sid, rk in todo:
                if rk not in rfut:
                    rfut[rk] = client.submit(render_task, s, rk, str(out), key=f"render-{rk}", retries=retries,
                                             pure=False, resources=resources)
                f = client.submit(sample_task, s, sid, rfut[rk], str(out), key=f"sample-{sid}", retries=retries,
                                  pure=False, resources=resources)
                futs[f.key] = sid
                flist.append(f)
            for fut in as_completed(flist):
                sid = futs[fut.key]
                if fut.status == "error":
                    record(sid, error=fut.exception(), attempts=retries + 1)
                else:
                    record(sid, fut.result())
    finally:
        bar.close()
        if own_client is not None:
            cluster = getattr(own_client, "cluster", None)
            own_client.close()
            if cluster is not None:
                cluster.close()
    failed = [{"id": sid, "index": r["index"], "error": r.get("error")} for sid, r in records.items()
              if r["status"] == "failed"]
    res = DatasetResult(out, len(samples), sum(r["status"] == "done" for r in records.values()), n_made, n_skipped,
                        failed, time.perf_counter() - t0)
    write_summary(out, manifest, res)
    return res


def write_summary(out: Path, manifest: dict, res: DatasetResult) -> Path:
    """DIR/summary.md: counts, renders, failures with their errors, and how to train on the data."""
    lines = [f"# Dataset `{out}`", "", "| quantity | value |", "|---|---|",
             f"| samples in the spec | {res.n_samples} |", f"| done | {res.n_done} |",
             f"| made in this run | {res.n_made} |", f"| already done (skipped) | {res.n_skipped} |",
             f"| failed | {len(res.failed)} |", f"| renders | {manifest['n_renders']} |",
             f"| spec hash | {manifest['spec_hash']} |", f"| time | {res.seconds:.1f} s |", ""]
    if res.failed:
        lines += ["## Failed samples (rerun the same command to retry them)", ""]
        lines += [f"- sample {f['index']} (`{f['id']}`): {f['error']}" for f in res.failed]
        lines.append("")
    lines += ["Train on it: `render2spike train --data rendered:" + str(out) + " --out RUN` "
              "(add `:spikes=spikes.npz` to use the stored streams).", ""]
    return write_text_atomic(out / "summary.md", "\n".join(lines))


def done_sample_folders(root) -> list[Path]:
    """The finished samples' folders of a dataset, in spec order (for ``rendered:DIR``)."""
    root = Path(root)
    man = json.loads((root / MANIFEST).read_text())
    recs = sorted(man["samples"].items(), key=lambda kv: kv[1]["index"])
    return [root / "samples" / sid for sid, r in recs if r["status"] == "done"]
