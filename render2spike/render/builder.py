"""Scene -> Mitsuba 3 scene dictionary (camera with the two-channel spectral film, lights, objects).

Shapes and their local geometry (before the object's pose T R S):

* ``rectangle`` ``size: [w, h]`` [m]: the plane z = 0, w x h, normal +z, uv over [0, 1]^2;
* ``disk`` ``radius`` [m]: z = 0, normal +z, uv polar (u = r / radius, v = angle / 2 pi);
* ``sphere`` ``radius`` [m]; ``cube`` ``size: [x, y, z]`` [m];
* ``cylinder`` ``radius``, ``length`` [m] along +z from z = 0;
* ``mesh`` ``file``: a PLY/OBJ (checked with trimesh), in its own units of metres.
"""

from __future__ import annotations

import functools
import re

import numpy as np

from sensor.errors import DependencyError, InputError
from sensor.units import mm_to_m

from .motion import Motion, Pose
from .photometry import fov_x_deg, lux_response, phi_response
from .scene import Scene, spectrum_curve
from .textures import make_texture

SENSOR_KEY = "camera"
SAMPLER = "multijitter"  #: stratified pixel sampling: texture-edge noise falls faster than 1/spp


def spectrum_dict(wl, values) -> dict:
    """Mitsuba ``irregular`` spectrum from arrays (wavelengths in nm)."""
    return {"type": "irregular",
            "wavelengths": ", ".join(f"{float(x):.6g}" for x in wl),
            "values": ", ".join(f"{max(float(v), 0.0):.8g}" for v in values)}


def light_spectrum(spec: dict | None, strength: float) -> dict:
    c = spectrum_curve(spec)
    return spectrum_dict(c.wavelength_nm, c.values * float(strength))


def shape_matrix(obj: dict) -> np.ndarray:
    """Local 4x4 scaling that gives a unit Mitsuba primitive the object's size."""
    s = np.eye(4)
    shp = obj["shape"]
    if shp == "rectangle":
        w, h = (obj.get("size") or [1.0, 1.0])[:2]
        s[0, 0], s[1, 1] = w / 2.0, h / 2.0
    elif shp == "cube":
        size = obj.get("size") or [1.0, 1.0, 1.0]
        if len(size) != 3:
            raise InputError("a cube's size needs [x, y, z] in metres", field=f"objects.{obj['name']}.size")
        s[0, 0], s[1, 1], s[2, 2] = (x / 2.0 for x in size)
    elif shp in ("disk", "sphere"):
        r = float(obj.get("radius", 0.5))
        s[0, 0] = s[1, 1] = s[2, 2] = r
    elif shp == "cylinder":
        r = float(obj.get("radius", 0.5))
        s[0, 0] = s[1, 1] = r
        s[2, 2] = float(obj.get("length", 1.0))
    return s


def object_motion(obj: dict, where: str) -> Motion:
    base = Pose.from_spec(obj, where=where)
    return Motion.from_spec(base, obj.get("motion"), where=where)


def moving_meshes(scene: Scene) -> list[tuple[int, dict, Motion]]:
    """``(index, object, motion)`` of every object of ``scene`` that Mitsuba loads as a triangle mesh (a ``cube``
    or a ``mesh`` file) and that moves: the objects the film launch moves by rewriting their vertices and the
    frozen launch as instances."""
    out = []
    for i, obj in enumerate(scene.data["objects"]):
        if obj["shape"] in ("cube", "mesh"):
            motion = object_motion(obj, f"objects.{i}.")
            if not motion.is_static:
                _check_start_pose(scene, obj, motion, f"objects.{i}.")
                out.append((i, obj, motion))
    return out


def _ply_has_normals(fh) -> bool:
    element, props = None, set()
    for n, raw in enumerate(fh):
        line = raw.decode("latin-1").strip()
        if line == "end_header" or n > 10000:
            break
        tok = line.split()
        if tok[:1] == ["element"] and len(tok) > 1:
            element = tok[1]
        elif tok[:1] == ["property"] and element == "vertex":
            props.add(tok[-1])
    return {"nx", "ny", "nz"} <= props


def _obj_keyword(line: bytes, word: bytes) -> bytes | None:
    """The rest of an OBJ ``line`` after its keyword ``word`` followed by a blank or tab (Mitsuba's test), or
    None: leading blanks, tabs and carriage returns are skipped."""
    line = line.lstrip(b" \t\r")
    n = len(word)
    return line[n + 1:] if line[:n] == word and line[n:n + 1] in (b" ", b"\t") else None


