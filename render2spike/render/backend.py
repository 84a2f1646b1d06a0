"""Choosing and importing the Mitsuba 3 variant, without ever letting the process abort.

Mitsuba's LLVM variants (``llvm_ad_spectral``) JIT-compile through libLLVM,
found via ``DRJIT_LIBLLVM_PATH``. With an unsuitable libLLVM (e.g. the LLVM 15
of Debian 12) Dr.Jit *aborts the process*, which no ``try`` can catch. So:

1. ``DRJIT_LIBLLVM_PATH`` is set (before ``import mitsuba``) to the first of
   :data:`LLVM_CANDIDATES` that exists, unless the user has already set it;
2. if a CUDA device and driver are present (:func:`cuda_device_present`: an
   NVIDIA device node or ``libcuda``, checked without initialising anything)
   and this Mitsuba build has :data:`GPU_VARIANT`, that variant is tried in a
   child process (:func:`probe_variant`) and used if the child succeeds;
3. else the LLVM variant, tried the same way;
4. otherwise the scalar variant (``scalar_spectral``; slower, same physics) is
   used, with a message saying to ``apt-get install libllvm19``.

The environment variable ``RENDER2SPIKE_VARIANT`` (or the commands' ``--variant``,
which wins over it) forces a variant (e.g. ``llvm_ad_spectral`` on a machine with
a GPU, to keep to the CPU); ``auto`` or empty means the automatic choice. The variant
is part of every frames folder's scene hash (``launch.settings_of``), so frames
rendered on a GPU and on a CPU are never mixed in one folder.
"""

from __future__ import annotations

import functools
import os
import subprocess
import sys
import warnings
from pathlib import Path

from sensor.errors import DependencyError

#: libLLVM shared objects known to work with Dr.Jit 1.x, best first.
LLVM_CANDIDATES = (
    "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1",
    "/usr/lib/x86_64-linux-gnu/libLLVM-19.so",
    "/usr/lib/llvm-19/lib/libLLVM.so.19.1",
    "/usr/lib/llvm-19/lib/libLLVM-19.so",
    "/usr/lib/x86_64-linux-gnu/libLLVM-18.so",
    "/usr/lib/llvm-18/lib/libLLVM-18.so",
    "/usr/lib/x86_64-linux-gnu/libLLVM-17.so",
    "/usr/lib/llvm-17/lib/libLLVM-17.so",
    "/opt/homebrew/opt/llvm/lib/libLLVM.dylib",
    "/usr/local/opt/llvm/lib/libLLVM.dylib",
)
PREFERRED_VARIANT = "llvm_ad_spectral"
GPU_VARIANT = "cuda_ad_spectral"
FALLBACK_VARIANT = "scalar_spectral"
INSTALL_HINT = ("Mitsuba's fast LLVM variant needs a libLLVM it can use (LLVM 17-19); on Debian/Ubuntu run "
                "`apt-get install libllvm19` (or set DRJIT_LIBLLVM_PATH to a libLLVM.so). Falling back to the "
                f"'{FALLBACK_VARIANT}' variant: same results, several times slower.")


def variant_family(variant: str) -> str:
    """``cuda``, ``llvm`` or ``scalar``: the back end a Mitsuba variant runs on."""
    return variant.split("_", 1)[0]


def cuda_device_present() -> bool:
    """Cheap, side-effect-free check for an NVIDIA device and driver (no CUDA initialisation here).

    Linux: a ``/dev/nvidia<N>`` device node and a loadable-looking ``libcuda``; elsewhere
    ``libcuda``/``nvcuda`` found by :func:`ctypes.util.find_library`. The real test is the
    child-process probe of :data:`GPU_VARIANT`.
    """
    import ctypes.util
    import glob
    if sys.platform.startswith("linux"):
        if not glob.glob("/dev/nvidia[0-9]*"):  # no device node: nothing more to look at
            return False
        return bool(ctypes.util.find_library("cuda")) or any(Path(d, "libcuda.so.1").exists() for d in
                                ("/usr/lib/x86_64-linux-gnu", "/usr/lib64", "/usr/lib/wsl/lib",
                                 "/usr/local/nvidia/lib64", "/usr/lib/aarch64-linux-gnu"))
    return bool(ctypes.util.find_library("cuda") or ctypes.util.find_library("nvcuda"))


