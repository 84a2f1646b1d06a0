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

Checks, the folder, the lock
----------------------------
Before anything renders or any folder is made, :func:`load_spec` and
:func:`prepare` check the whole spec (every axis value, duplicates, models,
profiles, each scene variant loaded once with the scene-file validators,
samples that would come out the same), :func:`check_run_options` the
options, :func:`scheduler_address` the scheduler. The output folder is
locked for the run (:class:`sensor.io.lock.FolderLock`); a dataset of another
spec, a foreign ``manifest.json`` or other files are refused unless
``overwrite``. docs/studies.md lists every check.
"""

from __future__ import annotations

import contextlib
import copy
import functools
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
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from sensor.errors import DependencyError, InputError, UnknownMethodError
from sensor.io.fileio import (atomic_path, json_bytes, package_version, provenance, same_or_inside, write_bytes_atomic,
                             write_json_atomic, write_text_atomic)

DATASET_FORMAT = "render2spike-dataset"
DATASET_VERSION = 1
MANIFEST = "manifest.json"
#: environment variable: SIGKILL this process after this many samples were recorded (to test resume)
KILL_AFTER_ENV = "RENDER2SPIKE_DATASET_KILL_AFTER"
#: the brightest light level a spec may ask for [lux] (direct sunlight: about 1e5 lux); far above it the
#: scaled frames overflow float32
MAX_LUX = 1e8
#: the most samples one spec may plan (the manifest lists each)
MAX_SAMPLES = 100_000
#: the most retries of a failed sample, and of LocalCluster worker processes
MAX_RETRIES = 100
MAX_WORKERS = 4 * max(os.cpu_count() or 1, 16)
#: how long a Dask scheduler may take to accept a connection and to answer [s]
SCHEDULER_TIMEOUT_S = 10.0

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
             "properties": {"frames": {"type": "string"}, "profile": {"type": "string"}}},
            {"type": "object", "additionalProperties": False, "required": ["procedural"],
             "properties": {"procedural": {"type": "object", "anyOf": [{"required": ["count"]},
                                                                      {"required": ["index", "seed"]}]},
                            "set": {"type": "array", "items": {"type": "string"}}}}]}},
        "set": {"type": "array", "items": {"type": "string"}},
        # written by load_spec (a loaded spec, e.g. a manifest's, loads again): each scene's entry in the file
        "scene_entries": {"type": "array", "items": {"type": "array"}},
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
def _spec_loader():
    """A safe YAML loader that refuses a key given twice in one mapping (plain YAML keeps the last one)."""
    from render2spike.render.scene import _yaml
    yaml = _yaml()

    class Loader(yaml.SafeLoader):
        pass

    def mapping(loader, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            key = loader.construct_object(key_node, deep=True)
            try:
                dup = key in seen
                seen.add(key)
            except TypeError:  # unhashable: SafeLoader reports it
                continue
            if dup:
                raise yaml.constructor.ConstructorError(None, None, f"the key {key!r} is given twice",
                                                        key_node.start_mark)
        return yaml.SafeLoader.construct_mapping(loader, node, deep)

    Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, mapping)
    return Loader


def read_spec_file(path) -> dict:
    """The mapping a spec file holds; one-line errors for a missing, unreadable or malformed file."""
    path = Path(path)
    if not path.exists():
        raise InputError("dataset spec not found", path=path)
    if path.is_dir():
        raise InputError("is a folder; give a dataset spec file (YAML or JSON)", path=path)
    try:
        text = path.read_bytes().decode("utf-8")
    except OSError as exc:
        raise InputError(f"cannot read the dataset spec ({exc.strerror or exc})", path=path) from None
    except UnicodeDecodeError:
        raise InputError("not a text file; a dataset spec is YAML or JSON", path=path) from None
    try:
        spec = _spec_loader()(text).get_single_data()
    except Exception as exc:  # noqa: BLE001 - any parser error is the file's fault
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or str(exc).strip().splitlines()[-1:] or [type(exc).__name__]
        problem = problem if isinstance(problem, str) else problem[0]
        raise InputError(f"not valid YAML{where}: {' '.join(problem.split())}", path=path) from None
    if spec is None:
        raise InputError("the dataset spec is empty; it needs at least 'scenes'", path=path)
    return spec


def load_spec(spec) -> tuple[dict, Path | None]:
    """Read (a path) or take (a dict) a dataset spec, check it, fill defaults. Returns (spec, its path).

    Checks everything that needs no scene file: the schema, each axis value (``lux`` and ``duration_s`` finite
    and > 0, parameters finite, ranges low < high), no value twice in an axis, known models and resets, known
    profiles (bundled names or files), scene files and frames folders that exist. :func:`prepare` checks the
    rest (each scene with its overrides) before anything renders.
    """
    path = None
    if not isinstance(spec, dict):
        path = Path(spec)
        spec = read_spec_file(path)
    if not isinstance(spec, dict):
        raise InputError(f"a dataset spec must be a mapping of keys, got {type(spec).__name__}", path=path)
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
    _check_values(out, path)
    from render2spike.studies.common import parse_model_spec
    labels = {}
    for i, m in enumerate(out["models"]):
        try:
            name, reset = parse_model_spec(m)
        except (InputError, UnknownMethodError) as exc:
            raise InputError(str(exc), path=path, field=f"models.{i}") from None
        label = name if reset is None else f"{name}:{reset}"
        if label in labels:
            raise InputError(f"'{m}' is listed twice (models.{labels[label]} is the same model)", path=path,
                             field=f"models.{i}")
        labels[label] = i
    for i, p in enumerate(out["profiles"]):
        _check_profile_name(p, path, f"profiles.{i}", allow_scene=True)
    from render2spike.render.scene import resolve_scene_path
    base = path.parent if path else Path.cwd()
    seen = {}
    out["scenes"], out["scene_entries"] = _expand_procedural(out["scenes"], path, out.get("duration_s"),
                                                            out.get("scene_entries"))
    for i, sc in enumerate(out["scenes"]):
        if isinstance(sc, dict) and "procedural" in sc:
            ident = json.dumps(sc, sort_keys=True)
            _check_sets(sc["set"], path, f"{_entry(out, i)}.set")
        elif isinstance(sc, dict) and "frames" in sc:
            f = Path(sc["frames"])
            f = f if f.is_absolute() else base / f
            _check_frames_source(f, path, f"{_entry(out, i)}.frames")
            sc["frames"] = str(f.resolve())
            if sc.get("profile") is not None:
                _check_profile_name(sc["profile"], path, f"{_entry(out, i)}.profile", allow_scene=False)
            ident = json.dumps(sc, sort_keys=True)
        else:
            name = sc["scene"] if isinstance(sc, dict) else sc
            if not name.strip():
                raise InputError("expected a scene name or file, got ''", path=path, field=_entry(out, i))
            cand = Path(name) if Path(name).is_absolute() else base / name
            try:
                resolved = resolve_scene_path(cand if cand.is_file() else name)
            except InputError as exc:
                raise InputError(str(exc), path=path, field=_entry(out, i)) from None
            sets = list(sc.get("set", [])) if isinstance(sc, dict) else []
            _check_sets(sets, path, f"{_entry(out, i)}.set")
            out["scenes"][i] = {"scene": str(resolved.resolve()), "set": sets}
            ident = json.dumps(out["scenes"][i], sort_keys=True)
        if ident in seen:
            raise InputError(f"{_entry_text(out, seen[ident])} is the same scene with the same overrides as "
                             f"{_entry_text(out, i)}; list each once", path=path, field=_entry(out, i))
        seen[ident] = i
    frames_sources = [i for i, sc in enumerate(out["scenes"]) if "frames" in sc]
    if frames_sources:
        fixed = [k for k in ("duration_s",) if out.get(k) is not None] + (["params"] if out["params"] else []) + \
                (["set"] if out["set"] else [])
        if fixed:
            raise InputError(f"'{fixed[0]}' changes renders, but {_entry(out, frames_sources[0])} is a folder of frames "
                             "already rendered: its samples would repeat; put frames folders in a spec without "
                             f"'{fixed[0]}'", path=path, field=fixed[0])
    return out, path


def _entry(spec: dict, i: int) -> str:
    """The spec key of scene ``i`` of the loaded (expanded) list: ``scenes.E``, E its entry in the spec file."""
    ent = spec.get("scene_entries")
    return f"scenes.{ent[i][0] if ent else i}"


def _entry_text(spec: dict, i: int) -> str:
    """:func:`_entry`, with the generated scene's number for a procedural entry."""
    ent = spec.get("scene_entries")
    k = ent[i][1] if ent else None
    return _entry(spec, i) + ("" if k is None else f" (generated scene {k})")


