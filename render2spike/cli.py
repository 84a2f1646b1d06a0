"""The ``render2spike`` command line.

Each subcommand lives in its own module under :mod:`render2spike.commands`
and exposes ``register(subparsers)``; this file discovers them. A module's
``register`` adds one parser whose ``func`` default takes the parsed
arguments and returns an exit code.

Errors derived from :class:`sensor.errors.Render2SpikeError` are printed as one
line (``render2spike: error: ...``) with exit code 2; a full disk, a permission refused and a
read-only file system say which file; set ``RENDER2SPIKE_DEBUG=1`` to see the traceback instead.
SIGTERM is handled like Ctrl-C (SIGINT): the command stops, temp files are
removed, locks released, exit code 130 (143 for SIGTERM); the process then exits at once, without
waiting for a compiled kernel still running a block on a worker thread.

The top-level help lists every registered command with its one-line help,
generated from the modules, so it never goes stale.
"""

from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import sys
import zipfile

from sensor.errors import Render2SpikeError

EPILOG_TAIL = """
units: Phi [e-/(s m^2)] and E [lux] in frames; rates in expected photoelectrons per
interval; one interval T_r = 50 us; thresholds in electrons.
seeds: --seed is always the spike seed (the noise of the simulated camera);
--render-seed seeds the Monte Carlo render where a command renders.

examples:
  render2spike run rotating_disk --out out/demo --keep-frames
  render2spike simulate out/demo/frames --out spikes.dat --seed 1
  render2spike info out/demo/spikes.npz

Run `render2spike COMMAND --help` for each command's options and examples.
"""


class _Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C so that every cleanup path (temp files, locks) runs."""


def _on_sigterm(signum, frame):
    raise _Terminated()


def command_list(sub) -> str:
    """"commands:" followed by one line per registered command (name and its help)."""
    rows = [(a.dest, a.help or "") for a in sub._choices_actions]
    w = max((len(n) for n, _ in rows), default=0)
    return "commands:\n" + "\n".join(f"  {n:<{w}}  {h}" for n, h in rows) + "\n"


def _command_modules() -> list[str]:
    """Names of the command modules (``render2spike/commands/*.py``, private ones excluded), sorted."""
    from render2spike import commands
    return sorted(m.name for m in pkgutil.iter_modules(commands.__path__) if not m.name.startswith("_"))


def requested_command(argv) -> str | None:
    """The command module that ``argv`` names, or None (top-level help, --version, an unknown name).

    Top-level options take no values, so the first argument that is not an option is the command.
    """
    first = next((a for a in argv if not a.startswith("-")), None)
    return first if first in _command_modules() else None


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The CLI parser with every command, or only the command module ``only``.

    Registering one command imports only that command's dependencies: ``render2spike simulate``
    never pays for scipy (calibrate), torch (train, evaluate) or Mitsuba (render) at start-up.
    """
    from render2spike import __version__
    parser = argparse.ArgumentParser(
        prog="render2spike",
        description="Physically based rendering-to-spike-camera simulator.",
        usage="render2spike [-h] [--version] COMMAND [OPTIONS]",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"render2spike {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", help=argparse.SUPPRESS,  # listed in the epilog
                                prog="render2spike")
    for name in ([only] if only else _command_modules()):
        module = importlib.import_module(f"render2spike.commands.{name}")
        if hasattr(module, "register"):
            module.register(sub)
    parser.epilog = command_list(sub) + EPILOG_TAIL
    return parser


def _one_line_warning(message, category, filename, lineno, line=None) -> str:
    if issubclass(category, UserWarning) and category.__module__ == "builtins":
        return f"render2spike: warning: {message}\n"
    return f"{filename}:{lineno}: {category.__name__}: {message}\n"


def _missing_folders(out) -> list:
    """The folders on the way to ``out`` (``out`` included) that do not exist yet, deepest first."""
    if not out or not isinstance(out, (str, os.PathLike)):
        return []
    from pathlib import Path
    try:
        p = Path(out).absolute()
    except (OSError, ValueError):
        return []
    missing = []
    for q in [p, *p.parents]:
        try:
            if q.exists() or q.is_symlink():
                break
        except OSError:
            break
        missing.append(q)
    return missing


def _remove_made_folders(missing) -> None:
    """After a failed command: remove the folders of ``missing`` it made that are still empty (deepest first),
    so that a refusal leaves nothing behind."""
    for q in missing:
        try:
            os.rmdir(q)
        except OSError:  # absent, not empty, or not ours to remove
            pass


def main(argv=None) -> int:
    from_command_line = argv is None
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(requested_command(argv))
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 1
    import signal
    import threading
    import warnings
    # the project's own warnings (UserWarning) as one line each, like its errors
    warnings.formatwarning = _one_line_warning
    old_term = None
    if threading.current_thread() is threading.main_thread():
        old_term = signal.signal(signal.SIGTERM, _on_sigterm)
    made = _missing_folders(getattr(args, "out", None) or getattr(args, "output", None))
    ok = False
    stop_code = None  # the exit code of a command stopped by SIGTERM or Ctrl-C
    try:
        rc = int(args.func(args) or 0)
        ok = rc == 0
        return rc
    except Render2SpikeError as exc:
        if os.environ.get("RENDER2SPIKE_DEBUG"):
            raise
        print(f"render2spike: error: {exc}", file=sys.stderr)
        return 2
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, MemoryError) as exc:
        # last resort: a file or value problem we did not anticipate
        if os.environ.get("RENDER2SPIKE_DEBUG"):
            raise
        from sensor.io.fileio import is_disk_full, os_error_line
        line = os_error_line(exc, fallback=getattr(args, "out", None))
        if line is None and is_disk_full(exc):
            line = (f"disk full while writing {getattr(args, 'out', None) or 'the output'} (no space left on "
                    "device); free some space and rerun")
        if line is not None:
            print(f"render2spike: error: {line}", file=sys.stderr)
        else:
            print(f"render2spike: error: {type(exc).__name__}: {exc} (set RENDER2SPIKE_DEBUG=1 for the traceback)",
                  file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        term = isinstance(exc, _Terminated)
        print(f"render2spike: {'terminated' if term else 'interrupted'}; unfinished files were removed",
              file=sys.stderr)
        stop_code = 143 if term else 130
        return stop_code
    finally:
        if old_term is not None:
            signal.signal(signal.SIGTERM, old_term)
        from sensor.io.fileio import remove_live_temps
        remove_live_temps()  # temp files of writes a signal cut short before their own cleanup ran
        if not ok:
            _remove_made_folders(made)  # empty folders a refused or failed command made on the way to --out
        if from_command_line and stop_code is not None:
            # stopped, and everything is cleaned up: exit now. A normal exit would first wait for the worker
            # threads, and a compiled kernel (which holds no Python frame to interrupt) may still be running
            # a block of spikes there
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(stop_code)
        if from_command_line:
            # the process ends next: keep the interpreter's exit from a last cyclic-GC pass over every
            # object the command's imports made (~0.3 s after numba); files are closed by now
            import gc
            gc.freeze()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
