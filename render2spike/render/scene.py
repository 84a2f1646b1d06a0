"""Scene files: load, apply ``--set`` overrides, validate against the schema, fill defaults, hash.

A scene file is YAML (or JSON) following ``render2spike/schema/scene.schema.json``;
``docs/render.md`` describes every key. Errors raise :class:`sensor.errors.InputError`
naming the file, the key (dotted path) and what was expected.
"""

from __future__ import annotations

import copy
import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sensor.errors import DependencyError, InputError
from sensor.profile import SensorProfile
from sensor.spectral import SpectralCurve, blackbody_spd, flat_spd

SCHEMA_PATH = Path(__file__).resolve().parent.parent / "schema" / "scene.schema.json"


def _scenes_dir() -> Path:
    """The bundled scenes: ``render2spike/scenes`` in an installed wheel, the checkout's ``scenes/`` otherwise."""
    installed = Path(__file__).resolve().parents[1] / "scenes"
    return installed if installed.is_dir() else Path(__file__).resolve().parents[2] / "scenes"


SCENES_DIR = _scenes_dir()

#: defaults of the ``render`` block (documented in docs/render.md)
RENDER_DEFAULTS = {
    "spp": "auto",
    "max_depth": 3,
    "seed": 0,
    "keyframe_rate_hz": 1000.0,
    "adaptive": {"enabled": True, "tolerance": 0.1, "max_rate_hz": 8000.0},
    "noise": {"window_intervals": 64, "target_ratio": 0.2, "pilot_spp": 4, "min_spp": 4, "max_spp": 1024},
    "meter_spp": 16384,
}
CAMERA_DEFAULTS = {"transmission": 0.9, "position": [0.0, 0.0, 1.0], "look_at": [0.0, 0.0, 0.0], "up": [0.0, 1.0, 0.0]}
DEFAULT_SPECTRUM = {"blackbody_k": 5000.0}
DEFAULT_DURATION_S = 0.1


def load_schema() -> dict:
    return json.loads(SCHEMA_PATH.read_text())


def _yaml():
    try:
        import yaml
    except ImportError as exc:  # pragma: no cover - declared dependency
        raise DependencyError("PyYAML is not installed: run `pip install PyYAML`") from exc
    return yaml


def bundled_scenes() -> list[str]:
    """Names of the bundled scenes (usable wherever a scene file is asked for)."""
    return sorted(q.stem for q in SCENES_DIR.glob("*.yaml")) if SCENES_DIR.is_dir() else []


def resolve_scene_path(scene) -> Path:
    """A scene path as given, or the name of a bundled scene (``rotating_disk`` -> scenes/rotating_disk.yaml)."""
    p = Path(scene)
    if p.is_file():
        return p
    for cand in (SCENES_DIR / p.name, SCENES_DIR / f"{p.name}.yaml"):
        if cand.is_file():
            return cand
    bundled = ", ".join(bundled_scenes()) or "none"
    raise InputError(f"scene file not found (bundled scenes: {bundled})", path=scene)


def _parse_value(text: str):
    try:
        return _yaml().safe_load(text)
    except Exception:
        return text


def apply_overrides(data: dict, sets, path=None) -> dict:
    """Apply ``key=value`` overrides; keys are dotted paths, list items by index or by ``name``.

    Example: ``render.spp=32``, ``objects.disk.motion.parametric.0.rotate.omega_rad_s=20``,
    ``camera.f_number=2.8``. Values are parsed as YAML (numbers, lists, strings).
    """
    data = copy.deepcopy(data)
    for item in sets or []:
        if "=" not in item:
            raise InputError(f"--set needs key=value, got '{item}'", path=path, field="--set")
        key, value = item.split("=", 1)
        parts = [p for p in key.strip().split(".") if p]
        if not parts:
            raise InputError(f"--set has an empty key in '{item}'", path=path, field="--set")
        node = data
        for i, part in enumerate(parts):
            last = i == len(parts) - 1
            where = ".".join(parts[:i + 1])
            if isinstance(node, list):
                idx = None
                if part.lstrip("-").isdigit():
                    idx = int(part)
                else:
                    names = [j for j, el in enumerate(node) if isinstance(el, dict) and el.get("name") == part]
                    idx = names[0] if names else None
                if idx is None or not -len(node) <= idx < len(node):
                    raise InputError(f"--set: no list item '{part}' (index or name) here", path=path, field=where)
                if last:
                    node[idx] = _parse_value(value)
                else:
                    node = node[idx]
            elif isinstance(node, dict):
                if last:
                    node[part] = _parse_value(value)
                else:
                    node = node.setdefault(part, {})
            else:
                raise InputError(f"--set: '{'.'.join(parts[:i])}' is a value, not a mapping or list",
                                 path=path, field=where)
    return data