_OBJ_CORNER_SEP = re.compile(rb"[ \t\r\0]+")


def _obj_normals(fh) -> tuple[bool, int, int]:
    """(has ``vn`` lines, face corners with a normal, face corners without one) of an OBJ, read as Mitsuba
    3.9's loader (``obj.cpp``) reads a face line: one index triple (vertex, texture, normal) for the whole
    line, each number in a corner overwriting its slot (``/`` moves to the next slot), a corner ending at a
    blank, tab, carriage return or NUL and taking the triple as it then is. A normal index of 0 (or none
    given yet on the line) is no normal. Lines of fewer than three corners make no triangle: not counted."""
    has_vn, with_n, without_n = False, 0, 0
    for line in fh:
        if _obj_keyword(line, b"vn") is not None:
            has_vn = True
            continue
        rest = _obj_keyword(line, b"f")
        if rest is None:
            continue
        key = [0, 0, 0]
        normals = []
        for corner in _OBJ_CORNER_SEP.split(rest.rstrip(b"\n")):
            if not corner:
                continue
            for slot, part in enumerate(corner.split(b"/")[:3]):
                if part.strip():
                    try:
                        key[slot] = int(part)
                    except ValueError:
                        key[slot] = 0
            normals.append(key[2])
        if len(normals) >= 3:
            with_n += sum(1 for n in normals if n != 0)
            without_n += sum(1 for n in normals if n == 0)
    return has_vn, with_n, without_n


@functools.lru_cache(maxsize=64)
def _mesh_file_normals(path: str, stamp: tuple) -> tuple[bool, str | None]:
    """-> (has normals, why the file is refused or None); ``stamp`` (inode, size, times) keys the cache."""
    from pathlib import Path
    with open(path, "rb") as fh:
        if Path(path).suffix.lower() == ".ply":
            return _ply_has_normals(fh), None
        has_vn, with_n, without_n = _obj_normals(fh)
    if has_vn and without_n:
        return True, (f"the OBJ has vertex normals (vn lines) but {without_n} face corner(s) without a normal "
                      f"index (and {with_n} with one): Mitsuba 3.9's loader leaves those normals undefined (other "
                      "garbage from load to load). Give every face corner a normal (f v//vn or f v/vt/vn) or "
                      "drop the vn lines")
    return has_vn, None


def mesh_file_has_normals(path, field: str | None = None) -> bool:
    """Whether Mitsuba loads vertex normals from the mesh file ``path`` (rather than computing them from its
    triangles): a PLY whose ``vertex`` element has ``nx``, ``ny`` and ``nz`` properties (its header is read),
    or an OBJ with ``vn`` lines (scanned line by line; cached per file and its inode, size and times).

    Raises :class:`~sensor.errors.InputError` (naming ``field``, the scene file's field) for a file it cannot
    read, and for an OBJ with ``vn`` lines and any face corner left without a normal (:func:`_obj_normals`),
    whose normal Mitsuba 3.9 leaves undefined (it computes normals only for an OBJ without any ``vn`` line)."""
    from pathlib import Path
    path = Path(path)
    try:
        st = path.stat()
        has, refused = _mesh_file_normals(str(path), (st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns))
    except OSError as exc:
        raise InputError(f"cannot read the mesh file ({exc})", path=path, field=field) from exc
    if refused:
        raise InputError(refused, path=path, field=field)
    return has


def carries_normals(scene: Scene, obj: dict) -> bool:
    """Whether the film launch sets a moving mesh's vertex normals itself at each pose (by the inverse transpose
    of the pose, as Mitsuba's load does: ``renderer.carried_normals``) instead of letting Mitsuba recompute
    them from the moved triangles: for a ``cube`` (Mitsuba makes it with a normal per face) and for a mesh
    file with its own normals (:func:`mesh_file_has_normals`). Either way a moving mesh renders as the same
    mesh standing still in its pose: Mitsuba's load carries the normals it is given and computes the rest
    from the posed triangles."""
    if obj["shape"] == "cube":
        return True
    if obj["shape"] != "mesh":
        return False
    where = next((f"objects.{i}.file" for i, o in enumerate(scene.data["objects"]) if o is obj), "objects.file")
    return mesh_file_has_normals(scene.file(obj["file"], where), where)