def _longest(duration) -> float | None:
    """The longest clip a ``duration_s`` axis asks for [s] (a value, a list or a range), or None."""
    if duration is None:
        return None
    if isinstance(duration, dict):
        return float(max(next(iter(duration.values()))))
    return float(max(duration)) if isinstance(duration, list) else float(duration)


def _expand_procedural(scenes: list, path, duration=None, prior: list | None = None) -> tuple[list, list]:
    """The spec's scenes with each ``{procedural: {count: N, seed: S, ...}}`` entry replaced by its N generated
    scenes (:mod:`render2spike.scenegen`), each ``{procedural: {seed, index, options}, set}``, and for each
    scene ``[entry, generated index or None]`` (errors name the entry). The options are checked here (errors
    name ``scenes.E.procedural.KEY``); without ``duration_s`` of their own they take the spec's longest clip
    (``duration``), which sizes the background for a panning camera. Workers generate each scene again from its
    seed, index and options. A loaded spec's scenes (already expanded: ``index`` instead of ``count``) stay, with
    its ``prior`` entries."""
    from render2spike.scenegen import check_options
    out, entries = [], []
    if prior is not None and len(prior) != len(scenes):
        raise InputError(f"scene_entries has {len(prior)} items for {len(scenes)} scenes", path=path,
                         field="scene_entries")
    for i, sc in enumerate(scenes):
        if not (isinstance(sc, dict) and "procedural" in sc and "count" in sc["procedural"]):
            out.append(sc)
            k = sc["procedural"]["index"] if isinstance(sc, dict) and "procedural" in sc else None
            entries.append(list(prior[i]) if prior is not None else [i, k])
            continue
        opts = dict(sc["procedural"])
        count, seed = opts.pop("count"), opts.pop("seed", 0)
        longest = _longest(duration)
        if longest is not None and "duration_s" not in opts:
            opts["duration_s"] = longest
        for key, v, most in (("count", count, MAX_SAMPLES), ("seed", seed, 2 ** 32 - 1)):
            if not (isinstance(v, int) and not isinstance(v, bool) and (v >= 1 if key == "count" else v >= 0)
                    and v <= most):
                raise InputError(f"must be an integer {'>= 1' if key == 'count' else '>= 0'} and <= {most}; got "
                                 f"{v!r}", path=path, field=f"scenes.{i}.procedural.{key}")
        try:
            checked = check_options(opts)
        except InputError as exc:
            text = str(exc).split(": ", 1)[1] if exc.field else str(exc)  # without its "field '...'" prefix
            raise InputError(text, path=path, field=f"scenes.{i}.{exc.field or 'procedural'}") from None
        given = {k: checked[k] for k in sorted(opts)}
        out.extend({"procedural": {"seed": int(seed), "index": k, "options": given}, "set": list(sc.get("set", []))}
                   for k in range(count))
        entries.extend([i, k] for k in range(count))
    return out, entries


def _scene_arg(source: dict):
    """What :func:`render2spike.render.scene.load_scene` takes for a spec scene: its file, or the generated
    scene mapping of a procedural one."""
    if "procedural" in source:
        from render2spike.scenegen import generate_scene
        g = source["procedural"]
        return generate_scene(int(g["seed"]), int(g["index"]), g.get("options"))
    return source["scene"]


def _check_sets(sets, path, where: str) -> None:
    """KEY=VALUE overrides: each with a key, no key twice."""
    keys = {}
    for j, item in enumerate(sets):
        key, sep, _ = str(item).partition("=")
        key = key.strip()
        if not sep or not key:
            raise InputError(f"expected KEY=VALUE (e.g. render.spp=16), got '{item}'", path=path, field=f"{where}.{j}")
        if key in keys:
            raise InputError(f"'{key}' is set twice ({where}.{keys[key]} sets it too)", path=path,
                             field=f"{where}.{j}")
        keys[key] = j


def _check_profile_name(name, path, where: str, allow_scene: bool) -> None:
    """A profile entry must be `scene` (where allowed), a bundled profile name or an existing profile file."""
    from sensor.profile import DATA_DIR, bundled_profiles
    name = str(name)
    if allow_scene and name == "scene":
        return
    p = Path(name)
    if name.strip() and (p.is_file() or (DATA_DIR / f"{name}.npz").is_file()):
        return
    if p.is_dir():
        raise InputError(f"'{name}' is a folder, not a profile file (.npz)", path=path, field=where)
    scene = "'scene' (the scene's own camera), " if allow_scene else ""
    raise InputError(f"unknown profile '{name}': expected {scene}a bundled profile ({', '.join(bundled_profiles())}) "
                     "or a profile file", path=path, field=where)