def split_parameter_sets(raw: dict, sets) -> tuple[list, list]:
    """Split ``--set`` items into (plain overrides, parameter values); see :func:`apply_parameters`."""
    params = raw.get("parameters") if isinstance(raw, dict) else None
    names = set(params) if isinstance(params, dict) else set()
    plain, values = [], []
    for item in sets or []:
        key = str(item).split("=", 1)[0].strip()
        (values if key in names else plain).append(item)
    return plain, values


def apply_parameters(data: dict, values, path=None) -> dict:
    """Expand the scene's named ``parameters`` into the keys they drive.

    A parameter ``{value: v, sets: {KEY: factor, ...}}`` sets each dotted
    ``KEY`` to ``factor * v`` (the declared value, or the one given as
    ``NAME=VALUE`` in ``values``) and records the value used. Example: the
    bundled ``translating_object`` scene's ``speed_px_per_ms`` drives the
    cube's velocity [m/s]. Applied before plain ``--set`` overrides, which win.
    """
    params = data.get("parameters")
    if not isinstance(params, dict) or not params:
        return data
    data = copy.deepcopy(data)
    given = {}
    for item in values or []:
        key, _, text = str(item).partition("=")
        try:
            given[key.strip()] = float(text)
        except ValueError:
            raise InputError(f"parameter '{key.strip()}' needs a number, got '{text}'", path=path,
                             field=key.strip()) from None
    sets = []
    for name, spec in params.items():
        if not isinstance(spec, dict) or not isinstance(spec.get("sets"), dict):
            continue  # the schema check reports it
        v = given.get(name, spec.get("value"))
        if not isinstance(v, (int, float)):
            raise InputError(f"parameter '{name}' needs a numeric value", path=path, field=f"parameters.{name}.value")
        spec["value"] = float(v)
        for key, factor in spec["sets"].items():
            sets.append(f"{key}={float(factor) * float(v)!r}")
    return apply_overrides(data, sets, path)


def _error_path(err) -> str:
    return ".".join(str(p) for p in err.absolute_path) or "(top level)"


def _form(schema) -> str:
    """A few words for what a (sub)schema accepts: "'auto'", "an integer >= 1", "a mapping with keys ..."."""
    if not isinstance(schema, dict):
        return "a value"
    if "const" in schema:
        return repr(schema["const"])
    if "enum" in schema:
        return "one of " + ", ".join(map(repr, schema["enum"]))
    t = schema.get("type")
    bounds = [f">= {schema['minimum']}" if "minimum" in schema else "",
              f"> {schema['exclusiveMinimum']}" if "exclusiveMinimum" in schema else "",
              f"<= {schema['maximum']}" if "maximum" in schema else "",
              f"< {schema['exclusiveMaximum']}" if "exclusiveMaximum" in schema else ""]
    bounds = " and ".join(b for b in bounds if b)
    if t in ("integer", "number"):
        return f"{'an integer' if t == 'integer' else 'a number'}{' ' + bounds if bounds else ''}"
    if t == "string":
        return "a string"
    if t == "boolean":
        return "true or false"
    if t == "array":
        n = schema.get("minItems")
        return f"a list{f' of {n}' if n is not None and n == schema.get('maxItems') else ''} ({_form(schema.get('items'))} each)"
    if t == "object":
        req = schema.get("required")
        return f"a mapping with {', '.join(req)}" if req else "a mapping"
    return "a value of another form"


def _describe(err) -> str:
    """A one-line message for a jsonschema error: what was found and what was expected."""
    v = err.validator
    if v == "additionalProperties":
        allowed = sorted(err.schema.get("properties", {}))
        return f"{err.message}; allowed keys here: {', '.join(allowed)}"
    if v in ("oneOf", "anyOf") and err.context:
        depth = len(list(err.absolute_path))
        deep = [e for e in err.context if len(list(e.absolute_path)) > depth]
        if deep:  # the value has the shape of one form, and a part of it is wrong: say which part
            inner = max(deep, key=lambda e: len(list(e.absolute_path)))
            return f"{_describe(inner)} (at {_error_path(inner)})"
        forms = [_form(s) for s in err.validator_value]
        return f"must be {' or '.join(forms)}; got {err.instance!r}"
    if v == "enum":
        return f"{err.instance!r} is not one of {', '.join(map(repr, err.validator_value))}"
    if v == "required":
        return err.message.replace("is a required property", "is required here")
    return err.message


