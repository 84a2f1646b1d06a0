"""Helpers shared by the subcommands: output folders that protect themselves.

Every command that writes checks its output first (:func:`check_output`):

* an output that is one of the command's inputs (or holds one) is refused;
* an existing output file, or an existing non-empty output folder, is refused
  unless ``--overwrite`` is given;
* unfinished temp files (``.NAME.part-PID-*``) that a killed writer left in
  the output's folder are removed (:func:`sensor.io.lock.sweep_parts`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from sensor.errors import InputError
from sensor.io.fileio import same_or_inside

OVERWRITE_HELP = "replace an existing output (without it, an existing output is refused)"


def add_overwrite(p, help: str = OVERWRITE_HELP) -> None:
    p.add_argument("--overwrite", action="store_true", help=help)





def check_output(out, *, inputs=(), overwrite: bool = False, folder: bool = False, flag: str = "--out",
                 say=None) -> Path:
    """Check an output path before anything is written; returns it as a Path.

    ``folder``: the output is a folder (refused when it exists, is not empty and ``overwrite`` is off);
    else a file (refused when it exists and ``overwrite`` is off). ``inputs``: paths read by the command.
    """
    from sensor.io.lock import sweep_parts
    out = Path(out)
    for up in out.absolute().parents:  # the nearest existing folder above the output must be a folder
        if up.exists():
            if not up.is_dir():
                raise InputError(f"cannot make it: {up} on the way to it is a file, not a folder; choose another {flag}",
                                 path=out, field=flag)
            break
    for src in inputs:
        if src is None:
            continue
        src = Path(src)
        if src.exists() and same_or_inside(out, src):
            raise InputError(f"the output would overwrite (or sit inside) the input {src}; choose another {flag}",
                             path=out, field=flag)
    if folder:
        if out.exists() and not out.is_dir():
            raise InputError("exists and is not a folder", path=out, field=flag)
        if out.is_dir():
            sweep_parts(out, log=say)
            if not overwrite and any(p for p in out.iterdir() if not p.name.startswith(".")):
                raise InputError("the output folder exists and is not empty; pass --overwrite to write into it "
                                 "anyway, or choose another folder", path=out, field=flag)
    else:
        if out.is_dir():
            raise InputError("is a folder; give a file name", path=out, field=flag)
        if out.parent.is_dir():
            sweep_parts(out.parent, log=say)
        if out.exists() and not overwrite:
            raise InputError("the output file exists; pass --overwrite to replace it, or choose another name",
                             path=out, field=flag)
    return out


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Keeps the description's and examples' line breaks; appends "(default: X)" only where X says something.

    No "(default: None)" or "(default: False)", and nothing added to a help text that already names its default.
    """

    def _get_help_string(self, action):
        text = action.help or ""
        d = action.default
        if ("default" in text or d is None or d is False or d is argparse.SUPPRESS or d == []
                or action.option_strings == [] or isinstance(action, argparse._HelpAction)):
            return text
        return f"{text} (default: %(default)s)" if text else "(default: %(default)s)"


def check_numbers(args, *, at_least: dict | None = None, positive: tuple = (), at_most: dict | None = None) -> None:
    """Refuse numeric options out of range before anything is read or written (one line naming the option).

    ``at_least``: {attribute: minimum} for integer options; ``at_most``: {attribute: (maximum, why)}; ``positive``: float options that must be finite and
    above 0. Options left at None (not given, no default) are not checked.
    """
    import math
    for name, lo in (at_least or {}).items():
        v = getattr(args, name, None)
        if v is not None and v < lo:
            raise InputError(f"must be an integer >= {lo}; got {v}", field="--" + name.replace("_", "-"))
    for name, (hi, why) in (at_most or {}).items():
        v = getattr(args, name, None)
        if v is not None and v > hi:
            raise InputError(f"must be at most {hi} ({why}); got {v}", field="--" + name.replace("_", "-"))
    for name in positive:
        v = getattr(args, name, None)
        if v is not None and not (math.isfinite(v) and v > 0):
            raise InputError(f"must be a finite number above 0; got {v}", field="--" + name.replace("_", "-"))


def seed(text) -> int:
    """argparse type of a seed option (--seed, --render-seed): a whole number >= 0, refused while the
    arguments are parsed, before anything is read, rendered or written."""
    try:
        value = int(text)
    except (TypeError, ValueError):
        raise argparse.ArgumentTypeError(f"expected a seed (a whole number >= 0), got '{text}'") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a seed (a whole number >= 0), got {value}")
    return value


def seed_list(text) -> list[int]:
    """argparse type of a comma-separated list of seeds (--seeds): each a whole number >= 0, no repeats."""
    values = [seed(x.strip()) for x in str(text).split(",") if x.strip()]
    if not values:
        raise argparse.ArgumentTypeError(f"expected comma-separated seeds (whole numbers >= 0), got '{text}'")
    if len(set(values)) != len(values):
        raise argparse.ArgumentTypeError(f"expected distinct seeds, got '{text}' (a repeated seed repeats a run)")
    return values
