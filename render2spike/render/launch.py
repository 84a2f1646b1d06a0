"""How each frame's render is launched: one interface, a film and a frozen implementation, and one choice.

A launch starts one render of the loaded scene at a seed and a sample count and hands back its raw
channels (``Phi``, ``E``, float64 (H, W), in the film's raw units):

``film``
    the scene integrator's own ``render`` into Mitsuba's spectral film (:class:`FilmLaunch`), traced anew
    every frame; works on every variant.
``frozen``
    the same integrator inside a function recorded once with ``drjit.freeze`` and replayed after, with its
    own camera rays, wavelength sampling and per-pixel sums (:class:`.frozen.FrozenLaunch`); LLVM and CUDA
    variants only. The same channels in the same units, another Monte Carlo estimate of them.

:class:`.renderer.SceneRenderer` poses the scene, splits a frame's samples into launches
(:meth:`Launch.max_samples`) and turns the raw channels into physical units; it sees a launch only through
:class:`Launch`. A launch of several keyframes at once plugs in here: a :class:`Launch` whose ``launch``
takes one pose per keyframe, behind a renderer call that renders those keyframes together.

Which launch a render takes is decided in one place, :func:`resolve_launch`: ``film`` and ``frozen`` are
taken as named; ``auto`` (the default) takes ``frozen`` on a JIT variant unless the scene has a moving mesh
the frozen launch cannot move (:func:`.frozen.frozen_obstacle`), and a folder that already holds frames of
the other launch keeps it. The launch is part of a frames folder's scene hash (:func:`settings_of`).
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from . import backend
from . import frozen as _frozen
from .builder import carries_normals, moving_meshes
from .frozen import FrozenLaunch, frozen_obstacle

#: how a frame is launched: ``auto`` (the default: :func:`resolve_launch`), ``film`` (:class:`FilmLaunch`) or
#: ``frozen`` (:class:`.frozen.FrozenLaunch`)
LAUNCHES = ("auto", "film", "frozen")
#: the launch taken when none is named, the same in code, CLI and docs
DEFAULT_LAUNCH = "auto"
#: how the film launch moves a mesh's normals with its vertex rewrites: ``carried`` by the inverse transpose
#: of the pose (:func:`.renderer.carried_normals`); recorded in every film-launch render state and manifest,
#: and in the scene hash of a scene whose moving mesh carries its own normals (:func:`settings_of`)
FILM_MESH_NORMALS = "carried"


class Launch(Protocol):
    """One render of the loaded scene at a seed and a sample count (see the module docstring).

    Made in two steps around the scene's load: ``prepare(mi, scene, scene_dict, motions)`` (a static method)
    adapts the scene builder's dict to the launch and returns ``(instanced, bind)``: the moving meshes it
    made instances (``{key: (M(0) S)^-1}``) and ``bind(mi_scene)``, which makes the launch for the loaded scene.
    """

    #: the launch's name (:data:`LAUNCHES`)
    kind: str
    #: True: the camera's pose is an input of each launch, and Mitsuba's camera is never moved
    camera_pose_is_input: bool
    #: False: a mesh moved by rewriting its vertices would not be seen (it must be moved as an instance)
    sees_vertex_rewrites: bool

    def max_samples(self) -> int | None:
        """The most samples (over all pixels) one launch takes, or None for any number."""

    def launch(self, seed: int, spp: int, cam_to_world: np.ndarray):
        """Start one render with ``spp`` samples per pixel and the camera at ``cam_to_world`` (4 x 4); the
        launched render, not yet waited for."""

    def channels(self, launched) -> dict[str, np.ndarray]:
        """``{"Phi": ..., "E": ...}``, float64 (H, W) raw channels of a :meth:`launch` (waits for it)."""


class FilmLaunch:
    """The film launch: the scene integrator's ``render`` into Mitsuba's spectral film (:class:`Launch`)."""

    kind = "film"
    camera_pose_is_input = False
    sees_vertex_rewrites = True

    @staticmethod
    def prepare(mi, scene, scene_dict: dict, motions: dict):
        """The film launch renders the builder's dict as it is."""
        return {}, lambda mi_scene: FilmLaunch(mi_scene)

    def __init__(self, mi_scene):
        import drjit
        self._dr = drjit
        self.scene = mi_scene
        self.sensor = mi_scene.sensors()[0]
        self._integrator = mi_scene.integrator()
        self._names = None

    def max_samples(self) -> int | None:
        return None

    def launch(self, seed: int, spp: int, cam_to_world=None):
        """The scene integrator's ``render``, called the way ``mi.render`` calls it; Mitsuba's camera is where
        the renderer set it, so ``cam_to_world`` is not used.

        ``mi.render`` wraps that call in a differentiable operation (``dr.custom``) so that gradients can
        flow through it; nothing here is differentiated, and the wrapper's tracing cost (about 0.1 ms a
        launch, 2-3 % of a 32 x 48 frame at 16 spp) would be a fixed cost of every frame. The film is bitwise
        the one ``mi.render`` returns for the same seed and spp (tested)."""
        with self._dr.suspend_grad():
            return self._integrator.render(self.scene, self.sensor, seed=seed, spp=spp, develop=True,
                                           evaluate=False)

    def channels(self, launched) -> dict[str, np.ndarray]:
        arr = np.asarray(launched, dtype=np.float64)
        if self._names is None:
            bmp = self.sensor.film().bitmap()
            self._names = [bmp.struct_()[i].name for i in range(bmp.channel_count())]
        return {c: arr[..., self._names.index(c)] for c in ("Phi", "E")}