def check_finite(node, path=None, where: str = "") -> None:
    """Every number in a scene mapping must be finite (YAML's .nan/.inf and --lux nan pass the schema's bounds)."""
    if isinstance(node, dict):
        for k, v in node.items():
            check_finite(v, path, f"{where}.{k}" if where else str(k))
    elif isinstance(node, (list, tuple)):
        for i, v in enumerate(node):
            check_finite(v, path, f"{where}.{i}" if where else str(i))
    elif isinstance(node, float) and not np.isfinite(node):
        raise InputError(f"must be a finite number, got {node!r}", path=path, field=where or "(top level)")


def validate(data, path=None) -> None:
    """Check ``data`` against the scene schema; raise InputError naming the file and key."""
    try:
        import jsonschema
    except ImportError as exc:  # pragma: no cover
        raise DependencyError("jsonschema is not installed: run `pip install jsonschema`") from exc
    if not isinstance(data, dict):
        raise InputError(f"a scene file must hold a mapping of keys, got {type(data).__name__}", path=path)
    validator = jsonschema.Draft202012Validator(load_schema())
    errors = sorted(validator.iter_errors(data), key=lambda e: (len(list(e.absolute_path)), str(e.message)))
    if errors:
        err = max(errors, key=lambda e: len(list(e.absolute_path)))
        extra = f" (and {len(errors) - 1} more problem(s))" if len(errors) > 1 else ""
        raise InputError(_describe(err) + extra, path=path, field=_error_path(err))


def spectrum_curve(spec: dict | None) -> SpectralCurve:
    """Relative SPD from a scene ``spectrum`` mapping (default: 5000 K black body)."""
    spec = spec or DEFAULT_SPECTRUM
    if "blackbody_k" in spec:
        return blackbody_spd(float(spec["blackbody_k"]), np.arange(300.0, 1101.0, 5.0))
    if "flat_nm" in spec:
        lo, hi = (float(x) for x in spec["flat_nm"])
        if hi <= lo:
            raise InputError(f"flat_nm needs [low, high] with low < high, got {spec['flat_nm']}", field="spectrum")
        return flat_spd(lo, hi)
    t = spec["table"]
    if len(t["wavelength_nm"]) != len(t["values"]):
        raise InputError("spectrum table: wavelength_nm and values differ in length", field="spectrum.table")
    return SpectralCurve(np.asarray(t["wavelength_nm"], float), np.asarray(t["values"], float), unit="relative",
                         name="table")


def build_profile(spec, path=None) -> SensorProfile:
    """The sensor profile a scene's ``camera.profile`` names (bundled name/path, synthetic, or a window)."""
    try:
        if isinstance(spec, str):
            return SensorProfile.load(spec)
        if "synthetic" in spec:
            kw = dict(spec["synthetic"])
            h, w = int(kw.pop("height")), int(kw.pop("width"))
            return SensorProfile.synthetic(h, w, **kw)
        base = SensorProfile.load(spec["base"])
        top, left, h, w = (int(x) for x in spec["window"])
        return base.window(top, left, h, w)
    except TypeError as exc:
        raise InputError(f"bad synthetic profile parameter ({exc})", path=path, field="camera.profile") from exc
    except InputError as exc:
        raise InputError(f"{exc}", path=path, field="camera.profile") from exc