def _check_frames_source(folder: Path, path, where: str) -> None:
    """A frames folder used as a source: its manifest readable, with the light level it was rendered at."""
    man_path = folder / "frames.json"
    if not man_path.is_file():
        raise InputError(f"no frames.json in {folder}", path=path, field=where)
    try:
        man = json.loads(man_path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{man_path} is not a readable frames manifest ({exc})", path=path, field=where) from None
    if not isinstance(man, dict) or not isinstance(man.get("frames"), list) or len(man["frames"]) < 2:
        raise InputError(f"{man_path} lists fewer than two frames (a clip needs at least two)", path=path, field=where)
    for key in ("height", "width"):
        v = man.get(key)
        if not isinstance(v, int) or isinstance(v, bool) or v < 1:
            raise InputError(f"{man_path}: '{key}' must be a whole number >= 1, got {v!r}", path=path, field=where)
    for j, f in enumerate(man["frames"]):
        t = f.get("time_s") if isinstance(f, dict) else None
        if not isinstance(t, (int, float)) or isinstance(t, bool) or not np.isfinite(t):
            raise InputError(f"{man_path}: frames.{j} has no finite time_s", path=path, field=where)
    times = [float(f["time_s"]) for f in man["frames"]]
    if max(times) <= min(times):
        raise InputError(f"{man_path}: the frames span no time (every time_s is {times[0]!r})", path=path, field=where)
    lux = man.get("illuminance_lux", man.get("target_lux"))
    if not isinstance(lux, (int, float)) or isinstance(lux, bool) or not np.isfinite(lux) or lux <= 0:
        raise InputError(f"{man_path} does not say at which illuminance the frames were rendered "
                         f"(illuminance_lux: {lux!r}); the lux axis scales from it", path=path, field=where)


def _number_text(x) -> str:
    return repr(x) if isinstance(x, float) else str(x)


def _check_axis(value, path, key: str, positive: bool, most: float | None = None) -> None:
    """One axis: finite numbers (> 0 where ``positive``, at most ``most``), no value twice; ranges with
    low < high."""
    need = ("a finite number > 0" if positive else "a finite number") + (f" and at most {most:g}" if most else "")

    def bad(x) -> bool:
        return not np.isfinite(x) or (positive and x <= 0) or (most is not None and x > most)

    if isinstance(value, dict):
        (kind, pair), = value.items()
        for j, x in enumerate(pair):
            if bad(x):
                raise InputError(f"expected {need}, got {_number_text(x)}", path=path, field=f"{key}.{kind}.{j}")
        if not pair[0] < pair[1]:
            raise InputError(f"a range needs [low, high] with low < high, got {pair}", path=path,
                             field=f"{key}.{kind}")
        return
    seen = {}
    for j, x in enumerate(_values(value)):
        where = f"{key}.{j}" if isinstance(value, list) else key
        if bad(x):
            raise InputError(f"expected {need}, got {_number_text(x)}", path=path, field=where)
        if float(x) in seen:
            raise InputError(f"{_number_text(x)} is listed twice ({key}.{seen[float(x)]}); list each value once",
                             path=path, field=where)
        seen[float(x)] = j


def _check_values(spec: dict, path) -> None:
    """The axis values, overrides, parameter names and seeds of a spec with its defaults filled."""
    for key in ("duration_s", "lux"):
        if spec.get(key) is not None:
            _check_axis(spec[key], path, key, positive=True, most=MAX_LUX if key == "lux" else None)
    _check_sets(spec["set"], path, "set")
    set_keys = {str(s).partition("=")[0].strip() for s in spec["set"]}
    for k, v in spec["params"].items():
        if not k.strip() or "=" in k or k != k.strip():
            raise InputError(f"'{k}' is not a scene key (a dotted path such as camera.f_number) or a named scene "
                             "parameter", path=path, field="params")
        if k in ("duration_s", "illuminance_lux"):
            axis = "lux" if k == "illuminance_lux" else k
            raise InputError(f"use the spec's own '{axis}' axis for {k}", path=path, field=f"params.{k}")
        if k in set_keys:
            raise InputError(f"'{k}' is both a parameter axis and fixed in 'set'; keep one", path=path,
                             field=f"params.{k}")
        _check_axis(v, path, f"params.{k}", positive=False)
    seeds = spec.get("seeds")
    if isinstance(seeds, list):
        seen = {}
        for j, x in enumerate(seeds):
            if x in seen:
                raise InputError(f"seed {x} is listed twice (seeds.{seen[x]}); list each seed once", path=path,
                                 field=f"seeds.{j}")
            seen[x] = j
    for j, p in enumerate(spec["profiles"]):
        if p in spec["profiles"][:j]:
            raise InputError(f"'{p}' is listed twice (profiles.{spec['profiles'].index(p)}); list each once",
                             path=path, field=f"profiles.{j}")


_ONE_OF_TEXT = {
    "duration_s": "a number, a list of numbers or (mode: random) {uniform: [a, b]} or {log_uniform: [a, b]}",
    "lux": "a number, a list of numbers or (mode: random) {uniform: [a, b]} or {log_uniform: [a, b]}",
    "params": "a number, a list of numbers or (mode: random) {uniform: [a, b]} or {log_uniform: [a, b]}",
    "profiles": "a name or a list of names", "models": "a name or a list of names",
    "seeds": "a whole number >= 0 or a list of them",
    "scenes": "a scene name or file, {scene: NAME, set: [KEY=VALUE, ...]} or {frames: DIR, profile: NAME}",
}


def _spec_error(err):
    """(message, field) of a jsonschema error; for a value that fits none of a key's forms, the problem within
    the form it comes closest to (the form of its type with the fewest problems), else what the forms are."""
    from render2spike.render.scene import _describe, _error_path
    if err.validator == "oneOf" and err.context:
        branches = {}
        for sub in err.context:
            branches.setdefault(sub.schema_path[0], []).append(sub)
        fitting = [b for b in branches.values() if not any(e.validator == "type" and not e.relative_path for e in b)]
        if fitting:
            best = min(fitting, key=len)
            sub = max(best, key=lambda e: len(e.relative_path))
            return _describe(sub), _error_path(sub)
        where = _error_path(err)
        top = where.split(".")[0]
        if top in _ONE_OF_TEXT:
            return f"expected {_ONE_OF_TEXT[top]}, got {err.instance!r}", where
    return _describe(err), _error_path(err)


def validate_spec(spec: dict, path=None) -> None:
    """jsonschema check of a dataset spec; errors name the key."""
    try:
        import jsonschema
    except ImportError as exc:  # pragma: no cover
        raise DependencyError("jsonschema is not installed: pip install jsonschema") from exc
    v = jsonschema.Draft202012Validator(SPEC_SCHEMA)
    errs = sorted(v.iter_errors(spec), key=lambda e: (len(list(e.absolute_path)), str(e.message)))
    if errs:
        msg, where = _spec_error(errs[0])
        raise InputError(msg if len(msg) <= 300 else msg[:297] + "...", path=path, field=where)


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


def _grid_axes(spec: dict) -> list[tuple[str, list]]:
    """(name, values) of each axis of a grid, in plan order."""
    seeds = spec.get("seeds")
    return [("scenes", spec["scenes"]), ("duration_s", _values(spec.get("duration_s"))),
            ("lux", _values(spec.get("lux")))] + \
        [(f"params.{k}", _values(v)) for k, v in sorted(spec["params"].items())] + \
        [("profiles", spec["profiles"]), ("models", spec["models"]), ("seeds", _values(seeds if seeds is not None
                                                                                        else 0))]


_FIELDS = tuple(f.name for f in fields(SampleSpec))


def describe_plan(spec: dict) -> tuple[int, str]:
    """(number of samples, what they are) of a loaded spec, without planning them."""
    if spec["mode"] == "random":
        n = int(spec["samples"])
        return n, f"{n} samples drawn at random (seed {spec['seed']}) from {len(spec['scenes'])} scene(s)"
    n, parts = 1, []
    for name, vals in _grid_axes(spec):
        n *= len(vals)
        if vals != [None] and (len(vals) > 1 or name in ("scenes", "lux", "models", "seeds")):
            parts.append(f"{len(vals)} {name.removeprefix('params.')}")
    return n, f"{n} samples = " + " x ".join(parts)


def plan(spec: dict) -> list[SampleSpec]:
    """The samples of a (loaded) spec, in a fixed order."""
    params = sorted(spec["params"].items())
    seeds = spec.get("seeds")
    common = dict(window=int(spec["window"]), centers=int(spec["centers"]), preroll=int(spec["preroll"]))
    out = []
    if spec["mode"] == "grid":
        axes = [vals for _, vals in _grid_axes(spec)]
        # the parameters' overrides, made once per value
        axes[3:3 + len(params)] = [[f"{k}={v!r}" for v in _values(vals)] for k, vals in params]
        base = tuple(spec["set"])
        for i, combo in enumerate(itertools.product(*axes)):
            src, dur, lux = combo[:3]
            prof, model, seed = combo[3 + len(params):]
            out.append(SampleSpec(i, src, base + combo[3:3 + len(params)], None if dur is None else float(dur),
                                  None if lux is None else float(lux), str(prof), str(model), int(seed), **common))
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


def _load_source_scene(s: SampleSpec, cache: dict | None = None):
    from render2spike.render.scene import load_scene
    try:
        return load_scene(_scene_arg(s.source), list(s.source.get("set", [])) + list(s.sets),
                          duration_s=s.duration_s, cache=cache)
    except InputError as exc:
        raise InputError(f"sample {s.index}: {exc}", field="scenes") from None


def _frames_key(folder, man_bytes: bytes) -> str:
    """Content hash of a frames folder: its manifest and every frame file it lists (their bytes), so two
    folders of the same manifest but other pixels are two renders."""
    h = hashlib.sha256(man_bytes)
    for f in json.loads(man_bytes).get("frames", []):
        fp = Path(folder) / str(f.get("file", ""))
        h.update(fp.name.encode())
        if fp.is_file():
            with open(fp, "rb") as fh:
                for chunk in iter(lambda: fh.read(1 << 22), b""):
                    h.update(chunk)
    return "f" + h.hexdigest()[:15]


def render_key(s: SampleSpec) -> str:
    """Content hash of what the frames depend on (scene data and files, overrides, duration; not the lux)."""
    if "frames" in s.source:
        folder = Path(s.source["frames"])
        return _frames_key(folder, (folder / "frames.json").read_bytes())
    return _load_source_scene(s).content_hash({"dataset_render": 1})


@functools.lru_cache(maxsize=4096)
def _json_text(x) -> str:
    return json.dumps(x)


def sample_id(s: SampleSpec, rkey: str) -> str:
    """The sample's id: a hash of its render key and its own parameters (not its index or how it was listed).

    The hash of ``{"format", "render", "sample": {centers, lux, model, preroll, profile, seed, window}}`` as
    ``json.dumps(..., sort_keys=True)`` writes it, the text put together directly (a large plan has many).
    """
    lux = "null" if s.lux is None else repr(float(s.lux))
    text = (f'{{"format": {DATASET_VERSION}, "render": {_json_text(rkey)}, "sample": {{"centers": {int(s.centers)}, '
            f'"lux": {lux}, "model": {_json_text(s.model)}, "preroll": {int(s.preroll)}, '
            f'"profile": {_json_text(s.profile)}, "seed": {int(s.seed)}, "window": {int(s.window)}}}}}')
    return hashlib.sha256(text.encode()).hexdigest()[:16]


# ------------------------------------------------------------------------------------------------ the check
@dataclass(frozen=True)
class _Render:
    """What planning learnt of one render request: its key, frame size, and the camera its scene names."""

    key: str
    shape: tuple
    camera_profile: object  # the profile spec of the scene's camera / frames (str, dict or None)
    span_s: float           # the time the frames span [s]


@dataclass
class Plan:
    """A checked spec: its samples, each one's render key and id, and what the plan makes."""

    samples: list
    render_keys: list
    ids: list
    n_renders: int
    description: str


def _axis_field(spec: dict, key: str, value) -> str:
    """The spec key of ``value`` on the axis ``key`` (``lux.2``; the axis itself for a scalar or a range)."""
    axis = spec["params"][key[7:]] if key.startswith("params.") else spec.get(key)
    if isinstance(axis, list):
        for j, v in enumerate(axis):
            if float(v) == float(value):
                return f"{key}.{j}"
    return key


def _scene_error(s: SampleSpec, spec: dict, path, cache: dict, exc: Exception) -> InputError:
    """The spec key behind a scene that failed to load: try the scene, then each value of ``s`` on its own."""
    from render2spike.render.scene import load_scene
    i = next(j for j, sc in enumerate(spec["scenes"]) if sc == s.source)
    own = list(s.source.get("set", []))
    n_common = len(spec["set"])
    tries = [(_entry(spec, i), own, None, None), ("set", own + list(spec["set"]), None, None)]
    if s.duration_s is not None:
        tries.append((_axis_field(spec, "duration_s", s.duration_s), own + list(spec["set"]), s.duration_s,
                      f"duration_s={s.duration_s!r}"))
    for item in s.sets[n_common:]:
        k, _, v = item.partition("=")
        tries.append((_axis_field(spec, f"params.{k}", float(v)), own + list(spec["set"]) + [item], None, item))
    for where, sets, dur, what in tries:
        try:
            load_scene(_scene_arg(s.source), sets, duration_s=dur, cache=cache)
        except Exception as e2:  # noqa: BLE001 - reported with the key that caused it
            text = str(e2) if isinstance(e2, InputError) else f"{type(e2).__name__}: {e2}"
            if where == "set" and isinstance(e2, InputError) and e2.field:
                j = next((j for j, it in enumerate(spec["set"]) if it.partition("=")[0].strip() == e2.field), None)
                where = where if j is None else f"set.{j}"
            return InputError(text if what is None else f"{what} does not give a valid scene: {text}", path=path,
                              field=where)
    text = str(exc) if isinstance(exc, InputError) else f"{type(exc).__name__}: {exc}"
    what = ", ".join([f"duration_s={s.duration_s!r}"] * (s.duration_s is not None) + list(s.sets[n_common:]))
    return InputError(f"{_entry_text(spec, i)} with {what}: {text}", path=path, field=_entry(spec, i))


def _inspect_render(s: SampleSpec, spec: dict, path, cache: dict) -> _Render:
    """Load what sample ``s`` renders (once per distinct render request), with errors naming the spec key."""
    if "frames" in s.source:
        man_bytes = (Path(s.source["frames"]) / "frames.json").read_bytes()
        man = json.loads(man_bytes)
        key = _frames_key(s.source["frames"], man_bytes)
        times = [float(f["time_s"]) for f in man["frames"]]
        return _Render(key, (int(man["height"]), int(man["width"])),
                       s.source.get("profile") or (man.get("profile") or {}).get("spec"), max(times) - min(times))
    try:
        sc = _load_source_scene(s, cache)
    except Exception as exc:  # noqa: BLE001 - reported with the key that caused it
        raise _scene_error(s, spec, path, cache, exc) from None
    if sc.duration_s < sc.profile.interval_s:
        where = _axis_field(spec, "duration_s", s.duration_s) if s.duration_s is not None else \
            _entry(spec, next(j for j, x in enumerate(spec['scenes']) if x == s.source))
        raise InputError(f"a clip of {sc.duration_s!r} s is shorter than one interval of the camera "
                         f"({sc.profile.interval_s!r} s)", path=path, field=where)
    return _Render(sc.content_hash({"dataset_render": 1}), (sc.profile.height, sc.profile.width),
                   sc.data["camera"]["profile"], sc.duration_s)


def _check_sensor(s: SampleSpec, r: _Render, spec: dict, path, profiles: dict) -> None:
    """The sensor sample ``s`` simulates: its profile loads, covers the frames, and takes the model's reset."""
    from render2spike.render.scene import build_profile
    from sensor.models.spec import parse_model_spec
    from sensor.profile import SensorProfile
    from sensor.rates import n_intervals_spanned
    i = next(j for j, x in enumerate(spec["scenes"]) if x == s.source)
    if s.profile == "scene":
        where = _entry(spec, i) + (".profile" if "frames" in s.source else "")
        base = r.camera_profile
        if base is None:
            raise InputError(f"the frames in {s.source['frames']} do not say which sensor they were rendered for; "
                             "give 'profile' next to 'frames', or 'profiles' other than 'scene'", path=path,
                             field=where)
    else:
        where = f"profiles.{spec['profiles'].index(s.profile)}"
        base = s.profile
    pkey = json.dumps(base, sort_keys=True, default=str)
    try:
        if pkey not in profiles:
            profiles[pkey] = SensorProfile.load(base) if isinstance(base, str) else build_profile(base)
        prof = profiles[pkey].centred(*r.shape)
    except InputError as exc:
        raise InputError(str(exc), path=path, field=where) from None
    n_intervals = n_intervals_spanned(0.0, r.span_s, prof.interval_s)
    if s.centers > n_intervals:
        raise InputError(f"{s.centers} window centres in a clip of {n_intervals} intervals ({_entry_text(spec, i)}); at most one "
                         "per interval", path=path, field="centers")
    try:
        parse_model_spec(s.model).profile(prof)
    except (InputError, UnknownMethodError) as exc:
        raise InputError(f"{s.model} with profile {prof.name}: {exc}", path=path,
                         field=f"models.{spec['models'].index(s.model)}") from None


def prepare(spec: dict, path=None, log=print) -> Plan:
    """Plan a loaded spec and check every sample before anything renders (see :func:`load_spec`).

    Each distinct scene variant (scene, overrides, parameters, duration) is loaded and checked once, each
    scene file read once; each sensor (profile x frame size x model) is built once. Errors name the spec file
    and key. Refuses a plan of more than :data:`MAX_SAMPLES` samples, and two samples that come out the same.
    """
    n, text = describe_plan(spec)
    if n > MAX_SAMPLES:
        axes = f" ({text.split(' = ', 1)[1]})" if " = " in text else ""
        raise InputError(f"the spec makes {n:,} samples{axes}; a dataset holds at most "
                         f"{MAX_SAMPLES:,} (its manifest lists each): split it into several specs", path=path,
                         field="samples" if spec["mode"] == "random" else None)
    if n > 1000:
        log(f"dataset: planning {text}; checking every sample before anything renders")
    samples = plan(spec)
    src_keys = {}
    requests = []
    for s in samples:
        sk = src_keys.get(id(s.source))
        if sk is None:
            sk = src_keys[id(s.source)] = json.dumps(s.source, sort_keys=True)
        requests.append((sk, s.sets, s.duration_s))
    distinct = dict.fromkeys(requests)
    if len(distinct) > 50:
        log(f"dataset: checking {len(distinct)} scene variants before rendering")
    cache, renders = {}, {}
    for s, req in zip(samples, requests):
        if renders.get(req) is None:
            renders[req] = _inspect_render(s, spec, path, cache)
    rinfo = [renders[req] for req in requests]
    profiles, sensors, cam = {}, set(), {}
    for s, r in zip(samples, rinfo):
        ck = cam.get(id(r))
        if ck is None:
            ck = cam[id(r)] = json.dumps(r.camera_profile, sort_keys=True, default=str)
        key = (r.shape, s.profile, ck, s.model, r.span_s, s.centers)
        if key not in sensors:
            _check_sensor(s, r, spec, path, profiles)
            sensors.add(key)
    rkeys = [r.key for r in rinfo]
    ids = [sample_id(s, rk) for s, rk in zip(samples, rkeys)]
    first = {}
    for s, sid in zip(samples, ids):
        j = first.setdefault(sid, s.index)
        if j != s.index:
            if spec["mode"] == "random":
                raise InputError(f"draws {j} and {s.index} give the same sample: draw from ranges "
                                 "({uniform: [a, b]}), from longer lists, or fewer samples", path=path, field="samples")
            src = [next(k for k, x in enumerate(spec["scenes"]) if x == t.source) for t in (samples[j], s)]
            if src[0] != src[1]:
                raise InputError(f"{_entry_text(spec, src[0])} and {_entry_text(spec, src[1])} give the same samples "
                                 "(the same frames or scene once overrides apply, with the same sensor): list it "
                                 "once", path=path, field=_entry(spec, src[1]))
            raise InputError(f"samples {j} and {s.index} of the grid come out the same (overrides that change "
                             "nothing): list each value once", path=path, field=_entry(spec, src[1]))
    n_renders = len(set(rkeys))
    return Plan(samples, rkeys, ids, n_renders, f"{text}; {n_renders} render(s)")


# ------------------------------------------------------------------------------------------------ the tasks
def render_task(s: SampleSpec, rkey: str, out_root: str) -> str:
    """Render (or find) the frames of ``s``'s scene; returns the frames folder. Idempotent."""
    if "frames" in s.source:
        return s.source["frames"]
    from render2spike.render.job import render_scene
    folder = Path(out_root) / "renders" / rkey
    with _RENDER_LOCK:
        sc = _load_source_scene(s)
        if "procedural" in s.source and sc.content_hash({"dataset_render": 1}) != rkey:
            raise RuntimeError(f"this worker generates another scene for {s.source['procedural']} than the planner "
                               f"did (render key {rkey}): its numpy {np.__version__} or render2spike differs; run the "
                               "workers with the planner's versions")
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
    """Make sample ``sid`` (simulate, store spikes, truth, frames, metadata) unless it exists. Idempotent.

    -> ``{"id", "status", "skipped", "seconds"}`` and, for a sample made here, ``"timing"``: seconds per stage
    (``read``: the frames read back; ``simulate``: photoelectron rate and spikes; ``truth``: the clean images
    and window averages; ``write``: the sample's files), each measured with :func:`time.perf_counter`, their
    sum at most ``seconds`` (the rest: imports, the profile, the checks).
    """
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
    clock = time.perf_counter()
    timing = {"read": 0.0, "simulate": 0.0, "truth": 0.0, "write": 0.0}

    def lap(stage: str) -> None:  # the time since the last lap goes to ``stage``
        nonlocal clock
        now = time.perf_counter()
        timing[stage] += now - clock
        clock = now

    fs = read_frames(frames_folder)
    lap("read")
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
    clock = time.perf_counter()  # the profile's set-up above is in none of the stages
    phi = fs.phi_stack().astype(np.float32) * scale
    t = np.asarray(fs.times_s, np.float64)
    lap("read")
    rate = photoelectron_rate(phi, prof).astype(np.float32)
    spikes = simulate_clip(rate, t, prof, s.model, s.seed, s.preroll)
    T = spikes.shape[0]
    lap("simulate")
    centers = window_centers(T, min(s.window, T), s.centers)
    clean = np.stack([clean_image(rate, t, c, prof) for c in centers])
    avg = np.stack([clean_window_average(rate, t, c, min(s.window, T), prof) for c in centers])
    lap("truth")

    tmp = final.parent / f".tmp-{sid}-{uuid.uuid4().hex[:8]}"
    tmp.mkdir(parents=True)
    try:
        lux_frames = None
        try:
            lux_frames = np.stack([fs.read(i).illuminance_lux for i in range(len(fs))]).astype(np.float32) * scale
        except Exception:  # frames without an E channel
            lux_frames = None
        lap("read")
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
        lap("write")
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return {"id": sid, "status": "done", "skipped": False, "seconds": time.perf_counter() - t0, "timing": timing}


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


def check_run_options(workers=None, retries=2, resources=None, scheduler=None, client=None) -> None:
    """``workers``, ``retries``, ``resources`` and their combinations; one-line errors naming the option."""
    if workers is not None:
        if isinstance(workers, bool) or not isinstance(workers, int) or workers < 0:
            raise InputError(f"expected 0 (run here, without Dask) or a number of worker processes >= 1, got "
                             f"{workers!r}", field="--workers")
        if workers > MAX_WORKERS:
            raise InputError(f"{workers} worker processes is more than this tool starts on one machine "
                             f"({MAX_WORKERS}); use --scheduler for a cluster", field="--workers")
    if isinstance(retries, bool) or not isinstance(retries, int) or not 0 <= retries <= MAX_RETRIES:
        raise InputError(f"expected a whole number of retries from 0 to {MAX_RETRIES}, got {retries!r}",
                         field="--retries")
    for k, v in (resources or {}).items():
        if not np.isfinite(v) or v <= 0:
            raise InputError(f"resource '{k}' needs a finite amount > 0, got {v!r}", field="--resources")
    if scheduler is not None and not str(scheduler).strip():
        raise InputError("expected a scheduler address (tcp://HOST:PORT), got ''", field="--scheduler")
    if scheduler is not None and workers is not None:
        raise InputError("--workers starts a cluster on this machine; with --scheduler the cluster's own workers "
                         "run the samples: give one of the two", field="--workers")
    if resources and workers == 0 and scheduler is None and client is None:
        raise InputError("--workers 0 runs the samples in this process, where Dask resources do not apply; give "
                         "--workers N or --scheduler", field="--resources")


def parse_resources(text) -> dict | None:
    """``GPU=1,MEM=4e9`` -> {"GPU": 1.0, "MEM": 4e9} (Dask worker resources each task claims)."""
    if text is None:
        return None
    out = {}
    for tok in str(text).split(","):
        k, sep, v = tok.partition("=")
        try:
            amount = float(v)
        except ValueError:
            sep = ""
        if not sep or not k.strip():
            raise InputError(f"expected NAME=AMOUNT[,NAME=AMOUNT], got '{text}'", field="--resources")
        if k.strip() in out:
            raise InputError(f"'{k.strip()}' is given twice in '{text}'", field="--resources")
        if not np.isfinite(amount) or amount <= 0:
            raise InputError(f"'{k.strip()}' needs a finite amount > 0, got '{v}'", field="--resources")
        out[k.strip()] = amount
    return out


def check_scheduler(address: str, timeout_s: float | None = None) -> str:
    """The address of a Dask scheduler that accepts connections (``tcp://HOST:PORT``; a bare HOST:PORT is tcp).

    Refused in one line: a malformed address, a host that does not resolve, nothing listening, no answer
    within ``timeout_s`` (default :data:`SCHEDULER_TIMEOUT_S`).
    """
    import socket
    timeout_s = SCHEDULER_TIMEOUT_S if timeout_s is None else timeout_s
    text = str(address).strip()
    scheme, sep, rest = text.partition("://")
    if not sep:
        scheme, rest = "tcp", text
    form = f"expected tcp://HOST:PORT (e.g. tcp://head-node:8786), got '{address}'"
    if scheme not in ("tcp", "tls"):
        raise InputError(f"unsupported scheme '{scheme}://'; {form}", field="--scheduler")
    host, sep, port = rest.rstrip("/").rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if not sep or not host or not port.isdigit() or not 1 <= int(port) <= 65535 or "/" in host:
        raise InputError(form, field="--scheduler")
    try:
        with socket.create_connection((host, int(port)), timeout=timeout_s):
            pass
    except socket.gaierror:
        raise InputError(f"cannot resolve the host '{host}' of {text}", field="--scheduler") from None
    except ConnectionRefusedError:
        raise InputError(f"nothing listens at {text} (connection refused): start the scheduler "
                         "(`dask scheduler`) or check the address", field="--scheduler") from None
    except (socket.timeout, TimeoutError):
        raise InputError(f"no answer from {text} within {timeout_s:g} s (host down, unreachable or behind a "
                         "firewall)", field="--scheduler") from None
    except OSError as exc:
        raise InputError(f"cannot connect to {text}: {exc.strerror or exc}", field="--scheduler") from None
    return f"{scheme}://{rest}"


def _dask():
    try:
        import dask.distributed
    except ImportError as exc:
        raise DependencyError("datasets run on Dask: pip install 'dask[distributed]'") from exc
    return dask.distributed


@contextlib.contextmanager
def _quiet_dask():
    """Dask's own log lines muted (a peer that is no scheduler makes Dask log, and raise, strange things)."""
    import logging
    quiet = logging.getLogger("distributed")
    level = quiet.level
    quiet.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        quiet.setLevel(level)


def scheduler_address(scheduler: str) -> str:
    """The address of the Dask scheduler ``scheduler`` names, after checking that a scheduler answers there
    (:func:`check_scheduler`, then Dask's ``identity``), each within :data:`SCHEDULER_TIMEOUT_S`."""
    _dask()
    address = check_scheduler(scheduler)
    with _quiet_dask():
        _probe_scheduler(address, scheduler, SCHEDULER_TIMEOUT_S)
    return address


def _client_for(scheduler: str | None, workers: int | None, resources: dict | None = None, log=print,
                address: str | None = None):
    """A Dask client: of the scheduler ``scheduler`` (at ``address`` when already checked), else of a new
    LocalCluster of ``workers`` processes (default: one per CPU)."""
    Client, LocalCluster = _dask().Client, _dask().LocalCluster
    if scheduler:
        address = address or scheduler_address(scheduler)
        with _quiet_dask():
            try:
                client = Client(address, timeout=f"{SCHEDULER_TIMEOUT_S}s")
            except Exception as exc:  # noqa: BLE001 - one line, not Dask's traceback
                raise InputError(f"{scheduler} answered but the Dask client could not start "
                                 f"({type(exc).__name__}: {_first_line(exc)})", field="--scheduler") from None
        _note_workers(client, resources, scheduler, log)
        return client
    n = int(workers) if workers else max(1, (os.cpu_count() or 1))
    extra = {"resources": resources} if resources else {}
    try:
        import logging
        # a failed sample is reported in the manifest and the summary; the workers' own log of it is muted
        return Client(LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None,
                                   silence_logs=logging.CRITICAL, **extra))
    except Exception as exc:  # noqa: BLE001 - one line, not Dask's traceback
        raise DependencyError(f"could not start a Dask cluster of {n} worker processes on this machine "
                              f"({type(exc).__name__}: {exc}); try --workers 0") from None