def camera_motion(cam: dict) -> Motion:
    base = Pose.from_spec(cam, where="camera.")
    return Motion.from_spec(base, cam.get("motion"), where="camera.")


def check_mesh(path, field: str | None = None) -> int:
    """Load a mesh with trimesh to check it, and its normals as Mitsuba would take them
    (:func:`mesh_file_has_normals`; ``field``: the scene file's field, for its refusal); returns its face
    count."""
    try:
        import trimesh
    except ImportError as exc:
        raise DependencyError("mesh objects need trimesh: pip install trimesh") from exc
    try:
        m = trimesh.load(str(path), force="mesh")
    except Exception as exc:
        raise InputError(f"trimesh cannot read this mesh ({exc})", path=path) from exc
    if not hasattr(m, "faces") or len(m.faces) == 0:
        raise InputError("the mesh has no faces", path=path)
    mesh_file_has_normals(path, field)  # (refuses an OBJ whose normals Mitsuba would leave undefined)
    return int(len(m.faces))


def _check_start_pose(scene: Scene, obj: dict, motion: Motion, where: str) -> None:
    """Refuse a moving mesh whose pose at t = 0 is flat (a scale keyframed through zero there): both launches
    place a moving mesh in its t = 0 pose and move it from there, which needs that pose's inverse."""
    def flat(m):  # a condition number of 1e12 or more: an axis 1e-12 of the rest, or none
        with np.errstate(all="ignore"):
            k = np.linalg.cond(np.asarray(m)[:3, :3])
        return not (np.isfinite(k) and k < 1e12)

    if motion.is_static:
        return
    if flat(motion.matrix(0.0) @ shape_matrix(obj)):
        # the field to change: the size (the shape matrix), else the base pose's scale, else the motion
        field = (f"{where}size" if flat(shape_matrix(obj)) else
                 f"{where}scale" if flat(Pose.from_spec(obj, where=where).matrix() @ shape_matrix(obj)) else
                 f"{where}motion")
        raise InputError("this moving mesh is flat at t = 0: its scale or size is zero, or 1e-12 of the rest, "
                         "along an axis (a keyframed scale through zero there, or a size or scale that "
                         "small). A moving mesh is placed in its t = 0 pose and moved from it, which a flat "
                         "pose cannot give: move the keyframes, or give it a thickness", path=scene.path,
                         field=field)


def bsdf_dict(mi, obj: dict, scene: Scene) -> dict:
    mat = obj.get("material") or {}
    refl = mat.get("reflectance", 0.5)
    if isinstance(refl, dict):
        tex = make_texture(refl, scene.folder)
        r = {"type": "bitmap", "bitmap": mi.Bitmap(tex[:, :, None].astype(np.float32)), "raw": True,
             "filter_type": "bilinear", "wrap_mode": "repeat"}
    else:
        r = {"type": "uniform", "value": float(refl)}
    b = {"type": "diffuse", "reflectance": r}
    if mat.get("two_sided", True):
        b = {"type": "twosided", "material": b}
    return b