def choose_variant(want: str | None, available, cuda_present: bool, probe) -> tuple[str, list[str]]:
    """The variant to use and notes for the user; pure logic (``probe(variant) -> (ok, message)``).

    ``want`` (argument or ``$RENDER2SPIKE_VARIANT``) wins, after a probe when it needs a JIT back end;
    otherwise :data:`GPU_VARIANT` when a CUDA device is present, available and its probe passes, then
    :data:`PREFERRED_VARIANT` if its probe passes, then :data:`FALLBACK_VARIANT`.
    """
    notes = []
    if want:
        if want not in available:
            raise DependencyError(f"Mitsuba variant '{want}' is not available; this build has: "
                                  f"{', '.join(sorted(available))}")
        if variant_family(want) in ("llvm", "cuda"):
            ok, msg = probe(want)
            if not ok:
                msg = msg.split(" Make sure to call jit_init")[0]  # Dr.Jit's advice is for its own API users
                hint = INSTALL_HINT.split(" Falling back")[0] if variant_family(want) == "llvm" else \
                    "The CUDA variant needs an NVIDIA GPU with a working driver."
                raise DependencyError(f"Mitsuba variant '{want}' does not work here ({msg}). {hint} Or leave the "
                                      f"variant to the automatic choice (--variant auto, or unset "
                                      f"RENDER2SPIKE_VARIANT), which falls back to what works.")
        return want, notes
    if cuda_present and GPU_VARIANT in available:
        ok, msg = probe(GPU_VARIANT)
        if ok:
            return GPU_VARIANT, notes
        notes.append(f"a CUDA device was found but Mitsuba's '{GPU_VARIANT}' did not work ({msg}); using the CPU")
    ok, msg = probe(PREFERRED_VARIANT)
    if ok:
        return PREFERRED_VARIANT, notes
    notes.append(f"{INSTALL_HINT} (probe said: {msg})")
    return FALLBACK_VARIANT, notes


def find_libllvm() -> str | None:
    """The libLLVM to use: ``$DRJIT_LIBLLVM_PATH`` if set, else the first existing known candidate."""
    env = os.environ.get("DRJIT_LIBLLVM_PATH")
    if env:
        return env
    for cand in LLVM_CANDIDATES:
        if Path(cand).exists():
            return cand
    return None


@functools.lru_cache(maxsize=None)
def probe_variant(variant: str, libllvm: str | None) -> tuple[bool, str]:
    """Try ``variant`` in a child process (a Dr.Jit abort there cannot kill us). Returns (ok, message)."""
    env = dict(os.environ)
    if libllvm:
        env["DRJIT_LIBLLVM_PATH"] = libllvm
    # a tiny spectral render: exercises the kernels (e.g. fmaximum) that a bad libLLVM cannot compile
    code = ("import mitsuba as mi, drjit as dr; mi.set_variant(%r); "
            "s = mi.load_dict({'type': 'scene', 'i': {'type': 'path'}, 'e': {'type': 'constant'}, 'b': {'type': 'sphere'}, "
            "'sensor': {'type': 'perspective', 'to_world': mi.ScalarTransform4f().translate([0, 0, -4]), "
            "'film': {'type': 'specfilm', 'width': 4, 'height': 4, 'rfilter': {'type': 'box'}, "
            "'c': {'type': 'irregular', 'wavelengths': '400, 700', 'values': '1, 1'}}}}); "
            "print('ok', mi.render(s, spp=2).numpy().mean() > 0)" % variant)
    try:
        res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return False, f"probe failed to run ({exc})"
    if res.returncode == 0 and "ok" in res.stdout:
        return True, ""
    lines = (res.stderr or res.stdout).strip().splitlines()
    errs = [ln for ln in lines if "ERROR" in ln or "Error" in ln]
    return False, (errs or lines[-1:] or [f"exit code {res.returncode}"])[0][:300]


_STATE: dict = {}

