"""Procedural scenes: random rigid objects before a textured background, moving or still, seeded.

:func:`generate_scene` turns ``(seed, index, options)`` into a scene mapping of the scene-file format
(``docs/render.md``), the same one every time; :func:`write_scenes` writes them as YAML files
(``render2spike scenegen``), and a dataset spec takes them with a ``{procedural: {...}}`` entry under
``scenes`` (``docs/studies.md``). What a scene holds, each draw from its own child of
``SeedSequence([seed, index])``:

* **camera**: the ``profile`` (default ``vidar-default``) on a centred ``window`` (default 64 x 96 pixels),
  f = 8 mm (2.5 mm per pixel at 1 m), f/2, looking down -z at a background plane ``D`` metres away,
  ``D`` log-uniform in ``distance_m`` (default 0.8-3 m);
* **background**: a rectangle filling the view with margin for the motion, textured;
* **objects**: a count uniform in ``objects`` (default 1-4), each a sphere, cube, cylinder, disk,
  rectangle or one of the bundled meshes (``scenes/mesh_*.ply``: torus, blob, cone, capsule), 10-40 % of
  the view's width at a depth between the camera and the background (20-90 % of ``D`` from the camera),
  turned at random, textured or plain;
* **textures**: a photograph scikit-image ships (:data:`PHOTOS`) or a procedural one (checker, stripes,
  smooth noise), reflectance between a low of 0.02-0.2 and a high of 0.4-0.9; plain objects a reflectance
  of 0.05-0.9;
* **motion**: a share ``still_fraction`` (default 0.2) of the scenes are still; in the others every
  object turns about its centre and a random axis, its rim at an image speed log-uniform in
  ``speed_px_per_ms`` (default 0.05-3 px/ms: up to about 5 px per 32-interval window at T_r = 50 us), and
  its centre translates across the image at another such speed (a rim point then moves at up to the sum:
  ``generator.fastest_px_per_ms``); with probability ``camera_motion`` (default 0.5) the camera pans
  (translates) at such a speed too. Image speeds are converted with the distance and the profile's pitch
  (:func:`metres_per_pixel_at_1m`): 1 px/ms at ``d`` metres is 2.5 d m/s for a 20 um pitch;
* **light**: a directional key light from a random direction of the front hemisphere (black body
  3000-6500 K), a dim sky (0.5-10 % of the key), and with probability 0.3 a point light near the camera;
  ``illuminance_lux`` log-uniform in ``lux`` (default 0.5-500), measured on the background's centre
  (a dataset's ``lux`` axis replaces it);
* **render**: base keyframes at 1 kHz, refined up to the rate the fastest motion needs (at most 8 kHz),
  ``max_spp`` 128, as the bundled scenes; a render seed of its own.

Rigid motion only: every object keeps its shape (the frozen launch moves meshes as instances).
"""

from __future__ import annotations

import functools
import math
from pathlib import Path

import numpy as np

from sensor.errors import InputError

#: part of every generated scene (``generator`` block): a change to what a seed gives must bump it
GENERATOR_VERSION = 1
#: scikit-image's bundled photographs that load without a download
PHOTOS = ("astronaut", "brick", "camera", "cat", "chelsea", "clock", "coffee", "coins", "grass", "gravel",
          "horse", "hubble_deep_field", "immunohistochemistry", "moon", "page", "rocket", "text")
PROCEDURAL = ("checker", "stripes", "noise")
PRIMITIVES = ("sphere", "cube", "cylinder", "disk", "rectangle")
MESHES = ("torus", "blob", "cone", "capsule")
#: the generated camera's focal length [mm] (with vidar-default's 20 um pitch: 2.5 mm per pixel at 1 m)
FOCAL_LENGTH_MM = 8.0
DEFAULTS = {"objects": [1, 4], "speed_px_per_ms": [0.05, 3.0], "still_fraction": 0.2, "camera_motion": 0.5,
            "lux": [0.5, 500.0], "window": [64, 96], "profile": "vidar-default", "distance_m": [0.8, 3.0],
            "duration_s": 0.1}


def _pair(options: dict, key: str, positive: bool = True, integer: bool = False) -> list:
    v = options[key]
    if not (isinstance(v, (list, tuple)) and len(v) == 2 and all(isinstance(x, (int, float)) and
                                                                 not isinstance(x, bool) for x in v)):
        raise InputError(f"must be a pair [low, high]; got {v!r}", field=f"procedural.{key}")
    lo, hi = float(v[0]), float(v[1])
    if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi or (positive and lo <= 0) or lo < 0:
        raise InputError(f"must be finite with {'0 < ' if positive else '0 <= '}low <= high; got {v!r}",
                         field=f"procedural.{key}")
    if integer and (lo != int(lo) or hi != int(hi)):
        raise InputError(f"must be whole numbers; got {v!r}", field=f"procedural.{key}")
    return [lo, hi]