def _first_line(exc) -> str:
    return ((str(exc).strip().splitlines() or [""])[0])[:200]


def _probe_scheduler(address: str, given: str, timeout_s: float) -> None:
    """Ask ``address`` who it is (Dask's ``identity``), within ``timeout_s``: refuse a peer that does not answer,
    answers in another protocol, or is not a scheduler. Runs in a thread of its own (with its own event loop)."""
    import asyncio
    import threading
    from distributed.comm import connect

    result = {}

    async def ask():
        comm = await connect(address, timeout=timeout_s)
        try:
            await comm.write({"op": "identity", "reply": True})
            return await comm.read()
        finally:
            comm.abort()

    def run():
        try:
            result["reply"] = asyncio.run(asyncio.wait_for(ask(), timeout_s))
        except BaseException as exc:  # noqa: BLE001 - reported below
            result["error"] = exc

    t = threading.Thread(target=run, name="render2spike-scheduler-probe", daemon=True)
    t.start()
    t.join(timeout_s + 2.0)
    exc = result.get("error")
    if t.is_alive() or isinstance(exc, (asyncio.TimeoutError, TimeoutError)):
        raise InputError(f"{given} accepts connections but did not answer as a Dask scheduler within {timeout_s:g} s",
                         field="--scheduler")
    if isinstance(exc, (MemoryError, OverflowError)):
        raise InputError(f"{given} answered in another protocol: it is not a Dask scheduler", field="--scheduler")
    if exc is not None:
        raise InputError(f"{given} did not answer as a Dask scheduler ({type(exc).__name__}: {_first_line(exc)})",
                         field="--scheduler")
    reply = result.get("reply")
    kind = reply.get("type") if isinstance(reply, dict) else None
    if kind != "Scheduler":
        raise InputError(f"{given} is not a Dask scheduler (it says it is {kind or repr(reply)[:60]}); give the "
                         "scheduler's address", field="--scheduler")


