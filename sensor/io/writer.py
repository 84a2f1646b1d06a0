"""Streaming spike writers: a spike stream block by block into a ``.dat`` or a container ``.npz``."""

from __future__ import annotations

import contextlib
import os
import sys
from pathlib import Path

import numpy as np

from sensor.errors import SpikeFileError
from sensor.io.bits import count_bits, pack_frames, packed_to_dat
from sensor.io.container import STREAM_COMPRESSLEVEL, _container_meta_json, _npy_bytes, _npy_header, write_spikes
from sensor.io.fileio import DirectStream, atomic_path


class SpikeWriter:
    """Write a spike stream block by block to ``.dat`` or ``.npz``; the file appears only on :meth:`close`.

    ``.dat`` streams to a temporary file beside the target (bounded memory). ``.npz`` with
    ``expected_intervals`` (the stream's length, when the caller knows it) streams as well: each block is
    deflated (:data:`STREAM_COMPRESSLEVEL`) into the container's ``packed`` member as it comes, so memory
    stays flat in duration; should the stream end at another length, :meth:`close` rewrites the member's
    header in one more pass over the file. ``.npz`` without it keeps the bit-packed blocks (1 bit per
    pixel-interval) in memory until close and writes them as :func:`write_spikes` does. On an exception
    inside a ``with`` block nothing is left behind.

    ``background=True``: :meth:`write_packed` queues the block (at most two waiting) and a
    writer thread counts, re-orders and writes it, so the writing overlaps whatever the
    caller does next (the next block's simulation). The caller must not modify a block it
    has handed over. ``n_intervals`` and ``n_spikes`` are final after :meth:`close`; an error
    of the writer thread is raised by the next :meth:`write_packed` or by :meth:`close`.
    """

    def __init__(self, path, *, interval_s: float, model: str, profile_id: str, seed, source: str = "",
                 implementation: str = "", extra: dict | None = None, background: bool = False,
                 expected_intervals: int | None = None):
        self.path = Path(path)
        self.kind = "dat" if self.path.suffix.lower() == ".dat" else "npz"
        if self.kind == "npz" and self.path.suffix.lower() != ".npz":
            raise SpikeFileError("output must end in .dat (SpikeCV layout) or .npz (container with metadata)",
                                 path=self.path)
        self.meta = dict(interval_s=interval_s, model=model, profile_id=profile_id, seed=seed, source=source,
                         implementation=implementation, extra=extra)
        self._blocks: list[np.ndarray] = []
        self._ctx = None
        self._fh = None
        self.n_intervals = 0
        self.n_spikes = 0
        self.shape = None
        self._zip = self._member = None
        self._closed = False
        self.expected_intervals = None if expected_intervals is None else int(expected_intervals)
        if self.expected_intervals is not None and self.expected_intervals < 0:
            raise ValueError(f"expected_intervals must be >= 0; got {expected_intervals}")
        if self.kind == "dat":
            self._ctx = atomic_path(self.path)
            self._tmp = self._ctx.__enter__()
            self._fh = DirectStream(self._tmp)  # around the page cache where it can (see DirectStream)
        elif self.expected_intervals is not None:
            import zipfile
            self._ctx = atomic_path(self.path)
            self._tmp = self._ctx.__enter__()
            try:
                self._zip = zipfile.ZipFile(self._tmp, "w", compression=zipfile.ZIP_DEFLATED,
                                            compresslevel=STREAM_COMPRESSLEVEL, allowZip64=True)
            except BaseException:
                self._ctx.__exit__(SpikeFileError, SpikeFileError("cannot open"), None)
                raise
        self._queue = self._thread = self._error = None
        if background:
            import queue
            import threading
            self._queue = queue.Queue(maxsize=2)
            self._thread = threading.Thread(target=self._drain, name="r2s-write", daemon=True)
            self._thread.start()

    def _drain(self) -> None:
        """Writer thread: write queued blocks until None; after an error, only empty the queue."""
        while True:
            item = self._queue.get()
            if item is None:
                return
            if self._error is None:
                try:
                    self._write_packed(*item)
                except BaseException as exc:  # handed to the caller's thread by _raise_error
                    self._error = exc

    def _raise_error(self) -> None:
        if self._error is not None:
            exc, self._error = self._error, None
            raise exc

    def _stop(self) -> None:
        """Let the writer thread finish the queued blocks and end (no-op without one)."""
        if self._thread is not None:
            self._queue.put(None)
            self._thread.join()
            self._thread = None

    def write(self, spikes) -> None:
        """Append bool spikes (n, H, W) in image orientation."""
        s = np.asarray(spikes, bool)
        if s.shape[0]:
            self.write_packed(pack_frames(s), s.shape[1:])

    def write_packed(self, bits, shape) -> None:
        """Append packed frames uint8 (n, ceil(H*W/8)) (:func:`pack_frames` layout) of frame ``shape`` (H, W)."""
        bits = np.asarray(bits, np.uint8)
        if bits.shape[0] == 0:
            return
        if self._thread is not None:
            self._raise_error()
            self._queue.put((bits, shape))
            return
        self._write_packed(bits, shape)

    def _write_packed(self, bits, shape) -> None:
        shape = tuple(int(x) for x in shape)
        if self.shape is None:
            self.shape = shape
        elif shape != self.shape:
            raise SpikeFileError(f"frame shape changed from {self.shape} to {shape}", path=self.path)
        self.n_intervals += bits.shape[0]
        if self.kind == "dat":
            H, W = shape
            if W % 8 == 0:  # rows re-ordered (bottom-up) straight into the stream's staging buffer (memory
                n = bits.shape[0]  # reused block after block: no fresh pages to fault in and clear)
                src = np.ascontiguousarray(bits).reshape(n, H, W // 8)
                dst = np.frombuffer(self._fh.reserve(bits.size), np.uint8).reshape(n, H, W // 8)
                if "numba" in sys.modules:  # loaded (the fast kernels): re-order and count in one compiled call
                    from sensor.io.fastio import flip_rows_counted
                    self.n_spikes += flip_rows_counted(src, dst)
                else:  # numpy alone: a writer that does not load numba (~0.6 s) for it
                    np.copyto(dst, src[:, ::-1, :])
                    self.n_spikes += count_bits(src)
                del dst
                self._fh.commit(bits.size)
            else:
                self.n_spikes += count_bits(bits)
                self._fh.write(packed_to_dat(bits, *shape))
            return
        self.n_spikes += count_bits(bits)
        if self._zip is not None:
            if self._member is None:  # the header says the expected length (checked, and if need be fixed, at close)
                # zip64 always: the stream may outgrow the announced length past 2 GiB (20 bytes more)
                self._member = self._zip.open("packed.npy", "w", force_zip64=True)
                self._member.write(_npy_header((self.expected_intervals, bits.shape[1])))
            self._member.write(memoryview(np.ascontiguousarray(bits)).cast("B"))  # deflated here
        else:
            self._blocks.append(bits)

    def close(self) -> Path:
        if self._closed:  # a second close (e.g. inside and at the end of a with block) changes nothing
            return self.path
        self._closed = True
        self._stop()
        try:
            self._raise_error()
        except BaseException:
            self.abort()
            raise
        if self.kind == "dat" or self._zip is not None:  # streamed into a temp file: finish it, then rename
            try:  # (the last partial page, or the container's end, is written here: a full disk may say so now)
                self._fh.close() if self.kind == "dat" else self._finish_zip()
            except BaseException:
                self.abort()
                raise
            ctx, self._ctx = self._ctx, None
            ctx.__exit__(None, None, None)
            return self.path
        H, W = self.shape if self.shape is not None else (0, 0)
        packed = np.concatenate(self._blocks) if self._blocks else np.zeros((0, (H * W + 7) // 8), np.uint8)
        m = self.meta
        return write_spikes(self.path, packed=packed, height=H, width=W, interval_s=m["interval_s"], model=m["model"],
                            profile_id=m["profile_id"], seed=m["seed"], source=m["source"],
                            implementation=m["implementation"], extra=m["extra"])

    def _meta_json(self) -> np.ndarray:
        H, W = self.shape if self.shape is not None else (0, 0)
        m = self.meta
        return _container_meta_json(H, W, self.n_intervals, m["interval_s"], m["model"], m["implementation"],
                                    m["profile_id"], m["seed"], m["source"], m["extra"])

    def _finish_zip(self) -> None:
        """Close the streamed container: the ``packed`` member, then ``meta_json``; a ``packed`` whose header
        says another length than was written is rewritten (one pass over the file, beside it)."""
        H, W = self.shape if self.shape is not None else (0, 0)
        n_bytes = (H * W + 7) // 8
        if self._member is None:
            self._zip.writestr("packed.npy", _npy_header((self.n_intervals, n_bytes)))
        else:
            self._member.close()
        self._zip.writestr("meta_json.npy", _npy_bytes(self._meta_json()))
        self._zip.close()
        if self._member is not None and self.n_intervals != self.expected_intervals:
            _fix_packed_length(self._tmp, self.expected_intervals, self.n_intervals, n_bytes)
        self._member = self._zip = None

    def abort(self) -> None:
        if self._closed and self._ctx is None:  # closed and renamed: nothing left to abort
            return
        self._closed = True
        self._stop()
        self._error = None
        if self.kind == "dat" and self._fh is not None:
            with contextlib.suppress(OSError):  # the file is removed next
                self._fh.close()
            self._fh = None
        if self._zip is not None:  # the file is removed next: close what is open, however far it got
            with contextlib.suppress(Exception):
                if self._member is not None:
                    self._member.close()
            with contextlib.suppress(Exception):
                self._zip.close()
            if self._zip.fp is not None:
                with contextlib.suppress(Exception):
                    self._zip.fp.close()
                self._zip.fp = None  # nothing left for ZipFile.__del__ to finish
            self._zip = self._member = None
        if self._ctx is not None and (self.kind == "dat" or self.expected_intervals is not None):
            ctx, self._ctx = self._ctx, None
            try:
                ctx.__exit__(SpikeFileError, SpikeFileError("aborted"), None)
            except SpikeFileError:
                pass

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close()
        else:
            self.abort()
        return False


def _fix_packed_length(tmp: Path, said: int, wrote: int, n_bytes: int) -> None:
    """Rewrite the container ``tmp`` whose ``packed`` member's header says ``said`` frames where ``wrote``
    were written: the member is copied, header fixed, into a file beside it, which replaces it."""
    import shutil
    import tempfile
    import zipfile
    skip = len(_npy_header((said, n_bytes)))
    fd, fixed = tempfile.mkstemp(prefix=tmp.stem + ".fix-", suffix=".npz", dir=tmp.parent)
    os.close(fd)
    try:
        with zipfile.ZipFile(tmp) as old, zipfile.ZipFile(fixed, "w", compression=zipfile.ZIP_DEFLATED,
                                                          compresslevel=STREAM_COMPRESSLEVEL, allowZip64=True) as new:
            with old.open("packed.npy") as src, new.open("packed.npy", "w", force_zip64=True) as dst:
                src.read(skip)
                dst.write(_npy_header((wrote, n_bytes)))
                shutil.copyfileobj(src, dst, 8 << 20)
            new.writestr("meta_json.npy", old.read("meta_json.npy"))
        os.replace(fixed, tmp)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(fixed)
        raise
