"""One loaded Mitsuba scene, moved per frame by parameter updates, rendered to physical irradiance.

:class:`SceneRenderer` loads the scene once (``optimize=False`` so every named
object stays a separate, movable shape), measures the light level once, and
for each time ``t_s``:

1. sets every moving object's ``to_world`` (for meshes in the film launch, their vertex
   positions and normals; in the frozen launch, their instance's transform) and the
   camera's pose from :mod:`.motion` (its ``to_world`` in the film launch; in the frozen launch an
   input of the launch only, Mitsuba's camera being never rendered there);
2. renders the two raw channels with exactly the asked samples per pixel (seeds derived
   from the base seed and the frame time) through its launch (:mod:`.launch`: film or
   frozen), in one launch when the sampler takes that count exactly; optionally a second,
   independent render whose difference gives the frame's per-pixel Monte Carlo variance;
3. converts raw channels to ``Phi`` [e-/(s m^2)] and ``E`` [lux] with
   :func:`.photometry.to_physical`'s factors (:func:`.photometry.physical_factors`: the camera equation,
   per-pixel cos^4), made once per renderer.
"""

from __future__ import annotations

import contextlib
import time

import numpy as np

from sensor.errors import InputError
from sensor.units import mm_to_m, photoelectron_rate

from . import backend
from .builder import SAMPLER, SENSOR_KEY, build_dict, carries_normals, moving_meshes, to_transform
from .launch import DEFAULT_LAUNCH, LAUNCH_TYPES, check_launch, resolve_launch
from .photometry import (apply_factors, cos4_map, direct_raw_e, emitter_scale, physical_factors,
                         warn_if_reference_shadowed)
from .sampling import frame_seeds
from .scene import Scene, spectrum_curve


def _check_frozen_motion(moving: dict) -> None:
    """A launch whose replays do not see a mesh moved by its vertices (the frozen launch,
    :data:`.frozen.MESH_TYPES`): refuse any, so that a change to the builder cannot make its frames silently
    wrong."""
    vertex_moved = [k for k, v in moving.items() if v[0] == "vertices"]
    if vertex_moved:
        raise RuntimeError(f"the frozen launch cannot move {vertex_moved} by their vertices: make them instances "
                           "(frozen.instance_moving_meshes, frozen.MESH_TYPES), or use --launch film")


def carried_normals(m: np.ndarray, n_local: np.ndarray) -> np.ndarray:
    """Unit normals, float32 (N, 3), of a mesh posed by the 4 x 4 transform ``m`` (metres), from its normals
    ``n_local`` (N, 3) in the mesh's own frame: by the inverse transpose of ``m``'s linear part ``A``, as Mitsuba
    carries a mesh's normals through its ``to_world`` at load and an instance's through its transform.

    Computed as ``sign(det A) cof(A) n`` (``A^-T = cof(A) / det A``), so that a pose of zero scale along an axis
    (a keyframed scale passing through 0) gives finite normals; a normal that such a pose maps to zero keeps
    its direction in the mesh's own frame (any unit vector would do: the mesh is flat there)."""
    a = np.asarray(m, np.float64)[:3, :3]
    cof = np.stack([np.cross(a[:, 1], a[:, 2]), np.cross(a[:, 2], a[:, 0]), np.cross(a[:, 0], a[:, 1])], axis=1)
    det = float(np.linalg.det(a))
    n = (n_local @ cof.T) * (-1.0 if det < 0 else 1.0)  # rows: (cof n^T)^T
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    lost = norm[:, 0] == 0.0
    n[lost], norm[lost] = n_local[lost], np.linalg.norm(n_local[lost], axis=1, keepdims=True)
    return (n / np.maximum(norm, 1e-300)).astype(np.float32)