def _note_workers(client, resources, scheduler, log) -> None:
    """Say when the scheduler's workers cannot run the tasks yet (none, or none with the resources claimed)."""
    try:
        workers = client.scheduler_info().get("workers", {})
    except Exception:  # noqa: BLE001 - only a note
        return
    if not workers:
        log(f"note: the scheduler {scheduler} has no workers yet; the samples wait until workers join")
        return
    if resources:
        able = [w for w in workers.values()
                if all((w.get("resources") or {}).get(k, 0) >= v for k, v in resources.items())]
        if not able:
            want = ",".join(f"{k}={v:g}" for k, v in resources.items())
            log(f"note: none of the {len(workers)} workers of {scheduler} offers {want} (--resources); the samples "
                "wait until such a worker joins (start workers with `dask worker ... --resources ...`)")





def _folder_state(out: Path, spec_hash: str, overwrite: bool) -> str:
    """What ``out`` holds, for a run of the spec ``spec_hash``: "new" (missing or empty), "resume" (a dataset
    of this spec), "replace" (a dataset to replace: another spec, or ``overwrite``), "foreign" (other files,
    written into with ``overwrite``). Refuses the last two without ``overwrite``."""
    if out.exists() and not out.is_dir():
        raise InputError("exists and is not a folder; give a folder for the dataset", path=out, field="--out")
    if not out.is_dir():
        return "new"
    try:
        entries = [p.name for p in out.iterdir() if not p.name.startswith(".")]
    except OSError as exc:
        raise InputError(f"cannot list the output folder ({exc.strerror or exc})", path=out, field="--out") from None
    if not entries:
        return "new"
    man = None
    if (out / MANIFEST).is_file():
        try:
            man = json.loads((out / MANIFEST).read_text())
        except (OSError, UnicodeDecodeError, ValueError):
            man = None
    if not (isinstance(man, dict) and man.get("format") == DATASET_FORMAT):
        if overwrite:
            return "foreign"
        what = (f"holds a {MANIFEST} that `render2spike dataset` did not write" if (out / MANIFEST).exists() else
                "is not empty and holds no dataset")
        raise InputError(f"the output folder {what}; choose a new or empty folder for --out, or pass --overwrite to "
                         f"write the dataset into it (its {MANIFEST} replaced)", path=out, field="--out")
    if man.get("spec_hash") != spec_hash:
        if overwrite:
            return "replace"
        made = f" from {man['spec_file']}" if man.get("spec_file") else ""
        raise InputError(f"this folder holds a dataset of another spec (spec hash {man.get('spec_hash')}{made}; "
                         f"this spec: {spec_hash}); rerun with --overwrite to replace it, or choose another --out",
                         path=out, field="--out")
    return "replace" if overwrite else "resume"


