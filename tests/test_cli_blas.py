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


LEAN = """
import sys
sys.argv = [{argv0!r}, 'simulate']
import numpy as np, render2spike
from render2spike.commands.simulate import _lean_numba
_lean_numba()
import sensor
prof = sensor.SensorProfile.synthetic(6, 8, threshold_e=20, dark_rate=0.01, prnu_sigma=0.05, seed=1)
rate = np.random.default_rng(2).uniform(0, 3, (30, 6, 8)).astype(np.float32)
sim = sensor.SpikeSimulator(prof, 'elssim', 5)
sim.warm_up()
bits = np.concatenate(list(sim.iter_feed_packed(rate, np.arange(30) * 2e-4)) + [sim.finish_packed()])
print('scipy' in sys.modules, 'cffi' in sys.modules, int(np.bitwise_count(bits).sum()), bits.tobytes().hex()[:64])
"""


def test_the_simulate_command_leaves_scipy_unloaded_and_its_spikes_alone():
    """`render2spike simulate` keeps SciPy (and cffi) out of numba's start (0.1 s); the spikes are those of a
    process that loaded them, and a program importing the package is left as it is."""
    lean = _run(LEAN.format(argv0="/usr/bin/render2spike")).split()
    plain = _run(LEAN.format(argv0="myprogram.py")).split()
    assert lean[:2] == ["False", "False"] and int(lean[2]) > 0
    assert lean[2:] == plain[2:]
    import importlib.util
    if importlib.util.find_spec("scipy") is not None:
        assert plain[0] == "True"  # numba's own import of it: the program's process is untouched
