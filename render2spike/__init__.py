"""render2spike: physically based rendering-to-spike-camera simulation.

Stages (data flows one way): ``render2spike`` (scenes, Mitsuba rendering,
photometry, CLI, pipelines, studies) -> ``sensor`` (spike models, profiles,
calibration, spike files) -> ``recon`` (reconstruction, datasets, training,
metrics).

The Python API of this stage (imported lazily: ``import render2spike`` does not load Mitsuba)::

    import render2spike as r2s
    scene = r2s.load_scene("rotating_disk", ["render.spp=16"], lux=5.0, duration_s=0.02)
    result = r2s.render_scene(scene, "out/frames")           # frames folder (resumable, locked)
    summary = r2s.run_pipeline("rotating_disk", "out/demo")   # render -> spikes -> preview -> summary

* :func:`load_scene` (scene file or bundled name -> validated :class:`Scene`)
* :func:`render_scene` (:class:`Scene` -> frames folder; returns :class:`RenderResult`)
* :func:`run_pipeline` (the ``render2spike run`` command as a function)
* :func:`simulate_frames` (frames folder or frames in memory -> bit-packed spikes with :class:`sensor.SpikeSimulator`)
* :func:`bundled_scenes` (names of the scenes shipped with the package)
* :class:`SceneRenderer` (render single frames at any time)
"""



def _cli_blas_threads() -> None:
    """In the ``render2spike`` command (not in a program that imports the package), numpy's OpenBLAS gets
    one thread unless ``OPENBLAS_NUM_THREADS`` says otherwise: the commands' parallelism is their own
    (numba's tiles, torch's threads, Dask's workers), and OpenBLAS's idle threads spun on the cores at
    import (0.24 CPU s of a 0.4 s ``simulate`` start-up) and after every call. It must be set before
    numpy is imported, which this package's own import does next."""
    import os
    import sys
    if "numpy" in sys.modules:
        return
    if cli_process():
        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def cli_process() -> bool:
    """Whether this process is the ``render2spike`` command (the console script or ``python -m
    render2spike``), not a program that imports the package: process-wide settings (threads, what
    numba loads) are made only for the command."""
    import os
    import sys
    argv0 = os.path.basename(sys.argv[0]) if sys.argv and sys.argv[0] else ""
    orig = list(getattr(sys, "orig_argv", []))
    return argv0 == "render2spike" or any(a == "-m" and b == "render2spike" for a, b in zip(orig, orig[1:]))


_cli_blas_threads()

from sensor.io.fileio import package_version as _pv  # noqa: E402

__version__ = _pv()

_EXPORTS = {
    "load_scene": "render2spike.render.scene",
    "Scene": "render2spike.render.scene",
    "bundled_scenes": "render2spike.render.scene",
    "render_scene": "render2spike.render.job",
    "RenderResult": "render2spike.render.job",
    "SceneRenderer": "render2spike.render.renderer",
    "run_pipeline": "render2spike.pipeline",
    "simulate_frames": "render2spike.pipeline",
}

__all__ = ["__version__", *_EXPORTS]


def __getattr__(name):
    if name in _EXPORTS:
        import importlib
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'render2spike' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS))