#: the implementation of each launch name
LAUNCH_TYPES = {"film": FilmLaunch, "frozen": FrozenLaunch}


def check_launch(launch: str) -> str:
    """``launch`` if it is one of :data:`LAUNCHES`; else :class:`sensor.errors.InputError` listing them."""
    if launch not in LAUNCHES:
        from sensor.errors import InputError
        raise InputError(f"unknown launch '{launch}': choose one of {', '.join(LAUNCHES)}", field="--launch")
    return launch


def resolve_launch(launch: str, variant: str, scene=None, folder_hash: str | None = None,
                   folder_launch: str | None = None) -> str:
    """The launch a render with ``variant`` (a Mitsuba variant name) takes when ``launch`` is asked for.

    ``film`` and ``frozen`` are taken as named. ``auto`` is ``frozen`` on Mitsuba's JIT variants (``llvm_*``,
    ``cuda_*``: ``drjit.freeze`` records there) and ``film`` on the scalar ones (no JIT to record; also the
    fallback when no libLLVM is found), and ``film`` for a ``scene`` (:class:`~.scene.Scene`) the frozen
    launch cannot render (:func:`.frozen.frozen_obstacle`). A frames folder that already holds frames (its
    ``folder_hash``, rendered with ``folder_launch``) which differ from this run's by the launch alone keeps
    its launch under ``auto``: it is resumed, not refused (but never with the frozen launch for a scene that
    launch cannot render). Raises :class:`sensor.errors.InputError` naming the valid choices
    (:func:`check_launch`) for any other name."""
    if check_launch(launch) != "auto":
        return launch
    if not str(variant).startswith(("llvm_", "cuda_")):
        taken = "film"
    else:
        taken = "film" if scene is not None and frozen_obstacle(scene) else "frozen"
    if (scene is not None and folder_hash and folder_launch in LAUNCH_TYPES and folder_launch != taken
            and not (folder_launch == "frozen" and frozen_obstacle(scene))
            and scene_hash(scene, variant, folder_launch) == folder_hash):
        return folder_launch
    return taken


def launch_record(launch: str) -> dict:
    """What the render state and manifest record of the launch besides its name: the frozen launch's estimator
    version (:data:`.frozen.ESTIMATOR_VERSION`), or how the film launch moves mesh normals."""
    if launch == "frozen":
        return {"launch_estimator": _frozen.ESTIMATOR_VERSION}
    return {"mesh_normals": FILM_MESH_NORMALS}