def _clear_dataset(out: Path) -> None:
    """Remove a dataset's own files from ``out`` (samples, renders, manifest, summary)."""
    for name in ("samples", "renders"):
        if (out / name).is_dir():
            shutil.rmtree(out / name)
    for name in (MANIFEST, "summary.md"):
        (out / name).unlink(missing_ok=True)


def _refuse_if_locked(out: Path) -> None:
    """Refuse at once when a live process holds the folder's lock (before anything is started or made)."""
    from sensor.io.lock import describe, holder
    if out.is_dir():
        info = holder(out)
        if info is not None:
            raise InputError(f"a dataset run (or another writer) is already writing into this folder: "
                             f"{describe(info)}; wait for it to finish or choose another --out", path=out,
                             field="--out")


def build_dataset(spec, out, *, client=None, scheduler: str | None = None, workers: int | None = None,
                  retries: int = 2, resources: dict | None = None, progress: bool = True, overwrite: bool = False,
                  log=print) -> DatasetResult:
    """Make every sample of ``spec`` in ``out`` (see the module docstring); returns counts and failures.

    ``client``: a ``dask.distributed.Client`` to use; else ``scheduler`` (an address) or a LocalCluster of
    ``workers`` processes; ``workers=0`` runs in this process without Dask. ``resources`` (e.g.
    ``{"GPU": 1}``) is claimed by every task, so workers started with ``--resources GPU=1`` run one at a time.

    Before anything is made: the options, the whole spec (:func:`load_spec`, :func:`prepare`), the folder
    (a dataset of another spec, or other files, are refused unless ``overwrite``; ``overwrite`` starts the
    dataset afresh), the lock of a live run, the scheduler. A refusal leaves nothing behind. While it runs,
    ``out`` is locked (:class:`sensor.io.lock.FolderLock`): a second run into it is refused at once, naming
    this one's pid and host.
    """
    from sensor.io.lock import FolderLock

    t0 = time.perf_counter()
    check_run_options(workers, retries, resources, scheduler, client)
    spec, spec_path = load_spec(spec)
    out = Path(out)
    for i, sc in enumerate(spec["scenes"]):
        if "frames" in sc and same_or_inside(out, Path(sc["frames"])):
            raise InputError(f"the output would sit inside the frames folder of {_entry(spec, i)}; choose another --out",
                             path=out, field="--out")
    pl = prepare(spec, spec_path, log)
    spec_hash = _hash(spec)
    state = _folder_state(out, spec_hash, overwrite)
    _refuse_if_locked(out)
    fresh = state in ("new", "replace")
    todo_now = len(pl.ids) if fresh else len(set(pl.ids) - _done_ids(out))
    address = scheduler_address(scheduler) if todo_now and client is None and scheduler else None
    owned = []  # the client this call starts (under the lock, when there is something to make)

    def make_client():
        owned.append(_client_for(scheduler, workers, resources, log, address=address))
        return owned[-1]

    made = [p for p in [out, *out.parents] if not p.exists()]  # the folders the lock will make (deepest first)
    created = bool(made)
    lock = FolderLock(out, "a dataset run", log=log)

    def remove_made():
        for p in made:
            with contextlib.suppress(OSError):
                p.rmdir()  # only when empty

    try:
        lock.acquire()
    except OSError as exc:
        remove_made()
        raise InputError(f"cannot make or lock the output folder ({exc.strerror or exc})", path=out,
                         field="--out") from None
    except BaseException:
        remove_made()
        raise
    finished, state = False, None
    try:
        state = _folder_state(out, spec_hash, overwrite)  # again, now that no other run can change it
        if state == "replace":
            _clear_dataset(out)
        res = _run(pl, spec, spec_path, spec_hash, out, client, make_client, workers, scheduler, retries, resources,
                   progress, log, t0)
        finished = True
        return res
    except BaseException:
        while owned:
            _close(owned.pop())  # no task writes any more
        with contextlib.suppress(OSError):
            if (out / "samples").is_dir():
                for stale in (out / "samples").glob(".tmp-*"):
                    shutil.rmtree(stale, ignore_errors=True)
            if state in ("new", "replace") and not _holds_results(out):
                _clear_dataset(out)  # a run stopped before it made anything leaves no manifest
        raise
    finally:
        while owned:
            _close(owned.pop())
        lock.release()  # after the clean-up above
        if created and not finished:
            remove_made()  # only what is empty: the folders this call made and left nothing in