def emitter_sampling_weights(scene: Scene, motions: dict | None = None, sky_by_nee: bool = False) -> dict:
    """Next-event-estimation weights ~ each light's rough raw illuminance near the reference; the
    environment's 0 when another light is on.

    Mitsuba picks one emitter per shadow ray, uniformly by default; a dim sky
    and a bright sun then get half the samples each and the sun's pixels get
    a ~100 % relative noise. Weighting by the expected contribution removes
    most of that. Rough estimates suffice (they change the noise, never the mean):
    directional E_perp, point I/d^2, environment pi L, area emitter L A / d^2 (<= pi L).

    The environment (a constant sky) is not sampled by next-event estimation at all when another light is
    on: its light then comes from the BSDF-sampled rays alone (multiple importance sampling gives them full
    weight when the emitter's selection probability is 0), which for a constant sky is cosine sampling on a
    diffuse surface, no worse than the sky's own uniform-sphere sampling; and every shadow ray goes to the
    other lights, so a sun no longer loses a few per cent of its samples to the sky. On the README's scene
    (a sun and a sky of 7 % of its light) that cuts the render variance at 64 spp 4.2x, on translating_object
    2.4x, on room_pan (a panel and a sky) 1.5x, with means equal within their errors
    (``benchmarks/light_sampling.py``, ``tests/render/test_sky_sampling.py``). A sky that is the only light keeps
    its weight (something must be sampled). ``sky_by_nee``: keep the sky's weight ~ pi L as the other lights' (the two strategies mixed;
    for comparison). -> ``{light or object name: weight}``.
    """
    from .photometry import v_integral
    ref = scene.data.get("reference", {})
    if "point" in ref:
        p = np.asarray(ref["point"], np.float64)
    elif "object" in ref:
        o = scene.object(ref["object"])
        p = np.asarray(o.get("position", [0, 0, 0]), np.float64)
    else:
        p = np.zeros(3)
    w = {}
    for j, lt in enumerate(scene.data["lights"]):
        key = lt.get("name") or f"light{j}"
        e = v_integral(spectrum_curve(lt.get("spectrum")), float(lt.get("strength", 1.0)))
        if lt["type"] == "point":
            e /= max(float(np.sum((np.asarray(lt["position"], float) - p) ** 2)), 1e-6)
        elif lt["type"] == "environment":
            e *= np.pi
        w[key] = e
    for obj in scene.data["objects"]:
        if "emitter" in obj:
            em = obj["emitter"]
            e = v_integral(spectrum_curve(em.get("spectrum")), float(em.get("strength", 1.0)))
            sm = shape_matrix(obj)
            area = {"rectangle": 4 * sm[0, 0] * sm[1, 1], "disk": np.pi * sm[0, 0] ** 2,
                    "sphere": 4 * np.pi * sm[0, 0] ** 2, "cube": 8 * (sm[0, 0] * sm[1, 1] + sm[1, 1] * sm[2, 2]
                                                                     + sm[0, 0] * sm[2, 2]),
                    "cylinder": 2 * np.pi * sm[0, 0] * sm[2, 2]}.get(obj["shape"], 1.0)
            d2 = float(np.sum((np.asarray(obj.get("position", [0, 0, 0]), float) - p) ** 2))
            w[obj["name"]] = e * min(area / max(d2, 1e-6), np.pi)
    skies = {key for j, lt in enumerate(scene.data["lights"]) if lt["type"] == "environment"
             for key in [lt.get("name") or f"light{j}"]}
    lit = {k for k, v in w.items() if v > 0}
    if lit - skies and not sky_by_nee:  # another light is on: the sky is left to the BSDF-sampled rays
        w = {k: (0.0 if k in skies else v) for k, v in w.items()}
    total = sum(w.values()) or 1.0
    return {k: float(0.0 if w[k] == 0 and k in skies else max(v / total, 1e-3)) for k, v in w.items()}


def add_xml(mi, scene: Scene, d: dict) -> None:
    """Add the shapes and the non-surface emitters of the scene's Mitsuba XML file to ``d``.

    The XML's sensors and integrator are ignored (the scene file's camera and
    the path tracer are used). Its shapes are static and keep their ids as
    ``xml_<id>``. Point, spot and directional emitters are refused when a
    light level is set, because the irradiance meter cannot see delta lights;
    define those in ``lights`` instead.
    """
    path = scene.file(scene.data["xml"], "xml")
    try:
        from .backend import load_scene
        xs = load_scene(mi, path, from_file=True)
    except Exception as exc:
        raise InputError(f"Mitsuba cannot load this XML scene: {exc}", path=path) from exc
    for j, sh in enumerate(xs.shapes()):
        d[f"xml_{sh.id() or j}"] = sh
    for j, em in enumerate(xs.emitters()):
        if mi.has_flag(em.flags(), mi.EmitterFlags.Surface):
            continue  # area emitters come with their shapes
        if mi.has_flag(em.flags(), mi.EmitterFlags.Delta):
            raise InputError("the XML holds a point/spot/directional emitter; the light level cannot be "
                             "measured for delta lights in XML files: define it under 'lights' instead",
                             path=path, field="xml")
        d[f"xml_emitter_{em.id() or j}"] = em


def to_transform(mi, m: np.ndarray):
    return mi.ScalarTransform4f(np.asarray(m, np.float64).tolist())