#: ``variant`` value of :func:`mitsuba` that asks for the automatic choice even when
#: ``$RENDER2SPIKE_VARIANT`` is set (the CLI's explicit ``--variant auto``)
AUTO = "auto"


def _env_variant() -> str | None:
    """``$RENDER2SPIKE_VARIANT``, with unset, empty and ``auto`` all meaning: choose automatically."""
    v = (os.environ.get("RENDER2SPIKE_VARIANT") or "").strip()
    return None if v in ("", AUTO) else v


def mitsuba(variant: str | None = None):
    """Import Mitsuba with a working spectral variant set; returns the ``mitsuba`` module.

    ``variant``: a variant name forces it; None takes ``$RENDER2SPIKE_VARIANT`` if set, else the
    automatic choice; :data:`AUTO` the automatic choice whatever the environment says. The automatic
    choice (:func:`choose_variant`) is the CUDA variant when a GPU works, else
    :data:`PREFERRED_VARIANT` if it passes :func:`probe_variant`, else :data:`FALLBACK_VARIANT`.
    Each request is resolved once per process (probes included) and the variant is switched to it on
    every call, so a later call without ``variant`` goes back to that choice rather than keeping a
    variant an earlier call forced. A variant that is missing, does not work here or is not spectral
    raises :class:`DependencyError` saying what to use instead.
    """
    want = None if variant == AUTO else (variant or _env_variant())
    mi = _STATE.get("mi")
    if mi is None:
        lib = find_libllvm()
        if lib and "DRJIT_LIBLLVM_PATH" not in os.environ:
            os.environ["DRJIT_LIBLLVM_PATH"] = lib
        try:
            import mitsuba as mi  # noqa: F401  (importing alone does not initialise the LLVM backend)
        except ImportError as exc:
            raise DependencyError("Mitsuba 3 is not installed: run `pip install 'render2spike[render]'` "
                                  "(mitsuba>=3.5, drjit)") from exc
        _STATE["mi"] = mi
    chosen = _STATE.setdefault("chosen", {}).get(want)
    if chosen is None:
        lib = os.environ.get("DRJIT_LIBLLVM_PATH") or find_libllvm()
        chosen, notes = choose_variant(want, set(mi.variants()), want is None and cuda_device_present(),
                                       lambda v: probe_variant(v, lib))
        for note in notes:
            warnings.warn(note, RuntimeWarning, stacklevel=2)
            print(f"render2spike: note: {note}", file=sys.stderr)
        if chosen not in mi.variants():
            raise DependencyError(f"Mitsuba variant '{chosen}' is not available; this build has: "
                                  f"{', '.join(mi.variants())}")
        if "spectral" not in chosen:
            raise DependencyError(f"render2spike needs a spectral Mitsuba variant, got '{chosen}' (use "
                                  f"{GPU_VARIANT}, {PREFERRED_VARIANT} or {FALLBACK_VARIANT})")
        _STATE["chosen"][want] = chosen
    if mi.variant() != chosen:
        mi.set_variant(chosen)
        mi.set_log_level(mi.LogLevel.Error)  # no per-render chatter; errors still raise
    return mi


#: Mitsuba scenes loaded by this process through :func:`load_scene` (the frozen launch reads it:
#: :meth:`.frozen.FrozenLaunch._before_launch`)
_SCENES_LOADED = [0]


def load_scene(mi, source, *, from_file: bool = False):
    """A Mitsuba scene from a dict (``mi.load_dict``) or, ``from_file``, an XML file, loaded as every scene of this
    package is: in one thread, so that its objects get the same registry ids in every process (the ids are
    constants of the render kernels: with Mitsuba's parallel loading they came in thread order, and Dr.Jit's
    kernel cache on disk then missed in about half the processes), and not optimised. Each load is counted
    (:func:`scenes_loaded`)."""
    _SCENES_LOADED[0] += 1  # before the load: one that fails half way may leave objects behind too
    if from_file:
        return mi.load_file(str(source), parallel=False, optimize=False)
    return mi.load_dict(source, parallel=False, optimize=False)


def scenes_loaded() -> int:
    """How many scenes :func:`load_scene` has loaded in this process so far."""
    return _SCENES_LOADED[0]