def _done_ids(out: Path) -> set:
    """The ids of the finished samples in ``out`` (a folder ``samples/<id>/`` with its ``sample.json``)."""
    root = os.path.join(out, "samples")
    try:
        with os.scandir(root) as it:
            names = [e.name for e in it if not e.name.startswith(".") and e.is_dir()]
    except OSError:
        return set()
    return {n for n in names if os.path.isfile(os.path.join(root, n, "sample.json"))}


def _manifest_bytes(manifest: dict) -> bytes:
    """The manifest as JSON: indented for a small dataset, compact (and fast to write) for a large one."""
    if len(manifest["samples"]) <= 2000:
        return json_bytes(manifest)
    return (json.dumps(manifest, separators=(",", ":"), default=str) + "\n").encode("ascii")


def _close(client) -> None:
    if client is None:
        return
    cluster = getattr(client, "cluster", None)
    with contextlib.suppress(Exception):
        client.close()
    if cluster is not None:
        with contextlib.suppress(Exception):
            cluster.close()


def _holds_results(out: Path) -> bool:
    """Whether ``out`` holds a finished sample or render (kept after an interruption, for the rerun)."""
    s = out / "samples"
    r = out / "renders"
    return (s.is_dir() and any(not p.name.startswith(".") for p in s.iterdir())) or \
        (r.is_dir() and any(r.iterdir()))


