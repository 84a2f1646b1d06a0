"""The frozen launch: one frame's render recorded once with ``drjit.freeze`` and replayed after.

Why. Every ``mi.render`` call traces the whole integrator anew on the host (1.4 ms of a 3.7 ms
frame at 32 x 48 and 16 spp on a 2-core CPU; 96 % of a small frame on a GPU), and
``drjit.freeze``, which records a launch once and replays its kernels, fails on Mitsuba 3.9.1 as
soon as a perspective camera with a ``specfilm`` is among its inputs ("VarType mismatch 8 != 14",
even for a function that does nothing with it), and ``specfilm`` allocates its image block inside
every render, which a recording cannot replay (mitsuba3 issue 1810; the fix there, PR 1816, went
into ``hdrfilm`` only).

What. The scene is loaded with a plain ``hdrfilm`` camera (never rendered), and this module does
what the camera and the ``specfilm`` did, in Dr.Jit, around the scene integrator's ``sample``:

1. **Primary rays** of Mitsuba's ``perspective`` camera (pinhole, ``fov_axis`` x): the sample
   position ``(sx, sy)`` in [0, 1]^2 of the film gives the camera-space direction
   ``((1 - 2 sx) t, (1 - 2 sy) t H / W, 1)``, ``t = tan(fov_x / 2)``, moved by the camera's
   ``to_world``; the origin is put on the near clip plane as Mitsuba does. The sampler's
   dimensions are drawn in Mitsuba's order (pixel position, then wavelength).
2. **Wavelengths**: four per sample, stratified (``u + i/4``), each through a tabulated inverse
   distribution: ``M`` = :data:`N_QUANTILES` wavelengths ``lambda_j`` that cut the summed film
   responses (piecewise linear on a 1 nm grid) into equal parts; ``u`` in ``[j/M, (j+1)/M)``
   falls uniformly in ``[lambda_j, lambda_(j+1))``, so the density drawn from is
   ``p = 1 / (M (lambda_(j+1) - lambda_j))`` there (two gathers a wavelength). Each channel then gets
   ``mean_i srf_c(lambda_i) L(lambda_i) / p(lambda_i)``: an unbiased estimate of
   ``int srf_c(lambda) L(lambda) d lambda``, the quantity ``specfilm`` estimates (with its own
   density), with ``srf_c`` zero outside its own first and last wavelength as Mitsuba's ``irregular``
   spectrum is. Same expectation, another Monte Carlo estimate: frames are not bitwise those of the
   film launch.
3. **Per-pixel sums** with ``drjit.block_reduce`` (its evaluated mode) over each pixel's ``spp``
   consecutive samples (box filter: every sample lands in its own pixel, weight 1), divided by
   ``spp``. No atomic adds: the sum's order is fixed, so a GPU gives the same frame on every run
   too (on an H100 every value of 5 frames was equal in two runs at 64, 256 and 1024 spp, where the
   film launch's atomic sums left 1.4-64 % of the values differing). The price: the samples' channel
   values are held in memory before the sums, 8 bytes a sample, so the renderer takes a frame of more
   than :data:`MAX_SAMPLES_PER_LAUNCH` samples (512 MiB of them; 671 spp at 250 x 400) in several
   launches of at most that many, each with its own seed
   (:meth:`render2spike.render.renderer.SceneRenderer.launch_counts`); a launch of 2^32 samples or
   more (a sensor of that many pixels at 1 spp) is refused.
4. **Moving meshes as instances.** The film launch moves a mesh (a ``cube`` or a mesh file) by
   rewriting its vertices. Replays after such a rewrite traced a stale acceleration structure on
   the LLVM variant: the bundled ``translating_object`` had wrong geometry in 4 of 12 frames
   (``benchmarks/frozen_replay_check.py --as-vertices``; on an H100 the CUDA variant's replays were
   right). So the frozen launch loads each moving mesh, at its t = 0 pose, as an ``instance`` of a
   one-shape ``shapegroup``, and moves the instance by the transform from that pose to the current one,
   as it moves a rectangle or the camera (:func:`instance_moving_meshes`, :func:`relative_motion`):
   every replay then equals the unfrozen function, on both back ends, and the mesh's smooth normals are
   made from the same world-space vertices as the film launch's. A moving mesh that emits light, or
   whose motion changes its shape (a scale that changes over time), cannot move that way: ``auto``
   takes the film launch for its scene (:func:`frozen_obstacle`).

5. **Keyframes in blocks.** Where only the camera moves (:func:`block_obstacle`), :meth:`FrozenLaunch.launch_block`
   renders several keyframes in one launch: the poses are one more input, gathered per sample by its frame.

The result is the pair of raw channels (``Phi``, ``E``) that the film launch gives, in the same
units, so :mod:`.photometry` applies unchanged. :class:`FrozenLaunch` implements the launch interface
(:class:`.launch.Launch`); ``launch="auto"`` takes it on Mitsuba's LLVM and CUDA variants
(:func:`.launch.resolve_launch`); the scalar variants, which cannot record, take the film launch.
:class:`FrozenLaunch` keeps three frozen functions (a whole frame, a list of pixels, a block of frames); a whole
frame goes through the list's gather, so the two share a kernel at each sample count. ``frozen=False`` runs the
same functions without freezing (the tests hold the two bitwise equal).
"""