def _buffer_like(params, key: str, values: np.ndarray):
    """``values`` as a flat float32 buffer of the type Mitsuba holds ``params[key]`` in (``mi.Float`` on the JIT
    variants, ``drjit.scalar.ArrayXf`` on the scalar ones, where ``mi.Float`` is a Python float)."""
    return type(params[key])(np.ascontiguousarray(values, dtype=np.float32).ravel())


def _written_keys(moving: dict) -> list[str]:
    """The Mitsuba scene parameters :meth:`SceneRenderer.set_time` writes for the motions ``moving``
    (``{key: (kind, parameter, motion, shape matrix, local)}``): each moving object's ``to_world`` or vertex
    positions, and the vertex normals it carries; none for the frozen launch's camera."""
    keys = []
    for key, (kind, pkey, *_, local) in moving.items():
        if kind == "camera":
            continue
        keys.append(pkey)
        if kind == "vertices" and local[1] is not None:
            keys.append(f"{key}.vertex_normals")
    return keys


def _exact_keys(keys: list[str]) -> list[str]:
    """Patterns that ``SceneParameters.keep`` (which matches regular expressions from a key's start) reads as
    exactly ``keys``: the '.' between an object's name and its parameter would match any character, so that
    ``thing.to_world`` read as a pattern also matches the parameters of an object named ``thing_to_world``."""
    import re
    return [re.escape(k) + r"\Z" for k in keys]