def check_options(options: dict | None) -> dict:
    """The generator's options with defaults filled, each checked (one-line :class:`InputError` naming it)."""
    options = dict(options or {})
    unknown = sorted(set(options) - set(DEFAULTS) - {"count", "seed"})
    if unknown:
        raise InputError(f"unknown option(s) {', '.join(unknown)}; the options are "
                         f"{', '.join(sorted(set(DEFAULTS) | {'count', 'seed'}))}", field="procedural")
    out = {**DEFAULTS, **options}
    _pair(out, "objects", positive=False, integer=True)
    if out["objects"][1] > 32:
        raise InputError(f"at most 32 objects a scene; got {out['objects']!r}", field="procedural.objects")
    _pair(out, "speed_px_per_ms", positive=True)
    _pair(out, "lux", positive=True)
    _pair(out, "distance_m", positive=True)
    win = out["window"]
    if not (isinstance(win, (list, tuple)) and len(win) == 2 and all(isinstance(x, int) and not isinstance(x, bool)
                                                                     and x >= 1 for x in win)):
        raise InputError(f"must be [height, width] in pixels, each an integer >= 1; got {win!r}",
                         field="procedural.window")
    for key in ("still_fraction", "camera_motion"):
        v = out[key]
        if not (isinstance(v, (int, float)) and not isinstance(v, bool) and 0.0 <= float(v) <= 1.0):
            raise InputError(f"must be a probability in [0, 1]; got {v!r}", field=f"procedural.{key}")
    d = out["duration_s"]
    if not (isinstance(d, (int, float)) and not isinstance(d, bool) and math.isfinite(d) and d > 0):
        raise InputError(f"must be a duration in seconds above 0; got {d!r}", field="procedural.duration_s")
    if not isinstance(out["profile"], str):
        raise InputError(f"must be a profile name or file; got {out['profile']!r}", field="procedural.profile")
    centred_window(out["profile"], *win)  # fits the sensor
    return out


def _unit(rng) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def _texture(rng, resolution: int = 256) -> dict:
    lo, hi = float(rng.uniform(0.02, 0.2)), float(rng.uniform(0.4, 0.9))
    if rng.random() < 0.6:
        return {"texture": "skimage", "name": str(rng.choice(PHOTOS)), "resolution": 512, "low": round(lo, 4),
                "high": round(hi, 4)}
    kind = str(rng.choice(PROCEDURAL))
    tex = {"texture": kind, "resolution": resolution, "low": round(lo, 4), "high": round(hi, 4)}
    if kind == "noise":
        tex.update(seed=int(rng.integers(2 ** 31)), smooth_px=round(float(rng.uniform(1.0, 8.0)), 3))
    else:
        tex["squares"] = int(rng.integers(2, 17))
    return tex


def _rounded(v, nd: int = 6) -> list:
    return [round(float(x), nd) for x in v]


def _material(rng) -> dict:
    if rng.random() < 0.75:
        return {"reflectance": _texture(rng)}
    return {"reflectance": round(float(rng.uniform(0.05, 0.9)), 4)}