def settings_of(scene, variant: str, launch: str = "film") -> dict:
    """Everything besides the scene data that changes the frames (part of the hash).

    ``variant`` and its family (:func:`.backend.variant_family`: GPU and CPU frames are never mixed);
    ``frames_format`` 2 (frames named by tick, the light level stored in the render state); ``procedure``,
    how the spp is chosen: 2 for a given spp (taken exactly, in one launch per frame where the sampler
    allows), 4 for ``spp: auto`` (the noise budget's answer snapped on measured pairs,
    :func:`.noise.snap_to_measured`, and refined keyframes at their own spp, :func:`.noise.level_k_factors`). The frozen launch adds its name and estimator version: its frames are
    other Monte Carlo estimates than the film's, and no folder mixes frames of two estimators; and
    ``static_reuse`` (:data:`.reuse.REUSE_VERSION`) where it reuses a static frame (:func:`.reuse.reuse_obstacle`), and
    ``keyframe_blocks`` (:data:`.frozen.BLOCK_KEYFRAMES`, :data:`.frozen.BLOCK_VERSION`) where base keyframes share
    launches (:func:`.frozen.block_obstacle`). The film launch
    adds ``mesh_normals`` (:data:`FILM_MESH_NORMALS`) for a scene with a moving mesh that carries its own
    normals (a cube, a mesh file with normals: :func:`.builder.carries_normals`), whose frames depend on how
    the vertex rewrites move those normals; nothing otherwise.
    """
    if check_launch(launch) == "auto":
        raise ValueError("settings_of takes the launch a render takes (launch.resolve_launch), not 'auto'")
    auto = scene.render.get("spp") == "auto"
    out = {"variant": variant, "variant_family": backend.variant_family(variant), "frames_format": 2,
           "procedure": 4 if auto else 2}
    if launch != "film":
        out["launch"] = launch
        out["launch_estimator"] = _frozen.ESTIMATOR_VERSION
        from .reuse import REUSE_VERSION, reuse_obstacle
        if reuse_obstacle(scene, launch) is None:
            out["static_reuse"] = REUSE_VERSION
        if _frozen.block_obstacle(scene, launch) is None:
            out["keyframe_blocks"] = {"keyframes": _frozen.BLOCK_KEYFRAMES, "version": _frozen.BLOCK_VERSION}
    elif any(carries_normals(scene, obj) for _, obj, _ in moving_meshes(scene)):
        out["mesh_normals"] = FILM_MESH_NORMALS
    return out


def scene_hash(scene, variant: str, launch: str) -> str:
    """The scene hash of frames of ``scene`` rendered with ``variant`` and ``launch`` (:func:`settings_of`)."""
    return scene.content_hash(settings_of(scene, variant, launch))


def launch_taken(scene, variant: str, launch: str, old_hash: str | None = None,
                 old_launch: str | None = None) -> tuple[str, str]:
    """The launch a render of ``scene`` takes into a folder of frames ``old_hash`` rendered with ``old_launch``
    (:func:`resolve_launch`), and its scene hash."""
    taken = resolve_launch(launch, variant, scene, old_hash, old_launch)
    return taken, scene_hash(scene, variant, taken)


def refusal_hint(scene, variant: str, launch: str, asked: str, old_hash: str, old_variant, old_launch,
                 manifest: dict, state: dict) -> str:
    """What to do about a folder whose frames' hash (``old_hash``) is not this run's.

    A command is suggested only where it would resume the folder (the folder's hash recomputed with that
    variant and launch), the fewest switches first. A frozen-launch folder of another estimator version
    (recorded in its ``manifest`` or ``state``) is named as such."""
    def h(v: str, lnch: str):
        try:
            return scene_hash(scene, v, lnch)
        except (AttributeError, TypeError, ValueError):  # (a variant that is no name)
            return None

    if not isinstance(old_hash, str) or not old_hash:  # (a summary without a hash: nothing to match against)
        return ""
    old_v = old_variant if isinstance(old_variant, str) else None  # (a name no variant has matches no hash)
    old_l = old_launch if old_launch in LAUNCH_TYPES else None
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
    if (old_launch == launch == "frozen" and old_est is not None and old_est != _frozen.ESTIMATOR_VERSION
            and not hint):
        hint += (f" If nothing else changed, its frames were made by an earlier version of the frozen launch "
                 f"(estimator {old_est}; now {_frozen.ESTIMATOR_VERSION}), which is not resumed: --overwrite "
                 "renders them again.")
    return hint
