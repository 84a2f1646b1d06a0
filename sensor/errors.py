"""Exception hierarchy shared by all render2spike stages.

Every error the project raises on purpose derives from :class:`Render2SpikeError`,
so callers can catch one class and the CLI can print one clear line instead of a
traceback. Messages name the file, the field and what was expected, and say what
to do next where there is something to do.
"""

from __future__ import annotations

from pathlib import Path


class Render2SpikeError(Exception):
    """Base class of all deliberate render2spike errors."""


class InputError(Render2SpikeError, ValueError):
    """Bad user input: a file, a field or an argument that does not hold what it should.

    Parameters
    ----------
    message : str
        What is wrong and what was expected.
    path : str or Path, optional
        The file concerned; prefixed to the message.
    field : str, optional
        The key / field / argument concerned; named in the message.
    """

    def __init__(self, message: str, path: str | Path | None = None, field: str | None = None):
        self.path = None if path is None else Path(path)
        self.field = field
        parts = []
        if path is not None:
            parts.append(f"{path}")
        if field is not None:
            parts.append(f"field '{field}'")
        prefix = ": ".join(parts)
        super().__init__(f"{prefix}: {message}" if prefix else message)


class SpikeFileError(InputError):
    """A spike file (.dat, .npz, .h5) is malformed."""


class FrameFileError(InputError):
    """An irradiance frames folder / EXR file breaks the frame contract."""


class ProfileError(InputError):
    """A sensor profile is malformed or inconsistent."""


class CalibrationError(InputError):
    """Calibration recordings cannot support the requested estimate."""


class UnknownMethodError(Render2SpikeError, KeyError):
    """A name was looked up in a registry that does not hold it; lists the valid names."""

    def __init__(self, kind: str, name: str, valid):
        self.kind, self.name, self.valid = kind, name, sorted(valid)
        super().__init__(f"unknown {kind} '{name}'; valid choices: {', '.join(self.valid)}")

    def __str__(self) -> str:  # KeyError would quote the message
        return self.args[0]


class DiskFullError(Render2SpikeError, OSError):
    """The disk filled up while writing ``path`` (nothing half-written is left under its name)."""

    def __init__(self, message: str, path=None):
        self.path = None if path is None else Path(path)
        Exception.__init__(self, message)

    def __str__(self) -> str:
        return self.args[0]


class DependencyError(Render2SpikeError, ImportError):
    """An optional dependency (Mitsuba, libLLVM, PyTorch, Dask) is missing; says how to install it."""