def _speed(rng, lo: float, hi: float) -> float:
    """An image speed [px/ms], log-uniform in [lo, hi]."""
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def generate_scene(seed: int, index: int = 0, options: dict | None = None) -> dict:
    """The scene mapping number ``index`` of generator seed ``seed`` (see the module docstring)."""
    o = check_options(options)
    if not (isinstance(seed, (int, np.integer)) and seed >= 0 and isinstance(index, (int, np.integer))
            and index >= 0):
        raise InputError(f"seed and index must be integers >= 0; got {seed!r}, {index!r}", field="procedural.seed")
    ss = np.random.SeedSequence([int(seed), int(index), GENERATOR_VERSION])
    cam_rng, bg_rng, obj_rng, mot_rng, light_rng = (np.random.default_rng(s) for s in ss.spawn(5))
    h, w = (int(x) for x in o["window"])
    px_m = metres_per_pixel_at_1m(o["profile"])  # [m] per pixel at 1 m
    lo_d, hi_d = o["distance_m"]
    dist = float(math.exp(cam_rng.uniform(math.log(lo_d), math.log(hi_d))))
    duration = float(o["duration_s"])
    still = bool(mot_rng.random() < float(o["still_fraction"]))
    vmin, vmax = o["speed_px_per_ms"]
    fastest = 0.0

    camera = {"profile": {"base": o["profile"], "window": centred_window(o["profile"], h, w)},
              "focal_length_mm": FOCAL_LENGTH_MM, "f_number": 2.0, "transmission": 0.9,
              "position": [0.0, 0.0, round(dist, 6)], "look_at": [0.0, 0.0, 0.0], "up": [0.0, 1.0, 0.0]}
    pan = [0.0, 0.0, 0.0]
    if not still and mot_rng.random() < float(o["camera_motion"]):
        v = _speed(mot_rng, vmin, vmax)
        fastest = max(fastest, v)
        ang = mot_rng.uniform(0, 2 * math.pi)
        speed_m_s = v * 1000.0 * px_m * dist  # px/ms -> m/s at the background's distance
        pan = [speed_m_s * math.cos(ang), speed_m_s * math.sin(ang), 0.0]
        camera["motion"] = {"parametric": [{"translate": {"velocity_m_s": _rounded(pan)}}]}

    # the background fills the view at its distance, with room for the camera's pan over the clip
    view_w, view_h = w * px_m * dist, h * px_m * dist
    travel = math.hypot(pan[0], pan[1]) * duration
    background = {"name": "background", "shape": "rectangle",
                  "size": _rounded([1.5 * view_w + 2 * travel, 1.5 * view_h + 2 * travel]),
                  "position": [0.0, 0.0, 0.0], "material": {"reflectance": _texture(bg_rng, 512)}}
    objects = [background]
    lo_n, hi_n = (int(x) for x in o["objects"])
    for k in range(int(obj_rng.integers(lo_n, hi_n + 1))):
        d_cam = float(obj_rng.uniform(0.2, 0.9)) * dist  # distance from the camera
        z = dist - d_cam
        vw, vh = w * px_m * d_cam, h * px_m * d_cam
        size = float(obj_rng.uniform(0.1, 0.4)) * vw
        kind = str(obj_rng.choice(PRIMITIVES + ("mesh",)))
        obj = {"name": f"obj{k}", "shape": kind,
               "position": _rounded([obj_rng.uniform(-0.4, 0.4) * vw, obj_rng.uniform(-0.4, 0.4) * vh, z]),
               "rotation_deg": _rounded(obj_rng.uniform(-180, 180, 3), 3), "material": _material(obj_rng)}
        if kind in ("sphere", "disk"):
            obj["radius"] = round(size / 2, 6)
        elif kind == "cube":
            obj["size"] = _rounded(size * obj_rng.uniform(0.5, 1.0, 3))
        elif kind == "cylinder":
            obj.update(radius=round(size / 4, 6), length=round(size, 6))
        elif kind == "rectangle":
            obj["size"] = _rounded(size * obj_rng.uniform(0.5, 1.0, 2))
            obj["rotation_deg"] = _rounded(obj_rng.uniform(-40, 40, 3), 3)  # mostly facing the camera
            obj["material"]["two_sided"] = True
        else:
            obj["shape"] = "mesh"
            obj["file"] = mesh_path(str(obj_rng.choice(MESHES))).name  # bundled: Scene.file finds it
            obj["scale"] = round(size, 6)
        if not still:
            v = _speed(mot_rng, vmin, vmax)
            ang = mot_rng.uniform(0, 2 * math.pi)
            sp = v * 1000.0 * px_m * d_cam
            v_rim = _speed(mot_rng, vmin, vmax)  # the rim's image speed of the turn [px/ms]
            spin = v_rim * 1000.0 * px_m * d_cam / max(size / 2, 1e-9)  # [rad/s]
            fastest = max(fastest, v + v_rim)  # a rim point moves at up to both together
            # turned about its own centre first (the pose at t = 0), then carried along: parametric motions apply
            # in order, so the other order would turn it about where it started and send it on a growing orbit
            obj["motion"] = {"parametric": [
                {"rotate": {"axis": _rounded(_unit(mot_rng)), "omega_rad_s": round(
                    float(spin * mot_rng.choice([-1.0, 1.0])), 6), "center": list(obj["position"])}},
                {"translate": {"velocity_m_s": _rounded([sp * math.cos(ang), sp * math.sin(ang), 0.0])}}]}
        objects.append(obj)

    key_dir = np.array([light_rng.uniform(-0.7, 0.7), light_rng.uniform(-0.7, 0.7), -1.0])
    lights = [{"name": "key", "type": "directional", "direction": _rounded(key_dir / np.linalg.norm(key_dir)),
               "strength": 1.0, "spectrum": {"blackbody_k": round(float(light_rng.uniform(3000, 6500)), 1)}},
              {"name": "sky", "type": "environment", "strength": round(float(light_rng.uniform(0.005, 0.1)), 5),
               "spectrum": {"blackbody_k": 6500}}]
    if light_rng.random() < 0.3:
        lights.append({"name": "lamp", "type": "point", "strength": round(float(light_rng.uniform(0.05, 0.5)), 4),
                       "position": _rounded([light_rng.uniform(-0.3, 0.3) * dist, light_rng.uniform(-0.3, 0.3)
                                             * dist, 0.9 * dist]),
                       "spectrum": {"blackbody_k": round(float(light_rng.uniform(2700, 4000)), 1)}})
    lo_l, hi_l = o["lux"]
    lux = float(math.exp(light_rng.uniform(math.log(lo_l), math.log(hi_l))))
    # keyframes: 1 kHz base, refined up to where the fastest motion moves under a pixel a keyframe
    max_rate = float(min(8000.0, 1000.0 * 2 ** max(1, math.ceil(math.log2(max(1.0, 2.0 * fastest))))))
    return {
        "format": "render2spike-scene",
        "name": f"procedural_{int(seed)}_{int(index):04d}",
        "description": (f"Procedural scene {index} of generator seed {seed} (render2spike.scenegen version "
                        f"{GENERATOR_VERSION}): {len(objects) - 1} object(s) before a textured background at "
                        f"{dist:.2f} m, {'still' if still else f'moving up to {fastest:.2f} px/ms'}."),
        "duration_s": duration,
        "illuminance_lux": round(lux, 6),
        "reference": {"point": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0]},
        "camera": camera,
        "lights": lights,
        "objects": objects,
        "render": {"keyframe_rate_hz": 1000, "adaptive": {"enabled": True, "tolerance": 0.25,
                                                          "max_rate_hz": max_rate},
                   "noise": {"max_spp": 128}, "max_depth": 3,
                   # each scene its own render seed: scenes of a dataset share no sample pattern
                   "seed": int(np.random.SeedSequence([int(seed), int(index), 0x5EED]).generate_state(1)[0])},
        "generator": {"tool": "render2spike.scenegen", "version": GENERATOR_VERSION, "seed": int(seed),
                      "index": int(index), "fastest_px_per_ms": round(fastest, 6), "still": still},
    }