@dataclass
class Scene:
    """A validated scene file with defaults filled in.

    ``data`` is the normalised mapping (what is hashed); ``folder`` resolves
    relative file names; ``profile`` is the camera's sensor.
    """

    path: Path
    data: dict
    profile: SensorProfile
    file_hashes: dict = field(default_factory=dict)

    @property
    def folder(self) -> Path:
        return self.path.parent

    @property
    def name(self) -> str:
        return self.data.get("name", self.path.stem)

    @property
    def render(self) -> dict:
        return self.data["render"]

    @property
    def camera(self) -> dict:
        return self.data["camera"]

    @property
    def duration_s(self) -> float:
        return float(self.data["duration_s"])

    @property
    def illuminance_lux(self) -> float:
        return float(self.data["illuminance_lux"])

    def file(self, name: str, field_name: str) -> Path:
        """A file the scene refers to: an absolute path, else one beside the scene file, else a bundled one
        (``scenes/``, e.g. the meshes ``mesh_torus.ply`` that generated scenes place)."""
        p = Path(name)
        if not p.is_absolute():
            p = self.folder / p if (self.folder / p).is_file() or not (Path(SCENES_DIR) / p).is_file() \
                else Path(SCENES_DIR) / p
        if not p.is_file():
            raise InputError(f"referenced file does not exist: {p}", path=self.path, field=field_name)
        return p

    def object(self, name: str) -> dict:
        for o in self.data.get("objects", []):
            if o["name"] == name:
                return o
        raise InputError(f"no object named '{name}' (objects: "
                         f"{', '.join(o['name'] for o in self.data.get('objects', [])) or 'none'})",
                         path=self.path, field="reference.object")

    def content_hash(self, settings: dict | None = None) -> str:
        """SHA-256 over the normalised scene, the referenced files' bytes and ``settings``."""
        h = hashlib.sha256()
        h.update(json.dumps(self.data, sort_keys=True, default=str).encode())
        h.update(json.dumps(self.file_hashes, sort_keys=True).encode())
        # only what the render depends on: resolution, pixel pitch (focal-plane geometry) and QE (the Phi
        # response). Dark, PRNU, hot-pixel maps and the threshold act later, in the sensor stage.
        prof = self.profile
        h.update(json.dumps({"height": prof.height, "width": prof.width, "pixel_pitch_m": prof.pixel_pitch_m,
                             "qe": prof.qe.to_dict()}, sort_keys=True, default=str).encode())
        h.update(json.dumps(settings or {}, sort_keys=True, default=str).encode())
        return h.hexdigest()[:16]