def build_dict(mi, scene: Scene, *, spp: int = 4, for_meter: dict | None = None) -> tuple[dict, dict]:
    """The Mitsuba scene dict and the motions of its movable parts {key: (Motion, shape_matrix)}.

    ``for_meter`` (``{"point", "normal", "spp"}``) adds an irradiance-meter disk
    with a V(lambda) film instead of the camera.
    """
    prof = scene.profile
    cam = scene.camera
    f_m = float(mm_to_m(cam["focal_length_mm"]))
    motions = {}
    d = {"type": "scene", "integrator": {"type": "path", "max_depth": int(scene.render["max_depth"])}}
    if for_meter is None:
        wl, phi_v = phi_response(prof.qe)
        wl_e, e_v = lux_response()
        cm = camera_motion(cam)
        motions[SENSOR_KEY] = (cm, np.eye(4))
        d[SENSOR_KEY] = {
            "type": "perspective",
            "fov": fov_x_deg(prof.width, prof.pixel_pitch_m, f_m), "fov_axis": "x",
            "near_clip": 1e-3, "far_clip": 1e4,
            "to_world": to_transform(mi, cm.matrix(0.0)),
            "sampler": {"type": SAMPLER, "sample_count": int(spp)},
            "film": {"type": "specfilm", "width": prof.width, "height": prof.height,
                     "component_format": "float32", "rfilter": {"type": "box"},
                     "Phi": spectrum_dict(wl, phi_v), "E": spectrum_dict(wl_e, e_v)},
        }
    else:
        from .motion import look_at_rotation
        n = np.asarray(for_meter["normal"], np.float64)
        n = n / np.linalg.norm(n)
        p = np.asarray(for_meter["point"], np.float64)
        up = [0, 1, 0] if abs(n[1]) < 0.9 else [1, 0, 0]
        m = np.eye(4)
        r_m = 1e-4
        m[:3, :3] = look_at_rotation([0, 0, 0], n, up) * r_m
        m[:3, 3] = p + n * max(1e-4, 1e-5 * float(np.linalg.norm(p)))
        wl_e, e_v = lux_response()
        d["irradiance_meter"] = {
            "type": "disk", "to_world": to_transform(mi, m),
            "bsdf": {"type": "diffuse", "reflectance": {"type": "uniform", "value": 0.0}},
            "sensor": {"type": "irradiancemeter",
                       "sampler": {"type": "independent", "sample_count": int(for_meter["spp"])},
                       "film": {"type": "specfilm", "width": 1, "height": 1, "component_format": "float32",
                                "rfilter": {"type": "box"}, "E": spectrum_dict(wl_e, e_v)}},
        }
    weights = emitter_sampling_weights(scene, motions)
    for j, lt in enumerate(scene.data["lights"]):
        key = lt.get("name") or f"light{j}"
        if float(lt.get("strength", 1.0)) <= 0:
            continue  # a switched-off light (Mitsuba rejects all-zero spectra)
        spec = light_spectrum(lt.get("spectrum"), lt.get("strength", 1.0))
        if lt["type"] == "directional":
            d[key] = {"type": "directional", "direction": [float(x) for x in lt["direction"]], "irradiance": spec}
        elif lt["type"] == "point":
            d[key] = {"type": "point", "position": [float(x) for x in lt["position"]], "intensity": spec}
        else:
            d[key] = {"type": "constant", "radiance": spec}
        d[key]["sampling_weight"] = weights[key]
    if "xml" in scene.data:
        add_xml(mi, scene, d)
    for i, obj in enumerate(scene.data["objects"]):
        where = f"objects.{i}."
        key = obj["name"]
        if key in d:
            raise InputError(f"object name '{key}' clashes with a light or the camera; rename it",
                             path=scene.path, field=f"{where}name")
        mo = object_motion(obj, where)
        sm = shape_matrix(obj)
        motions[key] = (mo, sm)
        shp = obj["shape"]
        if shp in ("cube", "mesh"):
            _check_start_pose(scene, obj, mo, where)
        od = {"to_world": to_transform(mi, mo.matrix(0.0) @ sm), "bsdf": bsdf_dict(mi, obj, scene)}
        if shp == "mesh":
            f = scene.file(obj["file"], f"{where}file")
            check_mesh(f, f"{where}file")
            od["type"] = f.suffix.lower().lstrip(".")
            od["filename"] = str(f)
        else:
            od["type"] = shp
        if "emitter" in obj:
            em = obj["emitter"]
            od["emitter"] = {"type": "area", "radiance": light_spectrum(em.get("spectrum"), em.get("strength", 1.0)),
                             "sampling_weight": weights[key]}
        d[key] = od
    return d, motions
