"""The frames folder of a render: its lock, render state, journal, manifest, and what a rerun resumes.

Files
-----
``OUT/frame_TTTTTTTT.exr`` (:func:`tick_filename`: the frame's tick on the finest time grid, zero-padded, so
file names sort in time order) and ``OUT/frames.json`` (the manifest, :mod:`sensor.io.frames`), written last,
when every frame is done.

``OUT/render_state.json`` (:data:`STATE_NAME`) records the scene hash, the launch, the light-level measurement
(``calibration``: the irradiance meter's reading behind ``illuminance_lux``) and the samples per pixel, written
when the render starts; each finished frame appends one line to ``OUT/render_journal.jsonl``
(:data:`JOURNAL_NAME`, :class:`Journal`), so a long render does not rewrite a growing file per frame. Frames
and their journal lines are written by a background thread while the next frame renders (:mod:`.writer`): a
line is appended only once its frame file is in place, and the writer's errors are raised in the render.

Resume
------
A rerun into a folder of the same scene hash keeps the finished frames, reuses the stored measurement and spp,
and renders only the rest (:func:`load_state`). A folder of another hash is refused, or with ``overwrite``
emptied of our files (:meth:`FramesFolder.resume`): frames of two scenes are never mixed. A folder that holds
other files is refused (:meth:`FramesFolder.start`).

Lock
----
While rendering, ``OUT/.render2spike.lock`` names the writer (pid, host, start time); a second render into the
same folder is refused with that name, and a lock left by a dead process is taken over (:mod:`sensor.io.lock`).
Unfinished temp files of killed writers are swept on start (:meth:`FramesFolder.locked`).
"""

from __future__ import annotations

import contextlib
import json
import os
import time
from pathlib import Path

import numpy as np

from sensor.errors import InputError
from sensor.io.fileio import json_bytes, write_bytes_atomic, write_json_atomic
from sensor.io.frames import MANIFEST_NAME, manifest_record, read_frame
from sensor.io.lock import FolderLock, sweep_parts

from .writer import FrameWriter

STATE_NAME = "render_state.json"
JOURNAL_NAME = "render_journal.jsonl"
#: the state's format: frames named by tick and listed in the journal, the light level in the state
FORMAT_VERSION = 2
#: the journal is fsync'd at most this often while frames come in [s] (and always when it is closed)
JOURNAL_FSYNC_S = 1.0


def tick_filename(tick: int) -> str:
    """File name of the frame at grid tick ``tick`` (zero-padded: names sort in time order)."""
    return f"frame_{int(tick):08d}.exr"