def _mesh_local_frame(params, key: str, m0: np.ndarray, carry: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """(vertices, normals) of the loaded mesh ``key`` in its own frame, undone from ``m0``, its 4 x 4 pose at
    t = 0 (motion times shape matrix), with which the builder placed it. ``normals`` is None unless ``carry``
    (:func:`.builder.carries_normals`) and the mesh has vertex normals.

    Why. The film launch moves a mesh by rewriting its vertices, and Mitsuba then recomputes its vertex normals
    from the triangles unless they are set too. For a mesh file without normals that is what Mitsuba's load
    does for the same mesh standing in that pose. But a mesh given its normals (a ``cube``, a mesh file with
    normals) is loaded with them carried by the inverse transpose of its pose; a recomputation then turned it
    inside out wherever the pose mirrors it (a negative scale: the triangles' winding turns inwards while the
    carried normals point out) and discarded authored normals. The renderer sets those at each pose with
    :func:`carried_normals`."""
    v = np.array(params[f"{key}.vertex_positions"], dtype=np.float64).reshape(-1, 3)
    local = (np.linalg.inv(m0) @ np.c_[v, np.ones(len(v))].T).T[:, :3]
    nkey = f"{key}.vertex_normals"
    n = np.array(params[nkey], dtype=np.float64).reshape(-1, 3) if carry and nkey in params else np.zeros((0, 3))
    if len(n) != len(v) or len(n) == 0:
        return local, None
    return local, n @ m0[:3, :3]  # (A0^T n^T)^T: undoes the load's A0^-T (up to each normal's length)


class SceneRenderer:
    """Render a :class:`~.scene.Scene` at any time to physical focal-plane irradiance.

    Parameters
    ----------
    scene : Scene
    variant : str, optional
        Mitsuba variant (default: chosen by :func:`.backend.mitsuba`).
    calibration : dict, optional
        A light-level measurement made earlier (:meth:`measure_reference`, stored in a
        frames folder's render state): reused instead of measuring again, so frames of a
        resumed render share one emitter scale.
    launch : {"auto", "film", "frozen"}
        How each render is launched (:mod:`.launch`): ``film`` calls the integrator's ``render``
        into Mitsuba's spectral film; ``frozen`` records the launch once with ``drjit.freeze`` and
        replays it (:mod:`.frozen`): the same channels in the same units, another Monte Carlo
        estimate, without the per-launch tracing on the host; ``auto`` (the default) as
        :func:`.launch.resolve_launch` chooses. :attr:`launch_kind` is the launch taken, :attr:`frame_launch`
        the :class:`.launch.Launch` that renders.
    """

    def __init__(self, scene: Scene, variant: str | None = None, calibration: dict | None = None,
                 launch: str = DEFAULT_LAUNCH):
        check_launch(launch)
        self.scene = scene
        self.mi = mi = backend.mitsuba(variant)
        self.variant = mi.variant()
        self.launch_kind = resolve_launch(launch, self.variant, scene)
        launch_type = LAUNCH_TYPES[self.launch_kind]
        t0 = time.perf_counter()
        d, self.motions = build_dict(mi, scene)
        # {key: (M(0) S)^-1} of the meshes the launch moves as instances; bind: the launch for the loaded scene
        instanced, bind = launch_type.prepare(mi, scene, d, self.motions)
        try:
            self.mi_scene = backend.load_scene(mi, d)
        except Exception as exc:
            raise InputError(f"Mitsuba could not build the scene: {exc}", path=scene.path) from exc
        self.params = mi.traverse(self.mi_scene)
        self.sensor = self.mi_scene.sensors()[0]
        import drjit
        self._dr = drjit
        cam_motion, cam_shape = self.motions[SENSOR_KEY]
        self._cam_m = cam_motion.matrix(0.0) @ cam_shape  # the camera's pose at the time set (an input of a launch)
        self.frame_launch = bind(self.mi_scene)
        # the frozen launch itself (None for the film launch): tests and benchmarks drive its recording directly
        self._frozen = self.frame_launch if self.launch_kind == "frozen" else None
        self._moving = {}
        self._t_set = None  # the time the moving objects are at (set_time)
        self.n_launches = 0  # render launches so far (benchmarks count the verification launches with it)
        self._kept = None  # {(t_s, spp): (seed, raw Phi)} of single-launch renders, while keep_renders() is on
        self._reusable = None  # what keep_renders() kept, until the first verified frame
        carried = {obj["name"] for _, obj, _ in moving_meshes(scene) if carries_normals(scene, obj)}
        for key, (motion, shape_m) in self.motions.items():
            if motion.is_static:
                continue
            pkey = f"{key}.to_world"
            if key in instanced and pkey in self.params:  # to_world = frozen.relative_motion(t)
                self._moving[key] = ("instance", pkey, motion, shape_m, instanced[key])
            elif pkey in self.params:
                self._moving[key] = ("to_world", pkey, motion, shape_m, None)
            elif f"{key}.vertex_positions" in self.params:
                carry = key in carried
                self._moving[key] = ("vertices", f"{key}.vertex_positions", motion, shape_m,
                                     _mesh_local_frame(self.params, key, motion.matrix(0.0) @ shape_m, carry))
            else:
                raise InputError(f"object '{key}' cannot be moved: Mitsuba exposes neither to_world nor "
                                 "vertex_positions for it", path=scene.path, field=f"objects.{key}.motion")
        if not launch_type.sees_vertex_rewrites:
            _check_frozen_motion(self._moving)
        if launch_type.camera_pose_is_input and SENSOR_KEY in self._moving:
            # the launch traces its own primary rays from the camera's pose (self._cam_m, an input of each
            # launch); Mitsuba's camera is never rendered, and its to_world stays as loaded: a camera-only
            # motion updates nothing in Mitsuba's scene
            self._moving[SENSOR_KEY] = ("camera", None) + self._moving[SENSOR_KEY][2:]
        # the scene parameters set_time writes, and only those: Mitsuba's update then walks just these. Reading a
        # parameter makes Mitsuba check it at the next update (the loaded normals read above, also where they are
        # not carried): an update first settles those reads, so that no key dropped here is looked for later
        self.params.update()
        self.params.keep(_exact_keys(_written_keys(self._moving)))
        cam = scene.camera
        prof = scene.profile
        self.height, self.width = prof.height, prof.width
        self.f_number = float(cam["f_number"])
        self.transmission = float(cam["transmission"])
        self.focal_length_m = float(mm_to_m(cam["focal_length_mm"]))
        self.cos4 = cos4_map(prof.height, prof.width, prof.pixel_pitch_m, self.focal_length_m)
        self.load_s = time.perf_counter() - t0
        self.reference = self._reference_point()
        if calibration is not None:  # measured when the folder's render started: reused as stored
            self.calibration = dict(calibration)
        else:
            self.calibration = self.measure_reference()
            warn_if_reference_shadowed(self.calibration, scene.path)
        self.k = emitter_scale(scene.illuminance_lux, self.calibration["raw_e_total"])
        # per-pixel (Phi, E) factors of .photometry.to_physical, fixed for this renderer: made once, not per frame
        self._factors = physical_factors(self.k, self.f_number, self.transmission, self.cos4)

    # --------------------------------------------------------------- motion
    @property
    def is_static(self) -> bool:
        return not self._moving

    def set_time(self, t_s: float) -> None:
        """Move every moving object and the camera to their poses at ``t_s`` [s].

        A call at the time already set does nothing: the poses would be the same, and the update
        would make Mitsuba rebuild its ray-tracing structure and wait for the kernels in flight
        (the frame and its verification launch, or the launches of an spp taken in parts, share a time).
        With the frozen launch the camera's pose is an input of the launch only (Mitsuba's camera is never
        rendered there): a scene in which only the camera moves updates nothing in Mitsuba (on a 2-core
        CPU ``room_pan``'s scene update takes 0.15 ms a frame instead of about 0.75 ms;
        ``benchmarks/render_launch.py``).
        """
        if not self._moving or t_s == self._t_set:
            return
        mi = self.mi
        written = False
        for key, (kind, pkey, motion, shape_m, local) in self._moving.items():
            m = motion.matrix(t_s) @ shape_m
            if key == SENSOR_KEY:
                self._cam_m = m
            if kind == "camera":  # the frozen launch's camera: its pose is an input of the launch, not of Mitsuba
                continue
            written = True
            if kind == "instance":  # from the mesh's pose at t = 0 to the one at t_s (frozen.relative_motion)
                self.params[pkey] = to_transform(mi, m @ local)
            elif kind == "to_world":
                self.params[pkey] = to_transform(mi, m)
            else:  # the film launch's vertex rewrite; authored normals carried along (_mesh_local_frame)
                v_local, n_local = local
                v = (m @ np.c_[v_local, np.ones(len(v_local))].T).T[:, :3]
                self.params[pkey] = _buffer_like(self.params, pkey, v)
                if n_local is not None:
                    nkey = f"{key}.vertex_normals"
                    self.params[nkey] = _buffer_like(self.params, nkey, carried_normals(m, n_local))
                    # (the scalar variants skip a parameter set to equal values, and would then recompute
                    # the normals for the moved positions: under a translation the carried ones are equal)
                    self.params.set_dirty(nkey)
        if written:
            self.params.update()
        self._t_set = t_s

    # ----------------------------------------------------------- rendering
    def launch(self, t_s: float, seed: int, spp: int):
        """Start one render at ``t_s`` with ``spp`` samples per pixel (:meth:`_render_call`); the launched render
        (the film tensor, or the frozen launch's sums), not yet waited for.

        Dr.Jit's LLVM backend runs the kernel asynchronously: :meth:`channels` waits for it. A second
        render launched before waiting for the first (a frame and its verification launch) does not
        overlap with it, though: the second launch waits for the first kernel before it traces (the two
        share the sensor's film), so launching both first costs nothing and gains nothing (pairs timed both
        ways: 1.00x).
        """
        self.set_time(t_s)
        self.n_launches += 1
        return self._render_call(int(seed), int(spp))

    def _render_call(self, seed: int, spp: int):
        """One render of the loaded scene by its launch (:meth:`.launch.Launch.launch`), at the camera's pose."""
        return self.frame_launch.launch(seed, spp, self._cam_m)

    def channels(self, img) -> tuple[np.ndarray, np.ndarray]:
        """(Phi_raw, E_raw), float64 (H, W), of a render from :meth:`launch` (waits for its kernel)."""
        ch = self.frame_launch.channels(img)
        return ch["Phi"], ch["E"]

    def render_raw(self, t_s: float, seed: int, spp: int) -> tuple[np.ndarray, np.ndarray]:
        """Raw film channels (Phi_raw, E_raw), float64 (H, W), at ``t_s`` with ``spp`` samples per pixel."""
        raw_p, raw_e = self.channels(self.launch(t_s, seed, spp))
        if self._kept is not None:
            self._kept[(float(t_s), int(spp))] = (int(seed), raw_p)
        return raw_p, raw_e

    @contextlib.contextmanager
    def keep_renders(self):
        """Keep the raw Phi of each :meth:`render_raw` made inside (the last one per time and spp).

        The render job keeps the pilot's renders at t = 0: when one was made at the frame's spp in one
        launch, the first frame (also at t = 0) takes it as the independent second render of its noise
        verification (:meth:`render_frame`) instead of launching one more render of the same kind.
        """
        self._kept = {}
        try:
            yield self
        finally:
            kept, self._kept = self._kept, None
            self._reusable = kept

    def render_block(self, times_s, seed: int, spp: int) -> list[tuple[np.ndarray, np.ndarray]]:
        """Raw channels (Phi_raw, E_raw), float64 (H, W), of the frames at ``times_s`` in one launch of the frozen
        launch (:meth:`.frozen.FrozenLaunch.launch_block`): a scene in which only the camera moves
        (:func:`.frozen.block_obstacle`), ``spp`` a count the sampler takes exactly, at most
        :meth:`.frozen.FrozenLaunch.block_size` frames."""
        poses = []
        for t in times_s:
            self.set_time(float(t))
            poses.append(np.array(self._cam_m, np.float64))
        self.n_launches += 1
        fl = self.frame_launch
        return [(c["Phi"], c["E"]) for c in fl.block_channels(fl.launch_block(int(seed), int(spp), poses))]

    def effective_spp(self, spp: int) -> int:
        """The sample count the (stratified) sampler really takes for a request of ``spp`` (rounds up)."""
        cache = self.__dict__.setdefault("_spp_cache", {})
        spp = max(1, int(spp))
        if spp not in cache:
            s = self.mi.load_dict({"type": SAMPLER, "sample_count": spp})
            cache[spp] = int(s.sample_count())
        return cache[spp]

    def render_pixels(self, t_s: float, seeds, spp: int, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Raw channels (Phi_raw, E_raw), float64 (n,), of the pixels ``pixels`` (flat indices) at ``t_s`` with
        exactly ``spp`` samples each (:meth:`launch_counts` for that many pixels, one seed a launch); the frozen
        launch only (:meth:`.frozen.FrozenLaunch.launch_pixels`)."""
        pixels = np.asarray(pixels, np.int64).ravel()
        from .frozen import max_padded_pixels
        counts = self.launch_counts(spp, n_pixels=max_padded_pixels(pixels.size))
        self.set_time(t_s)
        fl = self.frame_launch
        launched = []
        for n, s in zip(counts, seeds):
            self.n_launches += 1
            launched.append((n, fl.launch_pixels(int(s), n, self._cam_m, pixels)))
        acc_p = acc_e = 0.0
        for n, lh in launched:
            v = fl.pixel_values(lh)
            acc_p = acc_p + v["Phi"] * n
            acc_e = acc_e + v["E"] * n
        return np.asarray(acc_p, np.float64) / spp, np.asarray(acc_e, np.float64) / spp

    def launch_counts(self, spp: int, n_pixels: int | None = None) -> list[int]:
        """Sample counts of the launches that together take exactly ``spp`` samples per pixel (of ``n_pixels``
        pixels a launch; default: the whole frame).

        One launch when the sampler takes ``spp`` exactly (always so for the noise budget's
        choice); otherwise the largest exact counts first (e.g. 17 -> [16, 1]). Where the launch takes at
        most so many samples (:meth:`.launch.Launch.max_samples`; the frozen launch's memory is 8 bytes a
        sample, :data:`.frozen.MAX_SAMPLES_PER_LAUNCH`) and one sample per pixel fits, a larger count is
        taken in ``k`` parts of about ``spp / k`` each, the fewest that fit, split the same way (e.g. 1024 spp
        at 250 x 400 -> [506, 506, 12] with the stratified sampler; equal parts share one recording).
        """
        from .noise import exact_below
        cache = self.__dict__.setdefault("_launch_cache", {})
        spp = max(1, int(spp))
        n_pix = self.scene.profile.height * self.scene.profile.width if n_pixels is None else int(n_pixels)
        if (spp, n_pix) not in cache:
            part = spp
            most = self.frame_launch.max_samples()
            if most is not None:
                cap = max(1, most // n_pix)
                part = -(-spp // -(-spp // cap))  # ceil(spp / k), k = ceil(spp / cap) parts
            out, left = [], spp
            while left > 0:
                n = exact_below(self.effective_spp, min(left, part))
                out.append(n)
                left -= n
            cache[(spp, n_pix)] = out
        return cache[(spp, n_pix)]

    def _launch_exact(self, t_s: float, seeds, spp: int) -> list:
        return [(n, self.launch(t_s, s, n)) for n, s in zip(self.launch_counts(spp), seeds)]

    def _finish_exact(self, launched: list, spp: int) -> tuple[np.ndarray, np.ndarray]:
        if len(launched) == 1:
            return self.channels(launched[0][1])
        acc_p = acc_e = 0.0
        for n, img in launched:
            p, e = self.channels(img)
            acc_p = acc_p + p * n
            acc_e = acc_e + e * n
        return acc_p / spp, acc_e / spp

    def render_exact(self, t_s: float, seeds, spp: int) -> tuple[np.ndarray, np.ndarray]:
        """Raw channels at ``t_s`` with exactly ``spp`` samples per pixel (:meth:`launch_counts`, one seed each)."""
        return self._finish_exact(self._launch_exact(t_s, seeds, spp), spp)

    def _reused_render(self, t_s: float, spp: int, own_seeds) -> tuple[int, np.ndarray] | None:
        """A kept pilot render (seed, raw Phi) at ``t_s`` and ``spp`` made in one launch, or None.

        Only the first verified frame after :meth:`keep_renders` is offered the kept renders (the
        render job's first frame, at t = 0 like the pilot); they are dropped then."""
        kept, self._reusable = self._reusable, None  # offered to the first verified frame only
        if not kept or len(self.launch_counts(spp)) != 1:
            return None
        hit = kept.get((float(t_s), int(spp)))
        if hit is None or hit[0] in own_seeds:  # never the frame's own seed (they would not be independent)
            return None
        return hit

    def render_frame(self, t_s: float, base_seed: int, spp: int, variance: bool = True) -> dict:
        """Physical frame at ``t_s`` [s]: ``phi`` [e-/(s m^2)], ``lux`` [lux], ``phi_var`` (MC variance of phi).

        The frame takes exactly ``spp`` samples per pixel, in one launch whenever the sampler
        takes that count exactly (:meth:`launch_counts`). With ``variance=True`` a second,
        independent render of the same spp is made; ``phi_var = (a - b)^2 / 2`` is then the
        per-pixel variance of the returned frame (which is the first render). Without it
        ``phi_var`` is None and the frame costs one render. Both renders are launched before
        either is waited for (no overlap: see :meth:`launch`). When a
        render of the same time and spp in one launch was kept from the pilot
        (:meth:`keep_renders`), it is the second render (``variance_seeds`` then names its seed)
        and no launch is added.
        """
        counts = self.launch_counts(spp)
        seeds = frame_seeds(base_seed, t_s, 2 * len(counts))
        sa, sb = seeds[:len(counts)], seeds[len(counts):]
        launched_a = self._launch_exact(t_s, sa, spp)
        reused = self._reused_render(t_s, spp, sa) if variance else None
        launched_b = self._launch_exact(t_s, sb, spp) if variance and reused is None else None
        raw_p, raw_e = self._finish_exact(launched_a, spp)
        phi, lux = apply_factors(raw_p, raw_e, self._factors)  # to_physical, its factors made once
        fp = self._factors[0]
        out = {"time_s": float(t_s), "phi": phi, "lux": lux, "seeds": list(sa), "spp": int(spp), "phi_var": None}
        if variance:
            if reused is not None:
                sb, pb = [reused[0]], reused[1]
            else:
                pb, _ = self._finish_exact(launched_b, spp)
            out["phi_var"] = (raw_p - pb) ** 2 / 2.0 * fp ** 2
            out["variance_seeds"] = list(sb)
        return out

    def rate_e(self, phi):
        """Phi [e-/(s m^2)] -> rate_e [e-/interval] for the scene's profile (sensor.units.photoelectron_rate)."""
        p = self.scene.profile
        return photoelectron_rate(phi, p.pixel_pitch_m, p.fill_factor, p.interval_s)

    def rate_scale(self) -> float:
        """rate_e per unit Phi: pitch^2 * fill * T_r [m^2 s]."""
        return float(photoelectron_rate(np.ones(1), self.scene.profile.pixel_pitch_m, self.scene.profile.fill_factor,
                                        self.scene.profile.interval_s)[0])

    # ----------------------------------------------------------- light level
    def _reference_point(self) -> dict:
        ref = self.scene.data["reference"]
        if "object" in ref:
            motion, shape_m = self.motions[ref["object"]]
            m = motion.matrix(0.0) @ shape_m
            n = m[:3, 2] / np.linalg.norm(m[:3, 2])
            return {"point": m[:3, 3].tolist(), "normal": n.tolist(), "object": ref["object"]}
        n = np.asarray(ref["normal"], np.float64)
        return {"point": [float(x) for x in ref["point"]], "normal": (n / np.linalg.norm(n)).tolist()}

    def _visible(self, point, normal, direction, dist) -> bool:
        mi = self.mi
        o = np.asarray(point) + 1e-4 * np.asarray(normal)
        ray = mi.Ray3f(mi.Point3f(*[float(x) for x in o]), mi.Vector3f(*[float(x) for x in direction]))
        if np.isfinite(dist):
            ray.maxt = float(dist) * (1 - 1e-4)
        hit = self.mi_scene.ray_test(ray)
        return not bool(np.asarray(hit).reshape(-1)[0])

    def _meter_mean(self, meter_scene, meter_sensor, seed: int, n: int) -> float:
        """Mean of ``n`` irradiance-meter samples (raw V-weighted illuminance), summed on the host.

        What ``mi.render`` of the meter computes (the meter's ray and wavelengths, the path integrator,
        the single-channel V(lambda) film: a sample's value is the mean over its wavelengths of ray
        weight x radiance; the 1 x 1 box-filtered film divides by the sample count), but each sample's
        value is brought to the host and the sum is a float64 ``numpy`` sum in sample order: the same
        bits on every run and thread count of a back end (reproducible on each of CPU and GPU; the
        two need not agree to the bit). The film's per-channel factor channel(lambda)/SRF(lambda),
        which ``specfilm`` applies, is 1 here: the meter's film has one channel, tabulated on the
        integer-nm grid of ``photometry.lux_response`` (measured within 1.2e-7 of 1); a film with
        more channels would need it. Scalar variants take one sample per call, summed in the same way.
        """
        dr, integrator = self._dr, meter_scene.integrator()
        sampler = meter_sensor.sampler().clone()

        def one_wave():  # the meter's samples, as many as the sampler's wavefront: (wavelengths, samples)
            wav_u = sampler.next_1d()
            pos_u = sampler.next_2d()
            ap_u = sampler.next_2d()
            with dr.suspend_grad():
                ray, weight = meter_sensor.sample_ray_differential(0.0, wav_u, pos_u, ap_u)
                radiance, valid, _ = integrator.sample(meter_scene, sampler, ray)
                value = dr.select(valid, weight * radiance, 0.0)
            return np.asarray(value, dtype=np.float64)
        if dr.is_jit_v(self.mi.Float):  # LLVM / CUDA: all n samples in one wavefront
            sampler.seed(seed, n)
            v = one_wave().reshape(-1, n)  # Dr.Jit's layout: wavelengths first
            return float(v.mean(axis=0).sum() / n)
        sampler.seed(seed, 1)  # scalar variants: one sample per call, summed in the same order
        total = 0.0
        for _ in range(n):
            total += float(one_wave().mean())
            sampler.advance()
        return total / n

    def measure_reference(self) -> dict:
        """Raw illuminance (V-weighted) at the reference at t = 0: analytic delta lights + irradiance meter.

        Deterministic on every back end (:meth:`_meter_mean`): the meter's samples come from fixed
        seeds, each sample's value is computed on its own (the meter's ray, the path integrator,
        the V(lambda) film's weight), and the values are summed on the host in float64 in a fixed
        order. ``mi.render`` would sum them into the meter's one pixel with atomic adds, whose order
        varies with the thread schedule (LLVM with several threads) and always on a GPU, so the
        float32 sum changed in its last bits, and an event-driven spike simulator turns that into
        different spike trains. Raises InputError when no light reaches the reference.
        """
        self.set_time(0.0)
        p, n = self.reference["point"], self.reference["normal"]
        direct = 0.0
        parts = []
        for j, lt in enumerate(self.scene.data["lights"]):
            if lt["type"] not in ("directional", "point"):
                continue
            e, to_light, dist = direct_raw_e(lt, spectrum_curve(lt.get("spectrum")), p, n)
            vis = e > 0 and self._visible(p, n, to_light, dist)
            direct += e if vis else 0.0
            parts.append({"light": lt.get("name") or f"light{j}", "raw_e": e if vis else 0.0, "visible": bool(vis),
                          "raw_e_unshadowed": e})
        mi = self.mi
        spp = int(self.scene.render["meter_spp"])
        d, _ = build_dict(mi, self.scene, for_meter={"point": p, "normal": n, "spp": spp})
        meter_scene = backend.load_scene(mi, d)
        meter_sensor = [s for s in meter_scene.sensors() if "irradiancemeter" in type(s).__name__.lower()
                        or "IrradianceMeter" in str(s)]
        meter_sensor = meter_sensor[0] if meter_sensor else meter_scene.sensors()[-1]
        # the meter measures E_raw with two independent halves -> its own MC error
        ss = np.random.SeedSequence([int(self.scene.render["seed"]), 0x5EED]).generate_state(2, dtype=np.uint32)
        vals = [self._meter_mean(meter_scene, meter_sensor, int(s), spp // 2) for s in ss]
        meter = 0.5 * (vals[0] + vals[1])
        meter_se = abs(vals[0] - vals[1]) / 2.0
        total = direct + meter
        if not (np.isfinite(total) and total > 0):
            raise InputError(f"no light reaches the reference (raw illuminance {total!r}): check the "
                             "lights' strengths and directions, the reference normal and occluders",
                             path=self.scene.path, field="reference")
        return {"raw_e_direct_delta": direct, "raw_e_meter": meter, "raw_e_meter_stderr": meter_se,
                "raw_e_total": total, "delta_lights": parts, "meter_spp": spp, **self.reference}