@functools.lru_cache(maxsize=16)
def _sensor(profile: str) -> tuple[int, int, float]:
    """(height, width [px], pixel pitch [m]) of ``profile``."""
    from sensor.profile import SensorProfile
    try:
        p = SensorProfile.load(profile)
    except InputError as exc:
        raise InputError(str(exc), field="procedural.profile") from None
    return int(p.height), int(p.width), float(p.pixel_pitch_m)


def metres_per_pixel_at_1m(profile: str) -> float:
    """The image scale of the generator's optics: ``profile``'s pixel pitch over the focal length [m per px at
    1 m]; an image speed of 1 px/ms at ``d`` metres is ``1000 d`` times it in m/s."""
    from sensor.units import mm_to_m
    return _sensor(profile)[2] / float(mm_to_m(FOCAL_LENGTH_MM))


def centred_window(profile: str, height: int, width: int) -> list[int]:
    """``[row, col, height, width]`` of a window of that size centred on ``profile``'s sensor."""
    ph, pw, _ = _sensor(profile)
    if height > ph or width > pw:
        raise InputError(f"a {height} x {width} window does not fit the {ph} x {pw} sensor of '{profile}'",
                         field="procedural.window")
    return [(ph - height) // 2, (pw - width) // 2, int(height), int(width)]


def mesh_path(name: str) -> Path:
    """The bundled mesh ``scenes/mesh_NAME.ply`` (installed as render2spike.scenes data)."""
    from render2spike.render.scene import SCENES_DIR
    return Path(SCENES_DIR) / f"mesh_{name}.ply"


def write_scenes(folder, count: int, seed: int, options: dict | None = None) -> list[Path]:
    """Write scenes ``0 .. count - 1`` of generator seed ``seed`` as ``FOLDER/procedural_SEED_IIII.yaml``
    (each written to a temporary file and renamed). -> their paths."""
    from render2spike.render.scene import _yaml
    from sensor.io.fileio import write_text_atomic
    if not (isinstance(count, int) and count >= 1):
        raise InputError(f"must be an integer >= 1; got {count!r}", field="--count")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for i in range(count):
        d = generate_scene(seed, i, options)
        p = folder / f"{d['name']}.yaml"
        write_text_atomic(p, "# made by render2spike scenegen; regenerate with the seed and index in 'generator'\n"
                          + _yaml().safe_dump(d, sort_keys=False, default_flow_style=None))
        out.append(p)
    return out