def _read_json(p: Path):
    try:
        return json.loads(p.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def load_state(out) -> dict | None:
    """The render state of a frames folder: the header (render_state.json) with ``frames`` from the journal.

    ``frames`` maps the tick (a string) to ``{"file", "time_s", "render_noise_ratio"}``. A journal line cut
    short by a kill is ignored (its frame is rendered again).
    """
    out = Path(out)
    state = _read_json(out / STATE_NAME)
    if not isinstance(state, dict):
        return None
    frames = {}
    try:
        lines = (out / JOURNAL_NAME).read_text().splitlines()
    except OSError:
        lines = []
    for line in lines:
        try:
            rec = json.loads(line)
            if "file" not in rec:
                continue  # not a frame's record
            frames[str(int(rec["tick"]))] = {k: rec[k] for k in ("file", "time_s", "render_noise_ratio") if k in rec}
        except (ValueError, KeyError, TypeError):
            continue
    state["frames"] = frames
    return state


class Journal:
    """``OUT/render_journal.jsonl``, appended one line per finished frame (by the writer thread).

    Each line is written and flushed to the operating system at once, after its frame file was renamed
    into place (:mod:`.writer`): a killed process (SIGKILL, OOM, Ctrl-C, SIGTERM) leaves every
    flushed line and every renamed file in the page cache, so a resumed render is exact whatever the
    fsync schedule. ``fsync`` only guards against the *machine* stopping (power loss, kernel crash):
    it runs when a line comes in at least :data:`JOURNAL_FSYNC_S` after the last one, and on
    :meth:`close` (every exit path of a render, errors and interruptions included), instead
    of once per frame (0.1 ms to several ms each on a busy disk, a fixed cost of every frame). After a
    machine crash at most the last second of lines is lost, and their frames are rendered again: the
    lost lines are the newest ones, so what is left still names only complete files. (The frame files
    themselves are not fsync'd; after a machine crash resume trusts what the file system kept.)
    """

    def __init__(self, path: Path, fsync_every_s: float = JOURNAL_FSYNC_S):
        self.path = Path(path)
        self.fsync_every_s = float(fsync_every_s)
        self._f = None
        self._dirty = False
        self._last_sync = time.monotonic()
        self.n_fsync = 0

    def append(self, rec: dict) -> None:
        if self._f is None:
            self._f = open(self.path, "a+b")
            if self._f.tell() > 0:  # a line cut short by a kill: end it, so the new line stands on its own
                self._f.seek(-1, os.SEEK_END)
                cut = self._f.read(1) != b"\n"
                self._f.seek(0, os.SEEK_END)
                if cut:
                    self._f.write(b"\n")
        self._f.write((json.dumps(rec) + "\n").encode())
        self._f.flush()
        self._dirty = True
        if time.monotonic() - self._last_sync >= self.fsync_every_s:
            self.sync()

    def sync(self) -> None:
        """fsync the lines appended so far (if any are not yet)."""
        if self._f is not None and self._dirty:
            os.fsync(self._f.fileno())
            self._dirty = False
            self.n_fsync += 1
        self._last_sync = time.monotonic()

    def close(self) -> None:
        """fsync and close (idempotent)."""
        if self._f is not None:
            try:
                self.sync()
            finally:
                self._f.close()
                self._f = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


class FramesFolder:
    """One frames folder while a render holds its lock (:meth:`locked`); see the module docstring.

    On opening it reads what the folder holds: :attr:`manifest` (a finished render's ``frames.json``) and
    :attr:`state` (the render state with its journal's ``frames``), each None where absent.
    """

    def __init__(self, path, log=print):
        self.path = Path(path)
        self.log = log
        manifest = _read_json(self.path / MANIFEST_NAME)
        self.manifest = manifest if isinstance(manifest, dict) else None
        self.state = load_state(self.path)
        self.n_resumed = 0
        self.wrote_any = False  # a journal line was written: the folder holds a frame of ours
        self._writer = None
        self._final = None

    @classmethod
    @contextlib.contextmanager
    def locked(cls, out, log=print):
        """The folder ``out`` (made if missing), locked for one render, its leftover temp files swept.

        On an error or interruption a folder this call made that received no frame is cleaned up (the state
        and journal the render began removed) while the lock is still held, then the lock is released and the
        folder, now empty, removed: it leaves no empty folder behind, and no other render can start in the
        folder while the clean-up runs (one that takes the lock at once keeps the folder: it is not empty)."""
        out = Path(out)
        if out.exists() and not out.is_dir():
            raise InputError("output path exists and is not a folder", path=out)
        created = not out.exists()
        lock = FolderLock(out, "a render", log=log)
        lock.acquire()
        folder = None
        try:
            sweep_parts(out, log=log)
            folder = cls(out, log)
            yield folder
        except BaseException:
            empty = created and not (folder is not None and folder.wrote_any)
            try:
                if empty:
                    for nm in (STATE_NAME, JOURNAL_NAME):
                        with contextlib.suppress(OSError):
                            (out / nm).unlink(missing_ok=True)
            finally:
                lock.release()  # after the clean-up; the lock file is the last thing in the folder
            if empty:
                with contextlib.suppress(OSError):
                    out.rmdir()  # fails, harmlessly, when another render has taken the folder since
            raise
        finally:
            lock.release()

    # ------------------------------------------------------------------ what the folder holds
    def _recorded(self, key: str):
        return (self.manifest or {}).get(key) or (self.state or {}).get(key)

    @property
    def scene_hash(self) -> str | None:
        """The scene hash of the frames the folder holds (manifest, else render state), or None."""
        return self._recorded("scene_hash")

    @property
    def launch(self) -> str | None:
        """The launch its frames were rendered with, or None."""
        return self._recorded("launch")

    @property
    def variant(self) -> str | None:
        """The Mitsuba variant its frames were rendered with, or None."""
        return self._recorded("variant")

    def _clean(self) -> None:
        """Remove our files: the frames the state and manifest name, the state, journal and manifest."""
        names = set()
        for rec in (self.state or {}).get("frames", {}).values():
            names.add(rec["file"])
        for rec in (self.manifest or {}).get("frames", []):
            if isinstance(rec, dict) and isinstance(rec.get("file"), str):
                names.add(rec["file"])
        for nm in names:
            if "/" not in nm and "\\" not in nm:
                (self.path / nm).unlink(missing_ok=True)
        for nm in (STATE_NAME, JOURNAL_NAME, MANIFEST_NAME):
            (self.path / nm).unlink(missing_ok=True)
        self.manifest = self.state = None

    # ------------------------------------------------------------------ resume decisions
    def resume(self, scene_hash: str, overwrite: bool, hint=lambda: "") -> None:
        """Keep the folder's frames for a render of ``scene_hash``, or clear them.

        Frames of another hash are refused (:class:`sensor.errors.InputError`, ending with ``hint()``), or
        with ``overwrite`` removed; with ``overwrite`` the frames of the same hash are removed too."""
        old = self.scene_hash
        if old is not None and old != scene_hash:
            if not overwrite:
                raise InputError(f"this folder holds frames of a different scene or settings (hash {old}, now "
                                 f"{scene_hash}); rerun with --overwrite to replace them, or choose another --out."
                                 + hint(), path=self.path)
            self._clean()
        elif (self.manifest or self.state) and overwrite:
            self._clean()

    def up_to_date(self, scene_hash: str) -> dict | None:
        """The manifest of a finished render of ``scene_hash`` whose frame files all exist, else None."""
        m = self.manifest
        if m is not None and m.get("complete") and self.scene_hash == scene_hash:
            if all((self.path / f["file"]).is_file() for f in m["frames"]):
                return m
        return None

    def start(self, header: dict, overwrite: bool) -> None:
        """Begin (or go on with) a render: a new render state ``header`` unless the folder holds one, and the
        journal's frames whose files exist (:attr:`n_resumed`). A folder of other files is refused unless
        ``overwrite``."""
        if self.manifest is None and self.state is None and not overwrite and any(
                not p.name.startswith(".") for p in self.path.iterdir()):
            raise InputError("this folder is not empty and holds no render2spike frames; choose an empty or new "
                             "folder for --out (or pass --overwrite to render into it anyway)", path=self.path)
        if self.state is None:
            self.state = {"format_version": FORMAT_VERSION, **header, "frames": {}, "complete": False}
        self.state["frames"] = {k: v for k, v in self.state["frames"].items() if (self.path / v["file"]).is_file()}
        self.n_resumed = len(self.state["frames"])

    def save_state(self) -> None:
        """Write the render state's header (its frames are in the journal)."""
        write_json_atomic(self.path / STATE_NAME, self._header())

    def _header(self) -> dict:
        return {k: v for k, v in self.state.items() if k != "frames"}

    # ------------------------------------------------------------------ frames
    def saved(self, tick: int) -> dict | None:
        """The journal's record of the frame at ``tick``, or None when it is still to render."""
        return self.state["frames"].get(str(tick))

    def read_phi(self, tick: int):
        """Phi of the saved frame at ``tick``, as float64."""
        return read_frame(self.path / self.saved(tick)["file"]).phi.astype(np.float64)

    @contextlib.contextmanager
    def writing(self):
        """Frames written in a background thread (:meth:`write`), each journalled once its file is in place.

        On leaving, the writer finishes the queued frames and closes (fsyncs) the journal in its thread, and
        is joined; its error is raised unless another is on its way out."""
        journal = Journal(self.path / JOURNAL_NAME)

        def journalled(rec: dict) -> None:  # writer thread: the frame file is in place
            journal.append(rec)
            self.wrote_any = True

        with journal, FrameWriter(on_written=journalled, on_stop=journal.close) as writer:
            self._writer = writer
            try:
                yield self
            finally:
                self._writer = None

    def write(self, tick: int, time_s: float, phi, lux, ratio: float, attrs: dict) -> None:
        """Queue the frame at ``tick`` (arrays as they are: the writer rounds them to the file's float32) and
        record it; its journal line follows the file."""
        name = tick_filename(tick)
        rec = {"file": name, "time_s": time_s, "render_noise_ratio": float(ratio)}
        self.state["frames"][str(tick)] = rec
        self._writer.submit(self.path / name, phi, lux, time_s=time_s, attrs=attrs, record={"tick": int(tick), **rec})

    def stop_writing(self) -> None:
        """Let the writer finish the queued frames and close the journal, without waiting (:meth:`writing`)."""
        self._writer.stop()

    def keep_only(self, ticks) -> list[float]:
        """Remove the frames not at ``ticks`` (rendered by a run that refined differently); -> each kept
        frame's ``render_noise_ratio``, in the order of ``ticks``."""
        keep = {str(t) for t in ticks}
        frames = self.state["frames"]
        for k in [k for k in frames if k not in keep]:
            (self.path / frames[k]["file"]).unlink(missing_ok=True)
            del frames[k]
        return [frames[str(t)].get("render_noise_ratio", float("nan")) for t in ticks]

    # ------------------------------------------------------------------ finish
    def prepare_finish(self, height: int, width: int, frames: list[dict], manifest: dict) -> dict:
        """The finished folder's manifest and state text, made now and written by :meth:`finish`. -> the
        manifest as written."""
        manifest_text = json_bytes(manifest_record(height, width, frames, **manifest))
        state_text = json_bytes({**self._header(), "complete": True})
        self._final = (manifest_text, state_text)
        return json.loads(manifest_text)

    def finish(self) -> None:
        """Write the manifest, then the state marked complete (once every frame is written)."""
        manifest_text, state_text = self._final
        write_bytes_atomic(self.path / MANIFEST_NAME, manifest_text)
        write_bytes_atomic(self.path / STATE_NAME, state_text)
        self.state["complete"] = True