from __future__ import annotations

import math

import numpy as np

#: spacing of the response tables [nm]
GRID_STEP_NM = 1.0
#: equal-probability parts of the wavelength density (``lambda_j`` table of ``N_QUANTILES + 1`` points)
N_QUANTILES = 4096
#: the frozen launch's estimator, in the frames' scene hash (:func:`.launch.settings_of`) and recorded as
#: ``launch_estimator``: a change to how it samples or sums (grid, table, order of the sampler's dimensions,
#: how a sample count is split into launches, how moving meshes are instanced) must bump it, so that no folder
#: mixes frames of two estimators
ESTIMATOR_VERSION = 3
#: the most samples one frozen launch takes (2^26: 512 MiB of held channel values, 8 bytes a sample); a frame
#: that needs more is taken in several launches of at most this many, each with its own seed
#: (:meth:`render2spike.render.renderer.SceneRenderer.launch_counts`). A constant, not the machine's memory:
#: the split is part of the estimator, so frames do not depend on where they were rendered
MAX_SAMPLES_PER_LAUNCH = 1 << 26
#: the most keyframes one block launch renders (:meth:`FrozenLaunch.launch_block`), where only the camera moves
#: (:func:`block_obstacle`); fewer where they would hold more than :data:`MAX_SAMPLES_PER_LAUNCH` samples. Part of
#: the frames' scene hash there (:func:`.launch.settings_of`): which keyframes share a launch decides their samples
BLOCK_KEYFRAMES = 16
#: how a block is seeded and which of its samples are whose frame; with :data:`BLOCK_KEYFRAMES`, part of the frames'
#: scene hash where blocks apply: a change must bump it, so that no folder mixes frames of two block layouts
BLOCK_VERSION = 2
#: a launch of a list of pixels (:meth:`FrozenLaunch.launch_pixels`) pads the list (:func:`padded_pixels`) to a
#: multiple of this many pixels at least, and of 1/PIXEL_STEPS of the list's power of two: the padded length is part
#: of what is recorded, so lists of nearly equal length share one recording, and the padding (whose samples are
#: traced and dropped) costs at most 1/PIXEL_STEPS of the samples
PIXEL_BUCKET = 32
PIXEL_STEPS = 32
#: a list may also take a length already recorded at its spp when that is at most this fraction longer
#: (:meth:`FrozenLaunch.pixel_length`): a list whose length wanders (a moving object's pixels) then replays a few
#: recordings instead of making a new one (a trace and a garbage collection, 70-100 ms on 2 cores) every few frames
PIXEL_SLACK = 0.125


