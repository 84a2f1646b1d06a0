"""Small file helpers shared by every stage: atomic writes and provenance records."""

from __future__ import annotations

import contextlib
import datetime as _dt
import errno
import functools
import itertools
import json
import os
import platform
import sys
import tempfile
from pathlib import Path


#: temp files of atomic writes still in progress in this process (removed by :func:`remove_live_temps`)
_LIVE_TEMPS: set = set()
#: (folder, name prefix) of every temp file this process is creating: a signal can land between the file's
#: creation and its registration in ``_LIVE_TEMPS`` (inside ``tempfile.mkstemp``), so the prefix goes first
_LIVE_PREFIXES: set = set()


def remove_live_temps() -> list[Path]:
    """Delete the temp files of atomic writes this process has not finished (the CLI calls this on abort,
    for a signal that arrived before a writer's cleanup could run)."""
    gone = []
    for tmp in list(_LIVE_TEMPS):
        with contextlib.suppress(OSError):
            Path(tmp).unlink()
            gone.append(Path(tmp))
        _LIVE_TEMPS.discard(tmp)
    for folder, prefix in list(_LIVE_PREFIXES):
        for tmp in Path(folder).glob(prefix + "*"):
            with contextlib.suppress(OSError):
                tmp.unlink()
                gone.append(tmp)
        _LIVE_PREFIXES.discard((folder, prefix))
    return gone


