"""The `render2spike` command runs numpy's OpenBLAS on one thread; importing the package does not."""

import os
import subprocess
import sys

CODE = "import os, numpy, render2spike; print(os.environ.get('OPENBLAS_NUM_THREADS'))"
PROBE = ("import sys; sys.argv = ['/usr/bin/render2spike']; import render2spike, os; "
         "print(os.environ.get('OPENBLAS_NUM_THREADS'))")


def _run(code, **env):
    e = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    e.update(env)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=e).stdout.strip()


def test_the_command_gets_one_blas_thread_and_a_user_setting_wins():
    assert _run(PROBE) == "1"
    assert _run(PROBE, OPENBLAS_NUM_THREADS="2") == "2"


def test_a_program_importing_the_package_keeps_its_blas_threads():
    assert _run(CODE) == "None"
    assert _run("import render2spike, os; print(os.environ.get('OPENBLAS_NUM_THREADS'))") == "None"


def test_python_dash_m_counts_as_the_command():
    e = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    out = subprocess.run([sys.executable, "-m", "render2spike", "--version"], capture_output=True, text=True, env=e)
    assert out.returncode == 0
    # the variable is set in that process only: check through a module run with -m that prints it
    code = ("import runpy, sys, os; sys.orig_argv = [sys.executable, '-m', 'render2spike']; "
            "import render2spike; print(os.environ.get('OPENBLAS_NUM_THREADS'))")
    assert _run(code) == "1"