def _pixel_step(n: int) -> int:
    return max(PIXEL_BUCKET, (1 << (max(1, int(n)).bit_length() - 1)) // PIXEL_STEPS)


def padded_pixels(n: int) -> int:
    """The length a list of ``n`` pixels is padded to for :meth:`FrozenLaunch.launch_pixels` the first time at
    its spp: a multiple of ``max(PIXEL_BUCKET, 2^floor(log2 n) / PIXEL_STEPS)`` (e.g. 2310 -> 2368: 2.5 %
    padding; 100 -> 128)."""
    n = max(1, int(n))
    step = _pixel_step(n)
    return -(-n // step) * step


def max_padded_pixels(n: int) -> int:
    """The longest a list of ``n`` pixels is padded to (:meth:`FrozenLaunch.pixel_length`): the largest multiple
    of :func:`padded_pixels`' step within ``n (1 + PIXEL_SLACK)``, or that function's length. What the launch's
    memory is planned for (:meth:`.renderer.SceneRenderer.launch_counts`)."""
    n = max(1, int(n))
    step = _pixel_step(n)
    return max(padded_pixels(n), int(math.floor(n * (1.0 + PIXEL_SLACK))) // step * step)


#: Mitsuba shape plugins that are triangle meshes (the scene builder's ``cube`` and mesh files). The film
#: launch moves such an object by rewriting its vertices, which a frozen launch's replays do not see: on
#: Mitsuba 3.9.1's LLVM variant they traced against a stale acceleration structure (wrong geometry in a third
#: or more of the frames of ``translating_object``, unless Dr.Jit happened to record again). The frozen launch
#: moves a moving mesh as an instance of a shape group instead (:func:`instance_moving_meshes`)
MESH_TYPES = ("cube", "ply", "obj", "serialized")
#: evenly spread frame times over the clip at which :func:`frozen_obstacle` checks that a moving mesh's motion
#: relative to its t = 0 pose is rigid, besides every keyframe time and the midpoints between keyframes (where
#: a scale that differs between keyframes shows); parametric motions (rotate, translate) are rigid
RIGID_CHECK_TIMES = 65


def relative_motion(motion, shape_m: np.ndarray, t_s: float) -> np.ndarray:
    """A mesh's 4 x 4 transform from its pose at t = 0 to its pose at ``t_s`` [s]: ``M(t) S (M(0) S)^-1``
    (``motion``: the builder's :class:`~render2spike.render.motion.Motion`, ``shape_m``: its shape matrix
    ``S``). The identity at t = 0; rigid (a rotation and a translation) for the motions that move a body
    without deforming it."""
    return motion.matrix(float(t_s)) @ shape_m @ np.linalg.inv(motion.matrix(0.0) @ shape_m)


def _is_rigid(m: np.ndarray, tol: float = 1e-6) -> bool:
    a = m[:3, :3]
    return bool(np.allclose(a.T @ a, np.eye(3), rtol=0.0, atol=tol) and np.linalg.det(a) > 0)


def frozen_obstacle(scene) -> str | None:
    """Why the frozen launch cannot render ``scene``, or None.

    The frozen launch moves a mesh as an instance of its t = 0 pose (:func:`instance_moving_meshes`), so
    it cannot move a mesh that emits light (Mitsuba cannot instance an emitter) nor one whose motion
    changes its shape (a scale that changes over time; checked at every keyframe time, the midpoints
    between keyframes and :data:`RIGID_CHECK_TIMES` times over the clip): an instance's transform would
    carry the t = 0 shading normals along, where the film launch lets Mitsuba recompute the normals of a mesh
    file without normals of its own from the deformed vertices, as the mesh standing in that pose would get
    them (``builder.carries_normals``)."""
    from .builder import moving_meshes, shape_matrix
    even = np.linspace(0.0, float(scene.duration_s), RIGID_CHECK_TIMES)
    for i, obj, motion in moving_meshes(scene):
        where = f"object '{obj['name']}' (objects.{i})"
        if "emitter" in obj:
            return (f"{where} is a moving mesh that emits light, which the frozen launch cannot move (it moves "
                    "meshes as instances; Mitsuba cannot instance an emitter)")
        sm = shape_matrix(obj)
        keys = sorted(float(k["time_s"]) for k in (obj.get("motion") or {}).get("keyframes", []))
        times = np.concatenate([even, keys, 0.5 * (np.array(keys[:-1]) + np.array(keys[1:]))]) if keys else even
        bad = [t for t in times if not _is_rigid(relative_motion(motion, sm, t))]
        if bad:
            return (f"{where} is a moving mesh whose motion changes its shape (e.g. at t = {bad[0]:.6g} s: a "
                    "scale that changes over time), which the frozen launch cannot move as an instance")
    return None


def block_obstacle(scene, launch: str) -> str | None:
    """Why ``scene`` rendered with ``launch`` does not render its base keyframes in blocks
    (:meth:`FrozenLaunch.launch_block`), or None (it does)."""
    from .builder import camera_motion, object_motion
    if launch != "frozen":
        return "the film launch renders one frame a launch"
    if scene.render.get("keyframe_blocks") is False:
        return "render.keyframe_blocks is false in the scene"
    movers = [obj["name"] for i, obj in enumerate(scene.data["objects"])
              if not object_motion(obj, f"objects.{i}.").is_static]
    if movers:
        return (f"object '{movers[0]}' moves: Mitsuba holds one transform a shape in a launch, so only the camera's "
                "pose can differ between the frames of one launch")
    if camera_motion(scene.camera).is_static:
        return "nothing moves: every keyframe is the static frame"
    return None


def _free_key(scene_dict: dict, key: str) -> str:
    out, k = key, 1
    while out in scene_dict:
        k += 1
        out = f"{key}_{k}"
    return out


def instance_moving_meshes(mi, scene_dict: dict, motions: dict) -> dict:
    """Make every moving mesh of the scene builder's dict an ``instance`` of a one-shape ``shapegroup``, in place.

    ``mi``: the loaded ``mitsuba`` module. ``motions``: ``{key: (motion, shape matrix)}`` from the builder. The mesh keeps its BSDF and its t = 0
    pose (its ``to_world``: vertex normals are made from the same world-space vertices as in the film
    launch) and moves into the group (key ``KEY__mesh``, ``KEY__group``, or with a suffix where the scene
    has those names); the instance takes the object's key, with an identity ``to_world`` that the renderer
    sets to :func:`relative_motion` at each time. -> ``{key: (M(0) S)^-1}`` for each mesh made an instance.
    Raises ``ValueError`` for a moving mesh with an emitter (:func:`frozen_obstacle` says why beforehand)."""
    done = {}
    for key, (motion, shape_m) in motions.items():
        od = scene_dict.get(key)
        if motion.is_static or not isinstance(od, dict) or od.get("type") not in MESH_TYPES:
            continue
        if "emitter" in od:
            raise ValueError(f"object '{key}' is a moving mesh that emits light: the frozen launch cannot move it")
        group = _free_key(scene_dict, f"{key}__group")
        scene_dict[group] = {"type": "shapegroup", _free_key(scene_dict, f"{key}__mesh"): dict(od)}
        scene_dict[key] = {"type": "instance", "shapegroup": {"type": "ref", "id": group},
                           "to_world": mi.ScalarTransform4f()}
        done[key] = np.linalg.inv(motion.matrix(0.0) @ shape_m)
    return done


def response_tables(curves: dict[str, tuple[np.ndarray, np.ndarray]], step_nm: float = GRID_STEP_NM,
                    n_quantiles: int = N_QUANTILES):
    """The film responses on one regular grid, and the wavelength density drawn from.

    ``curves``: ``{channel: (wavelengths [nm], values)}``, each a piecewise-linear response (zero
    outside its range), as handed to ``specfilm``. Knots off the grid would be smoothed by it:
    refused.

    Returns ``(lambda0_nm, step_nm, tables, quantiles, ranges)``: ``tables[channel]`` the responses at
    ``lambda0 + k step`` (float64, n + 1 points); ``ranges[channel]`` its first and last wavelength
    [nm], outside which it is zero (the table alone would ramp a response that ends above zero down
    over one grid step); ``quantiles`` (``n_quantiles + 1`` points [nm]) the
    wavelengths below which ``j / n_quantiles`` of the summed responses' integral lies (their
    cumulative integral taken per 1 nm bin, linear inside it). Every wavelength where a response is
    above zero lies in a part of non-zero width.
    """
    lo = min(float(wl[0]) for wl, _ in curves.values())
    hi = max(float(wl[-1]) for wl, _ in curves.values())
    n = int(round((hi - lo) / step_nm))
    grid = lo + step_nm * np.arange(n + 1)
    tables, ranges = {}, {}
    for name, (wl, v) in curves.items():
        wl = np.asarray(wl, np.float64)
        off = (wl - lo) / step_nm
        if not np.allclose(off, np.round(off), rtol=0, atol=1e-9):
            raise ValueError(f"response '{name}' has knots off the {step_nm:g} nm grid from {lo:g} nm")
        tables[name] = np.interp(grid, wl, np.maximum(np.asarray(v, np.float64), 0.0), left=0.0, right=0.0)
        ranges[name] = (float(wl[0]), float(wl[-1]))
    total = sum(tables.values())
    w = 0.5 * (total[:-1] + total[1:]) * step_nm  # exact integral of the piecewise-linear sum per bin
    if not w.sum() > 0:
        raise ValueError("the film responses are zero everywhere")
    cdf = np.concatenate([[0.0], np.cumsum(w)]) / w.sum()
    cdf[-1] = 1.0
    quantiles = np.interp(np.arange(n_quantiles + 1) / n_quantiles, cdf, grid)
    return lo, step_nm, tables, quantiles, ranges


def _root(exc: BaseException) -> BaseException:
    while exc.__cause__ is not None:
        exc = exc.__cause__
    return exc


def check_camera(cam: dict) -> None:
    """The frozen launch makes the rays of a plain pinhole camera (:meth:`FrozenLaunch.primary_rays`): refuse a
    camera dict that asks for more, so that a change to the builder cannot make its frames drift."""
    film = cam.get("film", {})
    ok = (cam.get("type") == "perspective" and cam.get("fov_axis") == "x" and film.get("type") == "specfilm"
          and film.get("rfilter", {}).get("type") == "box"
          and not any(k in cam for k in ("principal_point_offset_x", "principal_point_offset_y",
                                         "shutter_open_time", "medium"))
          and not any(k in film for k in ("crop_offset_x", "crop_offset_y", "crop_width", "crop_height",
                                          "sample_border")))
    if not ok:
        raise RuntimeError("the frozen launch supports a perspective camera (fov along x, no principal-point "
                           "offset, shutter time or medium) with a box-filtered specfilm without crop or border; "
                           f"the scene builder made {cam!r}: use --launch film, or extend frozen.py")


class FrozenLaunch:
    """Render one frame's raw channels with a recorded (frozen) launch; see the module docstring.

    Parameters
    ----------
    mi, dr : the loaded ``mitsuba`` (variant set) and ``drjit`` modules.
    mi_scene : the scene, loaded with a plain (``hdrfilm``) camera: it is a frozen input.
    height, width : film size [px].
    fov_x_deg : horizontal field of view [deg] (the camera dict's ``fov``).
    near_clip, far_clip : [m], as the camera's.
    curves : ``{channel: (wavelengths [nm], response)}``, the film's responses (``Phi``, ``E``).
    sampler_type : Mitsuba sampler plugin (the camera's).
    frozen : False runs the same function without ``drjit.freeze`` (a reference for tests).

    :meth:`prepare` makes one for a scene the renderer loads (:class:`.launch.Launch`).
    """

    kind = "frozen"
    #: the camera's pose is an input of each launch (:meth:`launch`); Mitsuba's camera is never rendered
    camera_pose_is_input = True
    #: replays do not see a mesh moved by rewriting its vertices: moving meshes are instances
    sees_vertex_rewrites = False

    @staticmethod
    def prepare(mi, scene, scene_dict: dict, motions: dict):
        """Adapt the scene builder's dict (``scene_dict``, ``motions`` from :func:`.builder.build_dict`) of
        ``scene`` to the frozen launch, in place, before it is loaded: moving meshes become instances
        (:func:`instance_moving_meshes`), and the camera keeps its pose and sampler but gets a plain ``hdrfilm``
        (its film is never rendered). -> ``(instanced, bind)``: ``{key: (M(0) S)^-1}`` of the meshes made
        instances, and ``bind(mi_scene)``, the launch for the loaded scene.

        Raises :class:`sensor.errors.InputError` for a scene the frozen launch cannot render
        (:func:`frozen_obstacle`) and, from ``bind``, on a variant without a JIT (no ``drjit.freeze``)."""
        from sensor.errors import InputError

        from .builder import SAMPLER, SENSOR_KEY
        why = frozen_obstacle(scene)
        if why:
            raise InputError(f"{why}: render it with --launch film (--launch auto chooses it for this scene)",
                             path=scene.path, field="--launch")
        instanced = instance_moving_meshes(mi, scene_dict, motions)
        cam = scene_dict[SENSOR_KEY]
        check_camera(cam)
        film = cam["film"]
        curves = {c: tuple(np.array([float(x) for x in film[c][k].split(",")]) for k in ("wavelengths", "values"))
                  for c in ("Phi", "E")}
        cam["film"] = {"type": "hdrfilm", "width": film["width"], "height": film["height"],
                       "rfilter": {"type": "box"}}

        def bind(mi_scene):
            import drjit
            if not drjit.is_jit_v(mi.Float):
                raise InputError(f"the frozen launch needs an LLVM or CUDA variant of Mitsuba (drjit.freeze); "
                                 f"this run uses '{mi.variant()}': use --launch film with it", field="--launch")
            return FrozenLaunch(mi, drjit, mi_scene, scene.profile.height, scene.profile.width, cam["fov"],
                                cam["near_clip"], cam["far_clip"], curves, SAMPLER)
        return instanced, bind


    def __init__(self, mi, dr, mi_scene, height: int, width: int, fov_x_deg: float, near_clip: float,
                 far_clip: float, curves: dict, sampler_type: str, frozen: bool = True):
        self.mi, self.dr = mi, dr
        self.scene = mi_scene
        self.height, self.width = int(height), int(width)
        self.names = list(curves)
        lo, step, tables, quantiles, ranges = response_tables(curves)
        self._ranges = [ranges[c] for c in self.names]
        self._lo, self._step, self._nbins = float(lo), float(step), len(tables[self.names[0]]) - 1
        self._nq = len(quantiles) - 1
        self._tables = [mi.Float(tables[c].astype(np.float32)) for c in self.names]
        self._quantiles = mi.Float(quantiles.astype(np.float32))
        self._tan = float(np.tan(np.radians(float(fov_x_deg)) / 2.0))
        self._near, self._far = float(near_clip), float(far_clip)
        self._sampler = mi.load_dict({"type": sampler_type, "sample_count": 1})
        self._all_pixels = mi.UInt32(np.arange(self.height * self.width, dtype=np.uint32))  # a frame's list
        self._integrator = mi_scene.integrator()
        self.frozen = bool(frozen)
        self._fn = dr.freeze(self._launch) if self.frozen else self._launch
        self._fn_px = dr.freeze(self._launch_px) if self.frozen else self._launch_px
        self._fn_block = dr.freeze(self._launch_block) if self.frozen else self._launch_block
        self._collected_at = -1  # backend.scenes_loaded() at this launch's last garbage collection
        self._px_lengths = {}  # spp -> the padded pixel-list lengths recorded at it

    def max_samples(self) -> int:
        """:data:`MAX_SAMPLES_PER_LAUNCH`: the most samples one launch takes (its memory is 8 bytes a sample)."""
        return MAX_SAMPLES_PER_LAUNCH

    @property
    def n_recordings(self) -> int:
        """Recordings the three frozen functions (whole frame, pixel list, block) made so far (one per sample count
        and length at its first launch, at times one or two more in the next few, then replays); 0 unfrozen."""
        return sum(int(getattr(fn, "n_recordings", 0)) for fn in (self._fn, self._fn_px, self._fn_block))

    def sample_count(self, spp: int) -> int:
        """The samples per pixel the sampler takes for ``spp`` (a stratified one rounds up)."""
        s = self._sampler.clone()
        s.set_sample_count(int(spp))
        return int(s.sample_count())

    def launch(self, seed: int, spp: int, cam_to_world: np.ndarray):
        """Start the render at ``spp`` samples per pixel; -> ``(spp taken, per-channel sums)``, the sums
        Dr.Jit arrays of H*W each, not yet waited for.

        ``cam_to_world``: the camera's 4 x 4 pose (its ``to_world``). :meth:`channels` waits for the
        result and returns the channels as arrays. Raises :class:`sensor.errors.InputError` for a launch
        of 2^32 samples or more, :class:`sensor.errors.DependencyError` when Dr.Jit cannot freeze it.
        """
        mi = self.mi
        spp = self.sample_count(spp) if self.height * self.width * int(spp) < 1 << 32 else int(spp)
        if self.height * self.width * spp >= 1 << 32:
            from sensor.errors import InputError
            raise InputError(f"{self.height} x {self.width} pixels at {spp} spp is {self.height * self.width * spp:,} "
                             "samples in one launch, 2^32 or more: the frozen launch cannot take it; use fewer "
                             "samples per pixel or --launch film (which renders in passes)", field="spp")
        # the pose as one buffer of 16 float32 (row by row), an input of the recording (not a constant of it): one
        # recording serves every pose and seed. One copy to the device, where a Transform4f made opaque was 32
        # one-value memsets a launch (its matrix and inverse transpose). Made from a list, in memory of Dr.Jit's own:
        # made from a NumPy array, the buffer was at times another input layout to drjit.freeze, which then recorded
        # the launch again (in 5 of 40 processes of a 13-launch run, against none in 120 from a list)
        m = mi.Float([float(x) for x in np.asarray(cam_to_world, np.float32).reshape(16)])
        self._before_launch()
        seed_v = self.dr.opaque(mi.UInt32, int(seed) & 0xFFFFFFFF)
        return spp, self._replay(self._fn, self.scene, seed_v, m, spp, self._tables, self._quantiles,
                                 self._all_pixels)

    def _before_launch(self) -> None:
        """Before a launch, which Dr.Jit may record (at a new sample count, pixel-list length or block size, and at
        times again at one seen before): scenes with the spectral film that are garbage not yet collected (e.g. a
        light meter's, in a reference cycle) would break a recording, so they are collected first, unless no scene
        was loaded (:func:`.backend.scenes_loaded`) since this launch last collected. A collection is 30-90 ms in a
        process that holds PyTorch; a render launches hundreds of times and loads its scenes before the first."""
        if not self.frozen:
            return
        from .backend import scenes_loaded
        if self._collected_at != scenes_loaded():
            import gc
            gc.collect()
            self._collected_at = scenes_loaded()

    def _replay(self, fn, *args):
        """``fn(*args)``, one of the three recorded functions; Dr.Jit's failure to record or replay it raised as
        :class:`sensor.errors.DependencyError`, saying what to do."""
        try:
            return fn(*args)
        except RuntimeError as exc:
            if not self.frozen:
                raise
            from sensor.errors import DependencyError
            raise DependencyError(
                "the frozen launch failed: Dr.Jit could not record or replay the render "
                f"({' '.join(str(_root(exc)).split())}). Mitsuba 3.9.1 cannot freeze a function while "
                "a camera with a spectral film ('specfilm') exists anywhere in the process (mitsuba3 issue "
                "1810): free other scenes rendered with the film launch first, or render with --launch film "
                "(SceneRenderer(..., launch='film')). Dr.Jit's state in this process may be unusable after "
                "this: start a new process.") from exc

    def channels(self, launched) -> dict[str, np.ndarray]:
        """``{channel: float64 (H, W)}``: the per-pixel means of a :meth:`launch` (waits for it)."""
        spp, out = launched
        h, w = self.height, self.width
        return {c: np.asarray(x, dtype=np.float64).reshape(h, w) / spp for c, x in zip(self.names, out)}

    def launch_pixels(self, seed: int, spp: int, cam_to_world: np.ndarray, pixels: np.ndarray):
        """Start a render of the pixels ``pixels`` (flat indices, row by row, into the H x W frame) at ``spp``
        samples each; -> the launched render for :meth:`pixel_values`, not yet waited for.

        The same estimator as :meth:`launch` (rays, wavelengths, sums), on a list of pixels: the renderer's
        static-region reuse (:mod:`.reuse`) renders only the pixels something moving covers. The list is padded
        (with its last pixel) to :meth:`pixel_length` pixels, whose values are dropped: the padded
        length is an input of the recording (one recording per length and spp), so a list that changes a little
        from frame to frame replays the same recording. A pixel's samples depend on its place in the list, the
        seed and the spp, not on the padded length (tested), so which recording serves a list changes no value.
        ``spp`` must be a count the sampler takes exactly."""
        mi = self.mi
        pixels = np.asarray(pixels, np.int64).ravel()
        n_pix = int(pixels.size)
        if n_pix == 0:
            return spp, n_pix, None
        spp = self.sample_count(spp)
        padded = self.pixel_length(n_pix, spp)
        if padded * spp >= 1 << 32:
            from sensor.errors import InputError
            raise InputError(f"{n_pix} pixels at {spp} spp is 2^32 samples or more in one launch", field="spp")
        idx = np.empty(padded, np.uint32)
        idx[:n_pix] = pixels
        idx[n_pix:] = pixels[-1]
        m = mi.Float([float(x) for x in np.asarray(cam_to_world, np.float32).reshape(16)])
        self._px_lengths.setdefault(spp, set()).add(padded)
        self._before_launch()
        seed_v = self.dr.opaque(mi.UInt32, int(seed) & 0xFFFFFFFF)
        out = self._replay(self._fn_px, self.scene, seed_v, m, spp, self._tables, self._quantiles, mi.UInt32(idx),
                           padded)
        return spp, n_pix, out

    def block_size(self, spp: int, most: int = 0) -> int:
        """How many whole frames at ``spp`` one :meth:`launch_block` takes: at most ``most`` (default
        :data:`BLOCK_KEYFRAMES`) and :data:`MAX_SAMPLES_PER_LAUNCH` samples; 0 or 1: no block."""
        most = int(most) or BLOCK_KEYFRAMES
        return int(min(most, MAX_SAMPLES_PER_LAUNCH // max(1, self.height * self.width * self.sample_count(spp))))

    def launch_block(self, seed: int, spp: int, poses):
        """Start one render of ``len(poses)`` whole frames, one per camera pose (4 x 4 ``to_world`` matrices), at
        ``spp`` samples per pixel each; -> the launched block for :meth:`block_channels`, not yet waited for.

        One launch for many keyframes of a scene in which only the camera moves: the poses are an input of the
        recording, as one pose is of :meth:`launch`, and each sample takes its frame's pose. The estimator is
        :meth:`launch`'s (rays, wavelengths, per-pixel sums of ``spp`` samples); the sampler is seeded once for
        the block, and frame ``f``'s samples are the ``f``-th run of ``H W spp`` lanes, so each frame is another
        Monte Carlo estimate of the same quantity as a frame of its own launch (tested), not the same bits. At most
        :meth:`block_size` frames; ``spp`` must be a count the sampler takes exactly."""
        mi = self.mi
        k = len(poses)
        spp = self.sample_count(spp)
        if k < 1 or k * self.height * self.width * spp > MAX_SAMPLES_PER_LAUNCH:
            raise ValueError(f"a block of {k} frames at {spp} spp: 1 to {self.block_size(spp)} frames (block_size)")
        ms = mi.Float([float(x) for p in poses for x in np.asarray(p, np.float32).reshape(16)])
        self._before_launch()
        seed_v = self.dr.opaque(mi.UInt32, int(seed) & 0xFFFFFFFF)
        return spp, k, self._replay(self._fn_block, self.scene, seed_v, ms, spp, self._tables, self._quantiles, k)

    def block_channels(self, launched) -> list[dict[str, np.ndarray]]:
        """``[{channel: float64 (H, W)}]``, one per frame of a :meth:`launch_block`, in the order of its poses
        (waits for it). Each frame is an array of its own (not a view into the block's): a frame let go frees its
        memory."""
        spp, k, out = launched
        h, w = self.height, self.width
        blocks = [np.asarray(x).reshape(k, h, w) for x in out]
        return [{c: np.divide(a[f], spp, dtype=np.float64) for c, a in zip(self.names, blocks)} for f in range(k)]

    def pixel_length(self, n_pix: int, spp: int) -> int:
        """The padded length of a list of ``n_pix`` pixels at ``spp``: the shortest length already recorded at
        ``spp`` that holds it and is at most :data:`PIXEL_SLACK` longer; else, the first time at ``spp``,
        :func:`padded_pixels` (a list that keeps its length is padded little), and after that, when the length
        wanders, :func:`max_padded_pixels` (room for the lists that follow)."""
        recorded = self._px_lengths.get(int(spp), ())
        fits = [n for n in recorded if n_pix <= n <= max_padded_pixels(n_pix)]
        if fits:
            return min(fits)
        return max_padded_pixels(n_pix) if recorded else padded_pixels(n_pix)

    def pixel_values(self, launched) -> dict[str, np.ndarray]:
        """``{channel: float64 (n,)}``: the per-pixel means of a :meth:`launch_pixels`, in the order of its
        ``pixels`` (waits for it)."""
        spp, n_pix, out = launched
        if out is None:
            return {c: np.zeros(0) for c in self.names}
        return {c: np.asarray(x, dtype=np.float64)[:n_pix] / spp for c, x in zip(self.names, out)}

    # --------------------------------------------------------- the recorded function
    def _launch(self, scene, seed, m, spp, tables, quantiles, pixels):
        # every pixel, through the pixel list's gather: the kernel is then the one a list launch at the same count
        # compiles (one path-tracer kernel per count, not two; a first run compiles each count once), and its
        # values are the same as from the sample index alone
        return self._launch_px(scene, seed, m, spp, tables, quantiles, pixels, self.height * self.width)

    def _launch_px(self, scene, seed, m, spp, tables, quantiles, pixels, n_pix):
        mi, dr = self.mi, self.dr
        n = int(n_pix) * spp
        idx = dr.gather(mi.UInt32, pixels, dr.arange(mi.UInt32, n) // spp)  # spp consecutive samples a pixel
        return self._trace(scene, seed, self.pose(m), spp, tables, quantiles, idx, n)

    def _launch_block(self, scene, seed, ms, spp, tables, quantiles, k):
        mi, dr = self.mi, self.dr
        per = self.height * self.width * spp  # one frame's samples; frame f's are the f-th run of them
        n = int(k) * per
        lane = dr.arange(mi.UInt32, n)
        f = lane // per
        idx = (lane - f * per) // spp  # the sample's pixel in its frame: spp consecutive samples each
        # each sample's camera pose: its frame's 16 values, gathered (the lanes of one packet mostly share a frame)
        pose = mi.Transform4f(mi.Matrix4f(*[dr.gather(mi.Float, ms, f * 16 + i) for i in range(16)]))
        return self._trace(scene, seed, pose, spp, tables, quantiles, idx, n)

    def _trace(self, scene, seed, pose, spp, tables, quantiles, idx, n):
        """The samples of pixels ``idx`` (one entry a sample, ``spp`` consecutive ones a pixel; ``n`` of them)
        traced from the camera at ``pose`` (a ``Transform4f``, one or one per sample) and summed per pixel (per
        run of ``spp`` samples): -> per-channel sums."""
        mi, dr = self.mi, self.dr
        h, w = self.height, self.width
        sampler = self._sampler.clone()
        sampler.set_sample_count(spp)
        sampler.set_samples_per_wavefront(spp)
        sampler.seed(seed, n)
        py = idx // w
        px = idx - py * w
        pos = mi.Vector2f(mi.Float(px), mi.Float(py)) + sampler.next_2d()  # Mitsuba's order: position first
        u = sampler.next_1d()  # ... then the wavelength
        lam, inv_p = self.wavelengths(u, quantiles)
        o, d, maxt = self.primary_rays(pose, mi.Vector2f(pos.x * (1.0 / w), pos.y * (1.0 / h)))
        ray = mi.Ray3f(o, d, maxt, 0.0, mi.UnpolarizedSpectrum(*lam))
        L, _, _ = self._integrator.sample(scene, sampler, mi.RayDifferential3f(ray), None, True)
        accs = []
        for tab, rng in zip(tables, self._ranges):
            acc = mi.Float(0.0)
            for i in range(4):
                acc += self.response(tab, lam[i], rng) * L[i] * inv_p[i]
            accs.append(acc * 0.25)
        dr.eval(*accs)  # one kernel for all channels (each sum alone would trace the paths again)
        return [dr.block_reduce(dr.ReduceOp.Add, a, spp, mode="evaluated") for a in accs]

    # --------------------------------------------------------- its parts (also tested on their own)
    def pose(self, buf):
        """The camera's ``Transform4f`` from its 4 x 4 matrix held row by row in ``buf`` (``mi.Float`` of 16).

        The 16 values are taken out of the buffer once, by a kernel of one lane, so that the render's kernel
        reads each as one value, as it read the opaque ``Transform4f`` this replaced; gathered inside the
        render's kernel they were 12 vector gathers in every packet of samples (the kernel's IR, in review)."""
        mi, dr = self.mi, self.dr
        v = [dr.gather(mi.Float, buf, mi.UInt32(i)) for i in range(16)]
        dr.eval(*v)
        return mi.Transform4f(mi.Matrix4f(*v))

    def primary_rays(self, m, film_pos):
        """Rays of the pinhole camera at pose ``m`` through film positions ``film_pos`` in [0, 1]^2.

        What Mitsuba's ``perspective`` sensor (``fov_axis`` x) computes: the camera-space direction
        ``((1 - 2 x) t, (1 - 2 y) t H / W, 1)`` normalised, ``t = tan(fov_x / 2)``, turned by ``m``; the
        origin moved from the camera's centre to the near clip plane along the ray. -> (origin,
        direction, maxt) [m]."""
        mi, dr = self.mi, self.dr
        h, w = self.height, self.width
        d_cam = dr.normalize(mi.Vector3f((1.0 - 2.0 * film_pos.x) * self._tan,
                                         (1.0 - 2.0 * film_pos.y) * (self._tan * h / w), 1.0))
        d = dr.normalize(m @ d_cam)
        inv_z = dr.rcp(d_cam.z)
        near_t = self._near * inv_z
        return m @ mi.Point3f(0.0, 0.0, 0.0) + d * near_t, d, self._far * inv_z - near_t

    def wavelengths(self, u, quantiles):
        """Four stratified wavelengths [nm] from one uniform ``u`` and their 1 / density [nm].

        ``u + i / 4`` (wrapped into [0, 1)) picks part ``j`` of the quantile table and a uniform point
        in it; that part holds ``1 / M`` of the density, spread evenly over its width."""
        mi, dr = self.mi, self.dr
        nq = self._nq
        lam, inv_p = [], []
        for i in range(4):
            ui = u + 0.25 * i
            ui = dr.select(ui >= 1.0, ui - 1.0, ui) * nq
            j = mi.UInt32(dr.clip(dr.floor(ui), 0, nq - 1))
            l0 = dr.gather(mi.Float, quantiles, j)
            width = dr.gather(mi.Float, quantiles, j + 1) - l0
            lam.append(l0 + dr.clip(ui - mi.Float(j), 0.0, 1.0) * width)
            inv_p.append(width * nq)
        return lam, inv_p

    def response(self, table, lam, wl_range):
        """A film response at wavelengths ``lam`` [nm]: linear between the table's 1 nm points, zero outside
        ``wl_range`` (its own first and last wavelength [nm], as Mitsuba's ``irregular`` spectrum)."""
        mi, dr = self.mi, self.dr
        x = (lam - self._lo) * (1.0 / self._step)
        k = mi.UInt32(dr.clip(dr.floor(x), 0, self._nbins - 1))
        f = x - mi.Float(k)
        r = dr.lerp(dr.gather(mi.Float, table, k), dr.gather(mi.Float, table, k + 1), f)
        return dr.select((lam >= wl_range[0]) & (lam <= wl_range[1]), r, 0.0)
