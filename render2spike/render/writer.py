"""Background frame writer: EXR frames and journal lines written while the next frame renders.

Writing a frame (EXR file, atomic rename, one journal line) cost a few to ~20 ms
through the OpenEXR binding with an fsync per line, a fixed cost per frame that
at small sizes was a third of a bare ``mi.render``; with the project's own EXR
encoder and the journal fsync'd once a second it is ~0.1-0.3 ms of CPU, most of
it the file system creating the file. :class:`FrameWriter` moves it off the render loop: one thread
takes ``(path, arrays, header, journal record)`` jobs from a bounded queue
(at most ``max_pending`` frames wait, so memory stays bounded and a slow disk
throttles the renderer instead of filling RAM) and, in submission order,

1. writes the frame with :func:`sensor.io.frames.write_frame` (a temp file beside
   the target, then ``os.replace``: nothing half-written is ever at the name);
2. only then appends the frame's journal line (``on_written``), so a journal
   line always names a complete file and a resumed render is exact.

Errors in the thread are not lost: the first one stops the writer (later jobs
are dropped, their frames are not journalled, so a rerun renders them again)
and is raised again, as the same exception object, in the thread that calls
:meth:`FrameWriter.submit`, :meth:`FrameWriter.check` or
:meth:`FrameWriter.close` (a full disk stays a
:class:`~sensor.errors.DiskFullError` naming the file).

Interruptions: :meth:`close` (also the context manager's exit, whatever the
exit) waits for the jobs already queued, at most ``max_pending`` + 1 frames, so
no write is in flight when the caller's cleanup runs (the CLI's
``remove_live_temps`` after Ctrl-C or SIGTERM); every frame whose render
finished is then on disk with its journal line. A write that a hard kill cuts
short leaves only a hidden ``.NAME.part-PID-*`` temp file, which the next
render sweeps (:func:`sensor.io.lock.sweep_parts`).
"""

from __future__ import annotations

import queue
import threading
from pathlib import Path

_STOP = object()


class FrameWriter:
    """Write frames in a background thread, in order; see the module docstring.

    Parameters
    ----------
    on_written : callable(record) -> None, optional
        Called in the writer thread after each frame file is in place, with the job's
        ``record`` (the render job appends the journal line here).
    max_pending : int
        Frames that may wait in the queue (``submit`` blocks beyond that).
    write : callable, optional
        The frame writer, ``write(path, phi, lux, time_s=..., attrs=...)``
        (default :func:`sensor.io.frames.write_frame`; tests inject failures here).
    on_stop : callable() -> None, optional
        Called in the writer thread after the last queued frame, once :meth:`stop` or
        :meth:`close` asked it to end, unless an error stopped it (the render job closes, and
        so fsyncs, its journal here while it prepares the manifest). Its error is raised like a
        write error.
    """

    def __init__(self, on_written=None, max_pending: int = 2, write=None, on_stop=None):
        if write is None:
            from sensor.io.frames import write_frame as write
        self._write = write
        self._on_written = on_written
        self._on_stop = on_stop
        self._stopping = False
        self._q: queue.Queue = queue.Queue(maxsize=max(1, int(max_pending)))
        self._error: BaseException | None = None
        self.n_written = 0
        self._closed = False
        self._thread = threading.Thread(target=self._loop, name="render2spike-frame-writer", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ thread
    def _loop(self) -> None:
        while True:
            job = self._q.get()
            try:
                if job is _STOP:
                    if self._on_stop is not None and self._error is None:
                        try:
                            self._on_stop()
                        except BaseException as exc:  # noqa: BLE001 - handed to the main thread
                            self._error = exc
                    return
                if self._error is not None:
                    continue  # stopped by an earlier error: drop (not journalled, rendered again on resume)
                path, phi, lux, time_s, attrs, record = job
                try:
                    self._write(Path(path), phi, lux, time_s=time_s, attrs=attrs)
                    if self._on_written is not None:
                        self._on_written(record)
                    self.n_written += 1
                except BaseException as exc:  # noqa: BLE001 - handed to the main thread
                    self._error = exc
            finally:
                self._q.task_done()

    # ------------------------------------------------------------------ caller
    def check(self) -> None:
        """Raise the writer thread's first error, if any (the same exception object)."""
        if self._error is not None:
            raise self._error

    def submit(self, path, phi, lux, *, time_s: float, attrs: dict | None = None, record=None) -> None:
        """Queue one frame (arrays are kept as given: do not modify them afterwards); raise a writer error."""
        self.check()
        if self._closed or self._stopping:
            raise RuntimeError("FrameWriter.submit after close (or stop)")
        while True:  # put with a timeout, so a writer that failed meanwhile cannot leave us blocked
            try:
                self._q.put((path, phi, lux, float(time_s), attrs, record), timeout=0.5)
                return
            except queue.Full:
                self.check()
                if not self._thread.is_alive():  # pragma: no cover - the loop only ends on _STOP
                    raise RuntimeError("the frame writer thread stopped")

    def wait_idle(self) -> None:
        """Block until every queued frame is written (or dropped after an error); raise a writer error."""
        self._q.join()
        self.check()

    def stop(self) -> None:
        """Let the thread end after the frames already queued (and ``on_stop``), without waiting for it;
        no frame can be submitted after this. :meth:`close` waits for it."""
        if not self._stopping:
            self._stopping = True
            self._q.put(_STOP)

    def close(self, raise_error: bool = True) -> None:
        """Finish the queued frames, stop the thread and (``raise_error``) raise its error, if any."""
        if not self._closed:
            self._closed = True
            self.stop()
            self._thread.join()
        if raise_error:
            self.check()

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        # on the way out of an error, the caller's exception wins; the writer's is only raised on success
        self.close(raise_error=exc_type is None)
        return False