@contextlib.contextmanager
def atomic_path(path, suffix: str | None = None):
    """Yield a temporary path beside ``path``; rename it onto ``path`` only on success.

    Nothing half-written is ever left at ``path``: if the body raises, the
    temporary file is removed and ``path`` keeps its old content (or stays absent).
    ``suffix`` defaults to ``path``'s own suffix, so libraries that infer the
    format from the extension (OpenEXR, numpy, PIL) keep working. The temp name
    carries the writer's pid (``.STEM.part-PID-XXXX.ext``) so that
    :func:`sensor.io.lock.sweep_parts` can remove those of killed writers. A full
    disk raises :class:`~sensor.errors.DiskFullError` naming ``path``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    prefix = f".{path.stem}.part-{os.getpid()}-"
    _LIVE_PREFIXES.add((str(path.parent), prefix))  # stays registered if a signal cuts mkstemp short
    fd, tmp = tempfile.mkstemp(prefix=prefix, suffix=path.suffix if suffix is None else suffix, dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    _LIVE_TEMPS.add(tmp)
    _LIVE_PREFIXES.discard((str(path.parent), prefix))
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; give the final file the usual permissions
    with _renamed_on_success(tmp, path):
        yield tmp


@contextlib.contextmanager
def _renamed_on_success(tmp, path):
    """Rename the registered temp file ``tmp`` onto ``path`` when the body succeeds; else remove it (a full
    disk raised as DiskFullError naming ``path``); either way unregister it."""
    try:
        yield
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        if is_disk_full(exc):
            from sensor.errors import DiskFullError
            raise DiskFullError(f"disk full while writing {path}", path=path) from exc
        raise
    finally:
        _LIVE_TEMPS.discard(tmp)


_TMP_NUMBERS = itertools.count()


def write_bytes_atomic(path, data) -> Path:
    """Write ``data`` (bytes or a C-contiguous buffer) to ``path`` atomically; the lean :func:`atomic_path`.

    For writers of one buffer per file at a high rate (rendered frames): the same temp name pattern
    (``.STEM.part-PID-N.ext``, swept by :func:`sensor.io.lock.sweep_parts` when its writer is dead), the
    same registration for :func:`remove_live_temps`, the same permissions (``0o666`` less the umask,
    applied by the kernel at creation), the same :class:`~sensor.errors.DiskFullError` naming ``path``,
    and nothing left at ``path`` or beside it on failure; but one ``open`` with ``O_EXCL`` on a name
    numbered by a per-process counter instead of ``mkstemp``, ``close``, ``chmod`` and a second ``open``
    (~0.03 instead of ~0.15 ms per file on ext4), and the names built as strings (``pathlib`` cost about
    25 us a file, a quarter of a small frame's whole write).
    """
    spath = os.fspath(path)
    spath = spath.rstrip(os.sep) or spath  # "out/f.exr/" names the file out/f.exr (as Path() reads it)
    folder, name = os.path.split(spath)
    stem, ext = os.path.splitext(name)
    prefix = os.path.join(folder, f".{stem}.part-{os.getpid()}-")
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0)
    while True:
        tmp = f"{prefix}{next(_TMP_NUMBERS)}{ext}"
        _LIVE_TEMPS.add(tmp)  # before the file exists: a signal may land right after its creation
        try:
            fd = os.open(tmp, flags, 0o666)
            break
        except FileExistsError:  # left by a dead process of the same pid: take the next number
            _LIVE_TEMPS.discard(tmp)
        except FileNotFoundError:
            _LIVE_TEMPS.discard(tmp)
            Path(folder or ".").mkdir(parents=True, exist_ok=True)
        except OSError:  # the open failed: no file was made
            _LIVE_TEMPS.discard(tmp)
            raise
        # anything else (a signal's exception, e.g. KeyboardInterrupt, right after the file was made) leaves
        # the name registered, so remove_live_temps still finds the file
    with _renamed_on_success(tmp, spath):
        try:
            view = memoryview(data).cast("B")
            while view:  # os.write may write less than asked
                view = view[os.write(fd, view):]
        finally:
            os.close(fd)
    return Path(path)


class DirectStream:
    """An append-only file for large blocks (spike streams) written around the page cache where the file
    system allows it (``O_DIRECT``), else as usual.

    A buffered ``write`` copies every byte into page-cache pages the kernel must first find, clear and
    later write back: on the project's 2-core VM that costs about 2 CPU seconds per GB (1 GB of spikes is
    4 camera-seconds), as much as the spike kernel's own work. Written directly from an aligned buffer,
    the same GB costs about 0.1 CPU seconds (``dd`` on that VM: 1.97 s against 0.09 s of system time).

    Blocks are staged in a page-aligned buffer that this stream keeps (:meth:`reserve` hands out its free
    part to fill, :meth:`commit` writes out every whole ``align`` bytes and keeps the rest for the next
    block; :meth:`write` does both with a copy); :meth:`close` writes the last partial piece the usual way.
    Without ``O_DIRECT`` (a file system that refuses it, e.g. tmpfs before Linux 6.6, an unaligned write refused, other
    platforms, or ``RENDER2SPIKE_DIRECT_IO=0``) the same calls write through the page cache. The bytes
    in the file are the same either way.
    """

    def __init__(self, path, align: int = 4096):
        self.path = Path(path)
        self.align = int(align)
        flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_BINARY", 0)
        want = getattr(os, "O_DIRECT", 0) if os.environ.get("RENDER2SPIKE_DIRECT_IO", "1") != "0" else 0
        self.fd = None
        if want:
            try:
                self.fd = os.open(self.path, flags | want, 0o666)
            except OSError as exc:  # EINVAL: this file system has no direct I/O
                if exc.errno != errno.EINVAL:
                    raise
        self.direct = self.fd is not None
        if self.fd is None:
            self.fd = os.open(self.path, flags, 0o666)
        self._buf = None  # mmap: page-aligned, reused
        self._view = None
        self._fill = 0  # bytes staged, not yet written

    def reserve(self, nbytes: int) -> memoryview:
        """A writable view of ``nbytes`` free staged bytes (fill it, then :meth:`commit` it)."""
        need = self._fill + int(nbytes)
        if self._buf is None or len(self._buf) < need:
            import mmap
            cap = -(-max(need, 1 << 20) // mmap.PAGESIZE) * mmap.PAGESIZE
            buf = mmap.mmap(-1, cap)  # anonymous: page-aligned, what O_DIRECT asks of the memory
            view = memoryview(buf)
            if self._fill:
                view[:self._fill] = self._view[:self._fill]
            self._release()
            self._buf, self._view = buf, view
        return self._view[self._fill:need]

    def commit(self, nbytes: int) -> None:
        """Append the ``nbytes`` just filled in the view :meth:`reserve` gave."""
        self._fill += int(nbytes)
        whole = self._fill - self._fill % self.align if self.direct else self._fill
        if whole:
            self._write_all(self._view[:whole])
            rest = self._fill - whole
            if rest:  # less than one page: moved to the front for the next block
                self._view[:rest] = self._view[whole:self._fill]
            self._fill = rest

    def write(self, data) -> None:
        """Append ``data`` (any C-contiguous buffer)."""
        src = memoryview(data)
        if not src.nbytes:
            return
        src = src.cast("B")
        self.reserve(len(src))[:] = src
        self.commit(len(src))

    def _write_all(self, view) -> None:
        while view:
            try:
                k = os.write(self.fd, view)
            except OSError as exc:
                if not (self.direct and exc.errno == errno.EINVAL):
                    raise
                self._buffered()  # the file system refused this direct write: the usual way from here on
                continue
            view = view[k:]
            if view and self.direct and k % self.align:
                self._buffered()  # a short write left the next address unaligned

    def _buffered(self) -> None:
        import fcntl
        fcntl.fcntl(self.fd, fcntl.F_SETFL, fcntl.fcntl(self.fd, fcntl.F_GETFL) & ~os.O_DIRECT)
        self.direct = False

    def _release(self) -> None:
        if self._view is not None:
            self._view.release()
            try:
                self._buf.close()
            except BufferError:  # a caller still holds a view of it: the memory goes with that view
                pass
        self._buf = self._view = None

    def __del__(self):  # dropped without close(): the descriptor is not leaked
        if getattr(self, "fd", None) is not None:
            with contextlib.suppress(OSError):
                os.close(self.fd)
            self.fd = None

    def close(self) -> None:
        """Write what is staged and close the file."""
        if self.fd is None:
            return
        try:
            if self._fill:
                if self.direct:
                    self._buffered()  # the last partial page
                self._write_all(self._view[:self._fill])
                self._fill = 0
        finally:
            os.close(self.fd)
            self.fd = None
            self._release()


def is_disk_full(exc: BaseException) -> bool:
    """Whether ``exc`` (or what caused it) is a "no space left on device" / quota error."""
    seen = 0
    while exc is not None and seen < 5:
        if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
            return True
        if "No space left on device" in str(exc):
            return True
        exc = exc.__cause__ or exc.__context__
        seen += 1
    return False


#: the temp names of :func:`atomic_path` / :func:`write_bytes_atomic`: ``.STEM.part-PID-TAG.EXT``
_PART_NAME = None


def final_name(path) -> Path:
    """The file a temp file of an atomic write stands for (``d/.x.part-12-0.dat`` -> ``d/x.dat``); else ``path``."""
    global _PART_NAME
    import re
    if _PART_NAME is None:
        _PART_NAME = re.compile(r"^\.(?P<stem>.+)\.part-\d+-[A-Za-z0-9_]+(?P<ext>\.[^/]*)?$")
    p = Path(path)
    m = _PART_NAME.match(p.name)
    return p.with_name(m["stem"] + (m["ext"] or "")) if m else p


def os_error_line(exc: BaseException, fallback=None) -> str | None:
    """One line for an OS error a user can act on, naming the file; None for any other error.

    A full disk (or quota), a permission refused, a read-only file system. The file is the one the error
    names (a temp file of an atomic write is named by the file it stands for), else ``fallback``.
    """
    seen = 0
    while exc is not None and seen < 5:
        if isinstance(exc, OSError) and exc.errno is not None:
            name = getattr(exc, "filename", None) or getattr(exc, "path", None)
            where = final_name(name) if name else (fallback or "the output")
            if exc.errno in (errno.ENOSPC, errno.EDQUOT):
                return f"disk full while writing {where} (no space left on device); free some space and rerun"
            if exc.errno in (errno.EACCES, errno.EPERM):
                return f"{where}: permission denied; choose a file or folder you may read or write (e.g. --out)"
            if exc.errno == errno.EROFS:
                return f"{where}: cannot write: read-only file system; choose another output (e.g. --out)"
        exc = exc.__cause__ or exc.__context__
        seen += 1
    return None


def write_text_atomic(path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically (temp file, then rename)."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def write_json_atomic(path, obj) -> Path:
    """Write ``obj`` as indented JSON to ``path`` atomically (:func:`write_bytes_atomic`: one buffer).

    The text is ASCII (``json.dumps`` escapes everything else), so its bytes do not depend on the locale.
    """
    return write_bytes_atomic(path, json_bytes(obj))


def json_bytes(obj) -> bytes:
    """What :func:`write_json_atomic` writes for ``obj``: indented JSON and a newline, ASCII."""
    return (json.dumps(obj, indent=2, sort_keys=False, default=_json_default) + "\n").encode("ascii")


def _json_default(o):
    import numpy as np
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"cannot serialise {type(o).__name__} to JSON")


@functools.lru_cache(maxsize=1)
def package_version() -> str:
    """The installed render2spike distribution version ("unknown" when run from a bare checkout).

    Cached: the metadata lookup costs a few ms, and every written file's provenance asks for it.
    """
    from importlib import metadata
    try:
        return metadata.version("render2spike")
    except metadata.PackageNotFoundError:
        return "unknown"


def provenance(**extra) -> dict:
    """A record of how a file was made: tool version, command line, time, platform, plus ``extra``."""
    rec = {
        "tool": "render2spike",
        "version": package_version(),
        "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "command": " ".join(Path(sys.argv[0]).name if i == 0 else a for i, a in enumerate(sys.argv)),
        "python": platform.python_version(),
        "platform": platform.platform(),
    }
    rec.update(extra)
    return rec


def same_or_inside(out, src) -> bool:
    """Whether the path ``out`` is ``src`` or lies inside the folder ``src`` (both resolved; False if either
    cannot be resolved)."""
    try:
        out, src = Path(out).resolve(), Path(src).resolve()
    except OSError:
        return False
    return out == src or src in out.parents
