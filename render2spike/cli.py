"""The ``render2spike`` command line.

Each subcommand lives in its own module under :mod:`render2spike.commands`
and exposes ``register(subparsers)``; this file discovers them. A module's
``register`` adds one parser whose ``func`` default takes the parsed
arguments and returns an exit code.

Errors derived from :class:`sensor.errors.Render2SpikeError` are printed as one
line (``render2spike: error: ...``) with exit code 2; set
``RENDER2SPIKE_DEBUG=1`` to see the traceback instead.
"""

from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import sys

from sensor.errors import Render2SpikeError

EPILOG = """\
stages and units:
  render     scene file -> irradiance frames (OpenEXR; Phi [e-/(s m^2)], E [lux])
  simulate   frames or rate array [e-/interval] -> spike stream (T_r = 50 us per interval)
  run        render -> simulate -> preview -> summary, in one command
  calibrate  dark + flat-field spike recordings -> sensor profile
  info       what a spike, frames or profile file holds
  convert    spike file of any layout -> .dat, container .npz or HDF5
  realism    a real recording against each spike model: statistics, figure, distances

Run `render2spike COMMAND --help` for each command's options.
"""


def build_parser() -> argparse.ArgumentParser:
    from render2spike import __version__, commands
    parser = argparse.ArgumentParser(
        prog="render2spike",
        description="Physically based rendering-to-spike-camera simulator.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"render2spike {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for mod in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        if mod.name.startswith("_"):
            continue
        module = importlib.import_module(f"render2spike.commands.{mod.name}")
        if hasattr(module, "register"):
            module.register(sub)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 1
    try:
        return int(args.func(args) or 0)
    except Render2SpikeError as exc:
        if os.environ.get("RENDER2SPIKE_DEBUG"):
            raise
        print(f"render2spike: error: {exc}", file=sys.stderr)
        return 2
    except (OSError, ValueError) as exc:  # last resort: a file or value problem we did not anticipate
        if os.environ.get("RENDER2SPIKE_DEBUG"):
            raise
        print(f"render2spike: error: {type(exc).__name__}: {exc} (set RENDER2SPIKE_DEBUG=1 for the traceback)",
              file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("render2spike: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
