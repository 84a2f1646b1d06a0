"""Shared test configuration.

* ``--runslow`` (or ``-m slow``) runs the slow tests: tighter statistical runs,
  bigger renders, longer training, kill-and-resume renders in child processes,
  reference-simulator statistics. The default run skips them; it keeps a fast
  test of each capability.
* ``cli``: runs ``render2spike ARGV`` in this process and returns its exit code,
  stdout and stderr. Tests of signals, kills, start-up or process-wide state
  (BLAS threads, Mitsuba variants) run real child processes instead.
* ``rendered_run``: one tiny ``render2spike run`` made once per session (per worker
  process), for the tests that need some rendered frames (skipped where Mitsuba is missing).
* The suite runs in two worker processes, a test file to a process, where
  pytest-xdist is installed (:func:`pytest_cmdline_main`); ``-n 0`` or
  ``RENDER2SPIKE_TEST_WORKERS=0`` runs it here.
* Every stochastic test uses a fixed seed; tolerances come from the statistics
  (binomial / Poisson standard errors at a stated number of sigmas).
"""

import contextlib
import gc
import io
import os
from pathlib import Path
from typing import NamedTuple

import pytest

# z-score used for two-sided statistical tolerances: P(false failure) ~ 1e-4 per check
Z = 3.9


#: worker processes the suite runs in when pytest-xdist is installed and ``-n`` is not given (at most the machine's
#: cores); RENDER2SPIKE_TEST_WORKERS overrides it, 0 runs in this process
TEST_WORKERS = 2


def pytest_addoption(parser):
    parser.addoption("--runslow", action="store_true", default=False, help="run tests marked slow")


@pytest.hookimpl(tryfirst=True)
def pytest_cmdline_main(config):
    """Run the suite in :data:`TEST_WORKERS` processes, a file to a process (``--dist loadfile``: a file's module
    fixtures are made once), unless ``-n`` is given, pytest-xdist is missing, this is a worker (whose ``-n`` xdist
    clears: it would start workers of its own), or a debugger (``--pdb``, ``--trace``), output (``-s``) or
    collection alone is asked for. Called before pytest-xdist's own hook, which then starts the workers."""
    if not config.pluginmanager.hasplugin("xdist") or hasattr(config, "workerinput"):
        return
    opt = config.option
    if opt.numprocesses is not None or getattr(opt, "usepdb", False) or getattr(opt, "trace", False) \
            or getattr(opt, "capture", None) == "no" or getattr(opt, "collectonly", False) or getattr(opt, "tx", None):
        return
    want = os.environ.get("RENDER2SPIKE_TEST_WORKERS", "").strip()
    try:
        n = int(want) if want else min(TEST_WORKERS, os.cpu_count() or 1)
    except ValueError:
        raise pytest.UsageError(f"RENDER2SPIKE_TEST_WORKERS={want!r}: expected a whole number of worker processes "
                                "(0: run in this process)") from None
    if n > 1:
        opt.numprocesses = n
        if opt.dist == "no":
            opt.dist = "loadfile"


def pytest_configure(config):
    if config.getoption("--runslow"):
        # override the default "-m 'not slow'" from pyproject
        config.option.markexpr = ""


@pytest.fixture
def z():
    """Two-sided z-score for statistical tolerances."""
    return Z


@pytest.fixture
def slow_scale(request):
    """1 in the default run, larger with --runslow (more samples -> tighter checks)."""
    return 8 if request.config.getoption("--runslow") else 1


@pytest.fixture(autouse=True)
def _no_display(monkeypatch):
    monkeypatch.setenv("MPLBACKEND", "Agg")
    os.environ.setdefault("MPLBACKEND", "Agg")


class CliResult(NamedTuple):
    """What a command gave: its exit code and its output (the fields of ``subprocess.CompletedProcess``)."""
    returncode: int
    stdout: str
    stderr: str


def run_cli(argv) -> CliResult:
    """``render2spike ARGV`` in this process, its output captured: argparse's exits (``--help``, a bad
    option) give their exit code like the command line's."""
    from render2spike.cli import main
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            rc = main([str(a) for a in argv])
        except SystemExit as exc:
            rc = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    return CliResult(rc, out.getvalue(), err.getvalue())


@pytest.fixture
def cli():
    """cli(*argv) -> CliResult(returncode, stdout, stderr) of ``render2spike ARGV``, run in this process."""
    return lambda *argv: run_cli(argv)


class RenderedRun(NamedTuple):
    """A finished ``render2spike run``: its folder, its frames folder and the arguments that made it."""
    out: Path
    frames: Path
    argv: tuple


#: the session's run: the bundled Lambertian plane, 10 ms (200 intervals, 3 frames) at 8 spp, frames kept, spike seed 3
RENDERED_RUN_OPTIONS = ("--duration", "0.01", "--spp", "8", "--quiet", "--keep-frames", "--seed", "3")


@pytest.fixture(scope="session")
def rendered_run(tmp_path_factory) -> RenderedRun:
    """One tiny run rendered and simulated once per session (in this process); tests read it, never change it."""
    pytest.importorskip("mitsuba", reason="Mitsuba 3 not installed")
    out = tmp_path_factory.mktemp("rendered_run") / "run"
    argv = ("run", "lambertian_plane", "--out", str(out), *RENDERED_RUN_OPTIONS)
    res = run_cli(argv)
    assert res.returncode == 0, res.stderr
    gc.collect()  # the renderer goes before any test records a frozen launch
    return RenderedRun(out, out / "frames", argv)