def _merge_defaults(d: dict, defaults: dict) -> dict:
    out = copy.deepcopy(defaults)
    for k, v in (d or {}).items():
        out[k] = _merge_defaults(v, out[k]) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _sha_file(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()[:16]


def load_scene(scene, sets=None, *, lux: float | None = None, duration_s: float | None = None,
               profile: str | None = None, cache: dict | None = None) -> Scene:
    """Read, override, validate and normalise a scene file.

    Parameters
    ----------
    scene : path or bundled name, or a scene mapping made in code (:func:`render2spike.scenegen.generate_scene`;
        its files are looked up among the bundled ones)
    sets : list of "key=value" overrides (see :func:`apply_overrides`)
    lux, duration_s, profile : shortcuts for ``illuminance_lux``, ``duration_s``, ``camera.profile``.
    cache : a dict kept by a caller that loads many variants of the same files (a dataset's plan): each
        file is parsed and each sensor profile loaded once. The returned scenes share those profiles.
    """
    if isinstance(scene, dict):  # a scene mapping made in code (render2spike.scenegen): no file behind it
        text = json.dumps(scene, sort_keys=True, default=str)
        path = Path(SCENES_DIR) / f"{scene.get('name', 'scene')}.generated"  # bundled files are found beside it
        key = ("scene-data", hashlib.sha256(text.encode()).hexdigest())
        raw = json.loads(text)
        if cache is not None:
            raw = cache.setdefault(key, raw)
    else:
        path = resolve_scene_path(scene)
        key = ("scene-file", str(path))
    try:
        raw = raw if isinstance(scene, dict) else \
            cache[key] if cache is not None and key in cache else _yaml().safe_load(path.read_text())
    except Exception as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise InputError(f"not valid YAML{where}: {getattr(exc, 'problem', exc)}", path=path) from exc
    if cache is not None:
        cache[key] = raw  # never modified: overrides and parameters work on copies
    if raw is None:
        raise InputError("the scene file is empty", path=path)
    if not isinstance(raw, dict):
        raise InputError(f"a scene file must hold a mapping of keys, got {type(raw).__name__}", path=path)
    plain_sets, parameter_values = split_parameter_sets(raw, sets)
    data = apply_overrides(apply_parameters(raw, parameter_values, path), plain_sets, path)
    if lux is not None:
        data["illuminance_lux"] = float(lux)
    if duration_s is not None:
        data["duration_s"] = float(duration_s)
    if profile is not None and isinstance(data.get("camera"), dict):
        data["camera"]["profile"] = profile
    check_finite(data, path)
    validate(data, path)
    data["render"] = _merge_defaults(data.get("render", {}), RENDER_DEFAULTS)
    data["camera"] = _merge_defaults(data["camera"], CAMERA_DEFAULTS) if "rotation_deg" not in data["camera"] else \
        _merge_defaults(data["camera"], {k: v for k, v in CAMERA_DEFAULTS.items() if k in ("transmission", "position")})
    data.setdefault("duration_s", DEFAULT_DURATION_S)
    data.setdefault("lights", [])
    data.setdefault("objects", [])
    if "illuminance_lux" not in data:
        raise InputError("no light level: set illuminance_lux in the scene or pass --lux", path=path,
                         field="illuminance_lux")
    has_lights = bool(data["lights"]) or any("emitter" in o for o in data["objects"]) or "xml" in data
    if not has_lights:
        raise InputError("the scene has no light: add a 'lights' entry, an object 'emitter' or an 'xml' scene",
                         path=path, field="lights")
    if not data["objects"] and "xml" not in data:
        raise InputError("the scene has nothing to see: add at least one entry to 'objects' (or an 'xml' scene)",
                         path=path, field="objects")
    if "reference" not in data:
        raise InputError("illuminance_lux needs a 'reference': {point: [x, y, z], normal: [x, y, z]} or "
                         "{object: NAME}", path=path, field="reference")
    names = [o["name"] for o in data["objects"]]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError(f"object names must be unique; repeated: {', '.join(dup)}", path=path, field="objects")
    r = data["render"]
    if r["noise"]["min_spp"] > r["noise"]["max_spp"]:
        raise InputError("min_spp must be <= max_spp", path=path, field="render.noise")
    if r["adaptive"]["max_rate_hz"] < r["keyframe_rate_hz"]:
        raise InputError(f"adaptive.max_rate_hz ({r['adaptive']['max_rate_hz']}) must be >= keyframe_rate_hz "
                         f"({r['keyframe_rate_hz']})", path=path, field="render.adaptive.max_rate_hz")
    files = {}
    pkey = ("profile", json.dumps(data["camera"]["profile"], sort_keys=True, default=str))
    if cache is not None and pkey in cache:
        prof = cache[pkey]
    else:
        prof = build_profile(data["camera"]["profile"], path)
        if cache is not None:
            cache[pkey] = prof
    sc = Scene(path=path, data=data, profile=prof)
    if not data["duration_s"] >= sc.profile.interval_s:
        raise InputError(f"the clip ({data['duration_s']:g} s) is shorter than one read-out interval "
                         f"({sc.profile.interval_s * 1e6:g} us) of the profile '{sc.profile.name}': it would hold no "
                         f"spike frame; give at least {sc.profile.interval_s:g} s (--duration)", path=path,
                         field="duration_s")
    for i, o in enumerate(data["objects"]):
        where = f"objects.{i}"
        if o["shape"] == "mesh":
            if "file" not in o:
                raise InputError("shape 'mesh' needs 'file' (a .ply or .obj)", path=path, field=f"{where}.file")
            f = sc.file(o["file"], f"{where}.file")
            if f.suffix.lower() not in (".ply", ".obj"):
                raise InputError(f"mesh files must be .ply or .obj, got '{f.suffix}'", path=path, field=f"{where}.file")
            files[o["file"]] = _sha_file(f)
        refl = (o.get("material") or {}).get("reflectance")
        if isinstance(refl, dict) and refl["texture"] == "image":
            if "file" not in refl:
                raise InputError("texture 'image' needs 'file'", path=path, field=f"{where}.material.reflectance.file")
            files[refl["file"]] = _sha_file(sc.file(refl["file"], f"{where}.material.reflectance.file"))
        if isinstance(refl, dict) and refl["texture"] == "skimage" and "name" not in refl:
            raise InputError("texture 'skimage' needs 'name' (e.g. camera, brick, grass)", path=path,
                             field=f"{where}.material.reflectance.name")
    if "xml" in data:
        files[data["xml"]] = _sha_file(sc.file(data["xml"], "xml"))
    ref = data["reference"]
    if "object" in ref:
        obj = sc.object(ref["object"])
        if obj["shape"] not in ("rectangle", "disk"):
            raise InputError(f"reference object '{ref['object']}' is a {obj['shape']}; use a rectangle or disk, or "
                             "give {point, normal}", path=path, field="reference.object")
    elif np.linalg.norm(ref["normal"]) == 0:
        raise InputError("normal must be non-zero", path=path, field="reference.normal")
    for j, lt in enumerate(data["lights"]):
        if lt["type"] == "directional" and np.linalg.norm(lt["direction"]) == 0:
            raise InputError("direction must be non-zero", path=path, field=f"lights.{j}.direction")
    sc.file_hashes = files
    return sc
