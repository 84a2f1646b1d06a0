"""Choosing and importing the Mitsuba 3 variant, without ever letting the process abort.

Mitsuba's LLVM variants (``llvm_ad_spectral``) JIT-compile through libLLVM,
found via ``DRJIT_LIBLLVM_PATH``. With an unsuitable libLLVM (e.g. the LLVM 15
of Debian 12) Dr.Jit *aborts the process*, which no ``try`` can catch. So:

1. ``DRJIT_LIBLLVM_PATH`` is set (before ``import mitsuba``) to the first of
   :data:`LLVM_CANDIDATES` that exists, unless the user has already set it;
2. the LLVM variant is first tried in a child process (:func:`probe_variant`);
   only if the child succeeds is it set in this process;
3. otherwise the scalar variant (``scalar_spectral``; slower, same physics) is
   used, with a message saying to ``apt-get install libllvm19``.

The environment variable ``RENDER2SPIKE_VARIANT`` forces a variant.
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
FALLBACK_VARIANT = "scalar_spectral"
INSTALL_HINT = ("Mitsuba's fast LLVM variant needs a libLLVM it can use (LLVM 17-19); on Debian/Ubuntu run "
                "`apt-get install libllvm19` (or set DRJIT_LIBLLVM_PATH to a libLLVM.so). Falling back to the "
                f"'{FALLBACK_VARIANT}' variant: same results, several times slower.")


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


def mitsuba(variant: str | None = None):
    """Import Mitsuba with a working spectral variant set; returns the ``mitsuba`` module.

    ``variant`` (or ``$RENDER2SPIKE_VARIANT``) forces one; otherwise
    :data:`PREFERRED_VARIANT` if it passes :func:`probe_variant`, else
    :data:`FALLBACK_VARIANT`. The choice is made once per process.
    """
    if "mi" in _STATE:
        mi = _STATE["mi"]
        if variant and variant != mi.variant():
            mi.set_variant(variant)
        return mi
    want = variant or os.environ.get("RENDER2SPIKE_VARIANT") or None
    lib = find_libllvm()
    if lib and "DRJIT_LIBLLVM_PATH" not in os.environ:
        os.environ["DRJIT_LIBLLVM_PATH"] = lib
    try:
        import mitsuba as mi  # noqa: F401  (importing alone does not initialise the LLVM backend)
    except ImportError as exc:
        raise DependencyError("Mitsuba 3 is not installed: run `pip install 'render2spike[render]'` "
                              "(mitsuba>=3.5, drjit)") from exc
    chosen = want
    if chosen is None:
        ok, msg = probe_variant(PREFERRED_VARIANT, lib)
        if ok:
            chosen = PREFERRED_VARIANT
        else:
            warnings.warn(f"{INSTALL_HINT} (probe said: {msg})", RuntimeWarning, stacklevel=2)
            print(f"render2spike: note: {INSTALL_HINT}", file=sys.stderr)
            chosen = FALLBACK_VARIANT
    elif chosen.startswith("llvm"):
        ok, msg = probe_variant(chosen, lib)
        if not ok:
            raise DependencyError(f"Mitsuba variant '{chosen}' does not work here ({msg}). {INSTALL_HINT}")
    if chosen not in mi.variants():
        raise DependencyError(f"Mitsuba variant '{chosen}' is not available; this build has: "
                              f"{', '.join(mi.variants())}")
    if "spectral" not in chosen:
        raise DependencyError(f"render2spike needs a spectral Mitsuba variant, got '{chosen}'")
    mi.set_variant(chosen)
    mi.set_log_level(mi.LogLevel.Error)  # no per-render chatter; errors still raise
    _STATE["mi"] = mi
    return mi