def _run(pl: Plan, spec, spec_path, spec_hash, out: Path, client, make_client, workers, scheduler, retries,
         resources, progress, log, t0) -> DatasetResult:
    from tqdm import tqdm
    samples, sids, rk_of = pl.samples, pl.ids, pl.render_keys
    old = {}
    if (out / MANIFEST).is_file():
        try:
            old = json.loads((out / MANIFEST).read_text()).get("samples", {})
        except (OSError, ValueError, AttributeError):
            old = {}
        old = old if isinstance(old, dict) else {}
    (out / "samples").mkdir(parents=True, exist_ok=True)
    for stale in (out / "samples").glob(".tmp-*"):  # a killed run's half-written samples
        shutil.rmtree(stale, ignore_errors=True)
    on_disk = _done_ids(out)
    records = {}
    for s, sid, rk in zip(samples, sids, rk_of):
        prev = old.get(sid)
        rec = {"index": s.index, "render_key": rk, "params": {k: getattr(s, k) for k in _FIELDS}, "status": "pending",
               "attempts": int(prev.get("attempts", 0)) if isinstance(prev, dict) else 0}
        if sid in on_disk:
            rec["status"] = "done"
            rec["seconds"] = prev.get("seconds") if isinstance(prev, dict) else None
            if isinstance(prev, dict) and isinstance(prev.get("timing"), dict):
                rec["timing"] = prev["timing"]
        records[sid] = rec
    manifest = {"format": DATASET_FORMAT, "version": DATASET_VERSION, "spec": spec,
                "spec_file": str(spec_path) if spec_path else None, "spec_hash": spec_hash,
                "n_samples": len(samples), "n_renders": pl.n_renders, "samples": records,
                "provenance": provenance(stage="dataset")}
    last_save = [0.0, 0.0]  # when the manifest was last written, and how long that took [s]

    def save(force: bool = False) -> None:
        """Write the manifest; between forced writes at most 5 % of the time goes to it (large manifests)."""
        now = time.monotonic()
        if not force and now - last_save[0] < 20 * last_save[1]:
            return
        if force:  # the last word: statuses as the disk has them
            done = _done_ids(out)
            for sid, rec in records.items():
                if sid in done and rec["status"] != "done":
                    rec["status"] = "done"
                    rec.pop("error", None)
                elif sid not in done and rec["status"] == "done":
                    rec["status"] = "pending"
        for key in ("done", "failed", "pending"):
            manifest[f"n_{key}"] = sum(r["status"] == key for r in records.values())
        write_bytes_atomic(out / MANIFEST, _manifest_bytes(manifest))
        last_save[:] = [time.monotonic(), time.monotonic() - now]

    save(force=True)
    todo = [(s, sid, rk) for s, sid, rk in zip(samples, sids, rk_of) if records[sid]["status"] != "done"]
    n_skipped = len(samples) - len(todo)
    if n_skipped:
        log(f"dataset: {n_skipped} of {len(samples)} samples already done in {out}; making the other {len(todo)}")
    else:
        log(f"dataset: {pl.description}; making them in {out}")
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
            if result.get("timing") is not None:  # [s] per stage of sample_task
                rec["timing"] = result["timing"]
            rec.pop("error", None)
            n_made += 0 if result.get("skipped") else 1
        else:
            rec["status"] = "failed"
            rec["error"] = " ".join(f"{type(error).__name__}: {error}".split())
        save()
        bar.update(1)
        if kill_after and n_made >= kill_after:
            import signal
            save(force=True)
            os.kill(os.getpid(), signal.SIGKILL)

    flist = []
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
                client = make_client()
            rfut = {}
            futs = {}
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
                if fut.status == "finished":
                    record(sid, fut.result())
                elif fut.status == "error":
                    record(sid, error=fut.exception(), attempts=retries + 1)
                else:
                    record(sid, error=InputError(f"the task ended as '{fut.status}' (worker lost or cancelled)"),
                           attempts=retries + 1)
    except BaseException:
        if flist:
            with contextlib.suppress(Exception):
                client.cancel(flist)
        raise
    finally:
        bar.close()
        save(force=True)
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
