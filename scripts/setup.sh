#!/usr/bin/env bash
# Install render2spike and everything it needs on a fresh Debian/Ubuntu machine.
#
#   bash scripts/setup.sh            # system libLLVM 19 (for Mitsuba's LLVM variants) + pip install -e .[all]
#   bash scripts/setup.sh --no-apt   # skip the system package (Mitsuba then falls back to scalar variants)
#
# Mitsuba's LLVM variants abort the process with an old libLLVM (15); Debian's libllvm19 works. render2spike
# finds it at run time and sets DRJIT_LIBLLVM_PATH before importing Mitsuba.
set -euo pipefail
cd "$(dirname "$0")/.."

want_apt=1
for a in "$@"; do
  case "$a" in
    --no-apt) want_apt=0 ;;
    *) echo "setup.sh: unknown option $a" >&2; exit 2 ;;
  esac
done

have_llvm() {
  # one test per pattern: under pipefail, `ls A B C | grep` fails when any pattern matches nothing
  local f
  for f in /usr/lib/x86_64-linux-gnu/libLLVM.so.19* /usr/lib/aarch64-linux-gnu/libLLVM.so.19* \
           /usr/lib/llvm-19/lib/libLLVM*.so*; do
    [ -e "$f" ] && return 0
  done
  return 1
}

if [ "$want_apt" = 1 ] && ! have_llvm; then
  if command -v apt-get >/dev/null 2>&1; then
    SUDO=""
    [ "$(id -u)" = 0 ] || SUDO="sudo"
    echo "setup.sh: installing libllvm19 (for Mitsuba's LLVM variants)"
    $SUDO apt-get update -qq || true
    if ! $SUDO apt-get install -y -qq libllvm19 >/dev/null; then
      echo "setup.sh: warning: could not install libllvm19; rendering will use Mitsuba's slower scalar variants" >&2
    fi
  else
    echo "setup.sh: warning: no apt-get; install LLVM 19 and set DRJIT_LIBLLVM_PATH to libLLVM.so for fast rendering" >&2
  fi
fi

# torch is pinned to 2.13.0 in pyproject (the CPU wheel is provided locally on the project machines;
# elsewhere add: --extra-index-url https://download.pytorch.org/whl/cpu)
python3 -m pip install -q --disable-pip-version-check -e ".[all]"   # a failed install stops the script (set -e)
# An editable install leaves the project's own modules uncompiled, and where PYTHONDONTWRITEBYTECODE is set
# (as on the project's machines) every command would compile them again at start-up (about 40 ms of the
# `render2spike simulate` start-up); compile them once here, as a wheel install does. Python checks each .pyc
# against its source, so an edited module is still compiled afresh (in memory) until the next set-up.
python3 -m compileall -q -j 0 render2spike sensor recon >/dev/null
# numba compiles the spike kernels on their first use and caches them beside the source: compile them here once,
# so neither the first run nor the test suite pays for it
python3 -m sensor.models.precompile
python3 -c "import render2spike, sensor, recon" && echo "setup.sh: render2spike installed ($(python3 -m render2spike --version))"
