"""Folder locks: one writer at a time per output folder, stale locks of dead processes taken over.

A lock is a small JSON file (``.render2spike.lock``) created with ``O_CREAT | O_EXCL``
inside the folder, holding the writer's pid, host name, start time and command.
A second writer is refused with an :class:`~sensor.errors.InputError` naming the
holder. A lock whose process no longer exists (same host) is stale: it is taken
over, with a note. Readers can call :func:`holder` to learn whether a live writer
is at work.

Also here: :func:`sweep_parts`, which removes the hidden ``.NAME.part-PID-*`` temp
files (see :func:`sensor.io.fileio.atomic_path`) that a killed writer left behind.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import os
import re
import socket
import sys
import time
from pathlib import Path

from sensor.errors import InputError

LOCK_NAME = ".render2spike.lock"
#: temp files whose writer pid cannot be told are removed once older than this [s]
PART_MAX_AGE_S = 3600.0
_PART_RE = re.compile(r"^\..*\.part-(?:(\d+)-)?[^/]*$")


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` exists on this host."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def _read(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def describe(info: dict | None) -> str:
    if not info:
        return "an unknown process (unreadable lock file)"
    return (f"pid {info.get('pid')} on {info.get('host')} since {info.get('started_utc')}"
            + (f" ({info.get('command')})" if info.get("command") else ""))


def is_stale(info: dict | None, path: Path | None = None) -> bool:
    """A lock is stale when its process is gone (same host), or it is unreadable and older than a minute."""
    if not info:
        try:
            return time.time() - path.stat().st_mtime > 60.0 if path is not None else False
        except OSError:
            return True
    if info.get("host") != socket.gethostname():
        return False  # cannot tell: another machine on a shared disk
    return not pid_alive(int(info.get("pid", -1)))


def holder(folder) -> dict | None:
    """The live lock holder of ``folder`` ({pid, host, started_utc, command}), or None."""
    p = Path(folder) / LOCK_NAME
    if not p.exists():
        return None
    info = _read(p)
    return None if is_stale(info, p) else (info or {})


class FolderLock:
    """Exclusive writer lock on ``folder`` (a context manager); ``what`` names the job in messages."""

    def __init__(self, folder, what: str = "a render", log=None):
        self.folder = Path(folder)
        self.path = self.folder / LOCK_NAME
        self.what = what
        self.log = log
        self.held = False

    def acquire(self) -> "FolderLock":
        self.folder.mkdir(parents=True, exist_ok=True)
        info = {"pid": os.getpid(), "host": socket.gethostname(),
                "started_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                "command": " ".join(Path(a).name if i == 0 else a for i, a in enumerate(sys.argv))[:200]}
        for _ in range(3):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                old = _read(self.path)
                if not is_stale(old, self.path):
                    raise InputError(f"{self.what} is already writing into this folder: {describe(old)}; wait for "
                                     f"it to finish or choose another output (if that process is gone, delete "
                                     f"{self.path})", path=self.folder) from None
                if self.log:
                    self.log(f"note: taking over the stale lock of {describe(old)} in {self.folder}")
                with contextlib.suppress(FileNotFoundError):
                    self.path.unlink()
                continue
            with os.fdopen(fd, "w") as f:
                json.dump(info, f)
            self.held = True
            return self
        raise InputError("could not take the folder lock (another writer keeps creating it)", path=self.folder)

    def release(self) -> None:
        if self.held:
            info = _read(self.path)
            if info and info.get("pid") == os.getpid():
                with contextlib.suppress(FileNotFoundError):
                    self.path.unlink()
            self.held = False

    def __enter__(self):
        return self.acquire()

    def __exit__(self, *exc):
        self.release()
        return False


def sweep_parts(folder, log=None) -> list[Path]:
    """Remove hidden ``.NAME.part-*`` temp files in ``folder`` left by dead writers; returns what was removed.

    A temp file named with its writer's pid (``.NAME.part-PID-XXXX.ext``) is removed when that
    process no longer exists; one without a pid once it is older than :data:`PART_MAX_AGE_S`.
    """
    folder = Path(folder)
    removed = []
    if not folder.is_dir():
        return removed
    now = time.time()
    for p in folder.iterdir():
        m = _PART_RE.match(p.name)
        if not m or not p.is_file():
            continue
        pid = m.group(1)
        try:
            stale = (not pid_alive(int(pid))) if pid else (now - p.stat().st_mtime > PART_MAX_AGE_S)
            if stale:
                p.unlink()
                removed.append(p)
        except OSError:
            continue
    if removed and log:
        log(f"note: removed {len(removed)} unfinished temp file(s) left by an interrupted writer in {folder}")
    return removed
