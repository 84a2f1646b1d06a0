"""Rate inputs of the sensor stage, read in chunks: frames folders, ``.npz`` and ``.npy`` rate arrays and
in-memory arrays, and the plan of which rows to read when (:func:`plan_reads`).

A source hands out chunks ``(rate_e (k, H, W) float32 [e-/interval], t_s (k,) or None, overlap)``,
checked (finite, >= 0 and <= :data:`sensor.units.MAX_RATE_E`; errors name the file and row), that the consumer may keep
(``SpikeSimulator.iter_feed_packed(owned=True)``). Memory is a few chunks, flat in duration.
:func:`sensor.io.stream.open_stream` feeds them through a simulator.
"""

from __future__ import annotations

import math
import os
import zipfile
import zlib
from pathlib import Path

import numpy as np

from sensor.errors import InputError
from sensor.io.buffers import RecyclingPool
from sensor.io.npzrows import NpzMember, stored_member_map
from sensor.units import MAX_RATE_E


def _check_array(shape, t_s, path=None, dtype=None) -> None:
    """Check a rate array's shape (K, H, W), non-empty, its dtype (real numbers) and its keyframe times
    ``t_s`` (K,) when given."""
    if dtype is not None and np.dtype(dtype).kind not in "biuf":
        raise InputError(f"has dtype {np.dtype(dtype)}; expected real numbers (float or integer)", path=path,
                         field="rate_e")
    if len(shape) != 3:
        raise InputError(f"rate_e must be (K, H, W); got shape {shape}", path=path, field="rate_e")
    if t_s is not None and t_s.shape != (shape[0],):
        raise InputError(f"t_s has shape {t_s.shape}; expected ({shape[0]},)", path=path, field="t_s")
    if shape[0] == 0 or 0 in shape[1:]:
        raise InputError(f"rate_e is empty (shape {shape})", path=path, field="rate_e")
    if t_s is not None:
        from sensor.rates import check_times
        check_times(t_s, path=path)


class ChunkPool(RecyclingPool):
    """Float32 chunk arrays recycled once nobody else holds them (:class:`sensor.io.buffers.RecyclingPool`):
    chunks of one input share a shape, so the reader takes back an array the simulator has dropped."""

    def __init__(self, keep: int = 6):
        super().__init__(np.float32, keep)


class RateSource:
    """Chunks of (rate_e (k, H, W) [e-/interval], t_s (k,) or None) from a frames folder, .npz or .npy file,
    or frames held in memory (:class:`sensor.io.frames.MemoryFrameSequence`, read like a folder, no file).

    Nothing is read whole: an ``.npy`` (and an ``.npz`` whose ``rate_e`` is stored, as ``np.savez`` writes
    it) is memory-mapped and handed out in row chunks whose pages are dropped again once used, a deflated
    ``.npz`` member (``np.savez_compressed``) is decoded chunk by chunk from the zip stream, and a
    frames folder's EXR files are read (the Phi channel only). A reader thread reads and checks the
    next chunk while the kernel (which releases the GIL) simulates the current one (:meth:`chunks`).
    Memory is a few chunks, flat in duration.
    """

    def __init__(self, path):
        from sensor.io.frames import MemoryFrameSequence
        held = path if isinstance(path, MemoryFrameSequence) else None  # frames in memory, read like a folder
        self.path = Path(path) if held is None else Path(held.where)
        self.kind = None
        self._reader = None  # the read-ahead thread's executor while chunks are read ahead
        self._member = None
        self._mm = None
        self._crc = None  # a memory-mapped stored .npz member: its CRC-32, folded in as rows are handed out
        self._pool = ChunkPool()
        self.rate = None
        if held is not None or self.path.is_dir():
            from sensor.io.frames import read_frames
            self.frames = held if held is not None else read_frames(self.path)
            self.kind = "frames"
            self.shape = self.frames.shape
            self.n = len(self.frames)
            self.per_interval = False
            self.t_s = self.frames.times_s
        elif not self.path.exists():
            raise InputError("does not exist", path=self.path)
        elif self.path.suffix == ".npz":
            from sensor.io.container import check_zip_start
            check_zip_start(self.path, InputError)
            try:
                with np.load(self.path, allow_pickle=False) as z:
                    if "rate_e" not in z:
                        raise InputError(f"no array 'rate_e' (has: {', '.join(z.files)})", path=self.path,
                                         field="rate_e")
                    self.t_s = z["t_s"].astype(np.float64) if "t_s" in z else None
                mapped = stored_member_map(self.path, "rate_e")
                if mapped is None:  # deflated (or otherwise not mappable): decoded chunk by chunk
                    self._member = NpzMember(self.path, "rate_e")
                    shape, dtype = self._member.shape, self._member.dtype
                else:
                    self.rate, (want, crc) = mapped
                    self._crc = {"want": want, "crc": crc, "rows": 0}
                    shape, dtype = self.rate.shape, self.rate.dtype
            except InputError:
                raise
            except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
                raise InputError(f"not a readable .npz ({exc})", path=self.path) from exc
            self.kind = "array"
        elif self.path.suffix == ".npy":
            try:
                self.rate = np.load(self.path, allow_pickle=False, mmap_mode="r")
            except (OSError, ValueError, EOFError) as exc:
                raise InputError(f"not a readable .npy ({exc})", path=self.path) from exc
            shape, dtype = self.rate.shape, self.rate.dtype
            self.t_s = None
            self.kind = "array"
        else:
            raise InputError("INPUT must be a frames folder, an .npz (rate_e[, t_s]) or an .npy rate array",
                             path=self.path)
        if self.kind == "array":
            _check_array(shape, self.t_s, self.path, dtype)
            self.shape = tuple(shape[1:])
            self.n = shape[0]
            self.per_interval = self.t_s is None

    def n_intervals(self, interval_s) -> int:
        from sensor.rates import n_intervals_spanned
        if self.per_interval:
            return self.n
        return n_intervals_spanned(self.t_s[0], self.t_s[-1], interval_s)

    def _npy_map(self):
        """A read-only memory map of the whole .npy file (made on first use)."""
        if self._mm is None:
            import mmap
            with open(self.path, "rb") as fh:
                self._mm = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
            if hasattr(self._mm, "madvise") and hasattr(mmap, "MADV_SEQUENTIAL"):
                self._mm.madvise(mmap.MADV_SEQUENTIAL)  # read ahead: the rows are read once, in order
        return self._mm

    def _npy_offset(self, i: int) -> int:
        """File offset [bytes] of row ``i`` of the .npy."""
        m = self.rate
        return m.offset + i * int(np.prod(m.shape[1:], dtype=np.int64)) * m.dtype.itemsize

    def _npy_rows(self, i: int, j: int) -> np.ndarray:
        """Rows [i, j) of the .npy as float32 (j - i, H, W).

        A float32 C-ordered file is not copied: the rows are a view of its read-only memory map,
        whose pages come straight from the page cache (several times faster than reading into
        fresh memory, which must be faulted in and zeroed first), and :meth:`_release` drops them
        from the process again once used, so the resident set stays at a few chunks whatever the
        file's length. Other dtypes are converted (a copy of the chunk).
        """
        m = self.rate
        if not m.flags.c_contiguous:  # Fortran order: rows are not contiguous in the file
            return np.array(m[i:j], dtype=np.float32)
        row = int(np.prod(m.shape[1:], dtype=np.int64))
        out = np.frombuffer(self._npy_map(), dtype=m.dtype, count=(j - i) * row, offset=self._npy_offset(i))
        return out.reshape((j - i,) + tuple(m.shape[1:])).astype(np.float32, copy=False)

    def _crc_rows(self, j: int) -> None:
        """Fold rows up to ``j`` (read in order) into the stored member's CRC-32; at the last row, check it."""
        st = self._crc
        if j <= st["rows"]:
            return
        a, b = self._npy_offset(st["rows"]), self._npy_offset(j)
        with memoryview(self._npy_map()) as whole, whole[a:b] as part:  # no copy; crc32 releases the GIL
            st["crc"] = zlib.crc32(part, st["crc"])
        st["rows"] = j
        if j == self.n and st["crc"] != st["want"]:
            raise InputError(f"CRC-32 of member 'rate_e.npy' is {st['crc']:08x}, the zip directory says "
                             f"{st['want']:08x}: the file is damaged", path=self.path, field="rate_e")

    def _release(self, i: int, j: int) -> None:
        """Rows [i, j) are used: drop their pages from this process (.npy only). The data stays in the
        file: a row still referenced is read again from the page cache if touched, unchanged."""
        import mmap
        if self._mm is None or not hasattr(mmap, "MADV_DONTNEED") or not hasattr(self._mm, "madvise"):
            return
        a = self._npy_offset(i) // mmap.PAGESIZE * mmap.PAGESIZE
        b = len(self._mm) if j >= self.n else self._npy_offset(j) // mmap.PAGESIZE * mmap.PAGESIZE
        if b > a:
            self._mm.madvise(mmap.MADV_DONTNEED, a, b - a)

    def _read(self, profile, i: int, j: int, head=None) -> np.ndarray:
        """Rows [i, j) as rate_e float32 (n, H, W), checked. ``head``: rows already read that repeat
        just before ``i`` (the overlap of block-aligned reads); they are copied in front."""
        from sensor.io.fastio import count_bad
        from sensor.rates import check_rates
        ov = 0 if head is None else head.shape[0]
        if self.kind == "frames":
            # only the Phi channel is read (the E channel is not needed here), scaled to e-/interval and
            # checked in the same pass (finite, >= 0, size and time as in frames.json)
            from sensor.units import photoelectron_scale
            scale = photoelectron_scale(profile.pixel_pitch_m, profile.fill_factor, profile.interval_s)
            out = self._pool.take((ov + j - i,) + self.shape)
            if ov:
                out[:ov] = head
            self.frames.read_scaled_many(i, j, scale, out[ov:])
            if count_bad(out[ov:], MAX_RATE_E):  # Phi is finite and >= 0 here; the rate may still be absurd
                check_rates(out[ov:], path=self.path, field="Phi (in photoelectrons per interval)", offset=i)
            return out
        try:
            if self._member is not None:
                if self._member.dtype == np.float32:
                    out = self._pool.take((ov + j - i,) + self.shape)
                    self._member.rows(i, j, out=out[ov:])
                else:
                    rows = self._member.rows(i, j)
                    out = self._pool.take((ov + j - i,) + self.shape)
                    out[ov:] = rows
                if ov:
                    out[:ov] = head
                rate = out
            else:  # a memory map (called without ``head``: repeated rows are part of the view)
                rate = self._npy_rows(i, j)
        except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
            raise InputError(f"cannot read rows {i}..{j - 1} of rate_e (truncated or corrupt? {exc})",
                             path=self.path, field="rate_e") from exc
        if count_bad(rate[ov:], MAX_RATE_E):  # one pass; the slow search for the first bad value only on failure
            check_rates(rate[ov:], path=self.path, offset=i)  # names the absolute index
        return rate

    def chunks(self, profile, bounds, prefetch: int = 1):
        """Iterator of (rate_e, t_s, overlap) chunks of rows ``bounds`` (a list of ``(i, j)``; each range may
        begin before the previous one ended: its first ``overlap`` rows repeat the previous chunk's last,
        as :func:`sensor.rates.block_keyframe_rows` plans them); with ``prefetch`` = n > 0 a reader thread
        keeps the next n chunks read ahead, and starts on them at once (before the first ``next``).

        Each chunk is checked (finite, >= 0; errors name the file and row) and not modified by this
        source while anything else holds it: an array of the source's pool (reused only once the
        consumer has dropped every reference to it, views included), or for a float32 .npy or stored
        .npz a view of the file's read-only memory map, whose pages are dropped from the process once
        the consumer asks for the chunk after next (a simulator looking ahead still reads the one before;
        pages still touched are read again from the page cache). The consumer may keep a chunk
        (``iter_feed_packed(owned=True)``). Repeated rows are copied from the previous chunk (a memory
        map's are part of the view), not read again.
        """
        bounds = [(int(i), int(j)) for i, j in bounds]
        for (i0, j0), (i1, j1) in zip(bounds, bounds[1:]):
            if not (i0 <= i1 <= j0 < j1):
                raise ValueError(f"row ranges must advance and may only overlap the previous one: {(i0, j0)}, "
                                 f"{(i1, j1)}")
        depth = int(prefetch)
        if depth < 1 or len(bounds) < 2:
            return self._chunks_plain(profile, bounds)
        from collections import Counter, deque
        from concurrent.futures import ThreadPoolExecutor
        if self.rate is None:  # chunks are arrays of the pool: see reserve_count
            rows = Counter(j - i for i, j in bounds).most_common(1)[0][0]
            shape = (rows,) + tuple(self.shape)
            self._pool.reserve(shape, reserve_count(len(bounds), depth, 4 * int(np.prod(shape, dtype=np.int64))))
        ex = ThreadPoolExecutor(1, thread_name_prefix="r2s-read")
        self._reader = ex  # stopped by close(), also when the chunks are never asked for
        state = {"prev": None, "end": 0}
        futs = deque(ex.submit(self._read_next, profile, i, j, state) for i, j in bounds[:depth])
        return self._chunks_prefetched(profile, bounds, ex, futs, depth, state)

    def _read_next(self, profile, i: int, j: int, state: dict):
        """The chunk of rows [i, j) given the previous chunk (in ``state``; called in order)."""
        prev, end = state["prev"], state["end"]
        ov = end - i if prev is not None else 0
        if self.rate is not None:  # a memory map: the repeated rows are part of the view, nothing to copy
            rate = self._read(profile, i, j)
            if self._crc is not None:
                self._crc_rows(j)
        else:
            rate = self._read(profile, end if ov else i, j, head=prev[prev.shape[0] - ov:] if ov else None)
        state["prev"], state["end"] = rate, j
        return rate, ov

    def _chunks_plain(self, profile, bounds):
        state = {"prev": None, "end": 0}
        used = None  # rows of the chunk before: a simulator looking ahead reads them until this chunk's next
        try:
            for i, j in bounds:
                rate, ov = self._read_next(profile, i, j, state)
                yield rate, (None if self.t_s is None else self.t_s[i:j]), ov
                del rate
                if used is not None:
                    self._release(*used)
                used = (i, j)
        finally:
            self.close()

    def _chunks_prefetched(self, profile, bounds, ex, futs, depth, state):
        used = None  # as in _chunks_plain
        try:
            for k, (i, j) in enumerate(bounds):
                rate, ov = futs.popleft().result()
                if k + depth < len(bounds):
                    futs.append(ex.submit(self._read_next, profile, *bounds[k + depth], state))
                yield rate, (None if self.t_s is None else self.t_s[i:j]), ov
                del rate
                if used is not None:
                    self._release(*used)
                used = (i, j)
        finally:
            ex.shutdown(wait=True, cancel_futures=True)
            state["prev"] = None
            self.close()

    def close(self):
        """Stop the read-ahead thread (its pending reads cancelled) and close the file."""
        ex, self._reader = self._reader, None
        if ex is not None:
            ex.shutdown(wait=True, cancel_futures=True)
        if self._member is not None:
            self._member.close()
            self._member = None
        if self._mm is not None:
            try:
                self._mm.close()
            except BufferError:  # rows still referenced by the caller: the map closes with the last of them
                pass
            self._mm = None



class ArraySource:
    """Chunks of an in-memory rate array, like :class:`RateSource`'s: ``rate_e`` (K, H, W) [e-/interval] with
    keyframe times ``t_s`` (K,) [s], or one row per interval (``t_s`` None).

    The chunks are views of the (float32) array, checked as they are handed out; the caller must not
    modify the array until the stream that reads them has finished.
    """

    kind = "memory"

    def __init__(self, rate_e, t_s=None):
        _check_array(np.shape(rate_e), None, dtype=np.asarray(rate_e).dtype)
        self.rate = np.asarray(rate_e, dtype=np.float32)
        self.t_s = None if t_s is None else np.asarray(t_s, np.float64)
        _check_array(self.rate.shape, self.t_s)
        self.shape = tuple(self.rate.shape[1:])
        self.n = self.rate.shape[0]
        self.per_interval = self.t_s is None

    def n_intervals(self, interval_s) -> int:
        from sensor.rates import n_intervals_spanned
        if self.per_interval:
            return self.n
        return n_intervals_spanned(self.t_s[0], self.t_s[-1], interval_s)

    def chunks(self, profile=None, bounds=None, prefetch: int = 0):
        """Iterator of (rate_e, t_s, overlap) for row ranges ``bounds`` (as :meth:`RateSource.chunks`;
        ``profile`` and ``prefetch`` are not needed: the rows are in memory)."""
        bounds = [(0, self.n)] if bounds is None else [(int(i), int(j)) for i, j in bounds]
        return self._chunks(bounds)

    def _chunks(self, bounds):
        from sensor.io.fastio import count_bad
        from sensor.rates import check_rates
        end = 0
        for i, j in bounds:
            ov = end - i if end > i else 0
            rate = self.rate[i:j]
            if count_bad(rate[ov:], MAX_RATE_E):
                check_rates(rate[ov:], offset=i + ov)
            end = j
            yield rate, (None if self.t_s is None else self.t_s[i:j]), ov

    def close(self):
        pass


def open_rate_input(source, t_s=None):
    """A chunk source for ``source``: a frames folder or an ``.npz`` / ``.npy`` file or frames in memory
    (:class:`sensor.io.frames.MemoryFrameSequence`) (:class:`RateSource`), an in-memory rate array with optional keyframe times ``t_s`` (:class:`ArraySource`), or a source already.

    ``t_s`` [s] (K,): the keyframe times of an in-memory array, an ``.npy`` file or an ``.npz`` without its
    own ``t_s``; refused (InputError) for a frames folder or an ``.npz`` that has its own times, and for a
    source already opened."""
    if isinstance(source, (RateSource, ArraySource)):
        if t_s is not None:
            raise InputError("t_s is given with a rate source already opened; open the source with its times",
                             path=getattr(source, "path", None), field="t_s")
        return source
    from sensor.io.frames import MemoryFrameSequence
    if isinstance(source, MemoryFrameSequence):
        if t_s is not None:
            raise InputError("t_s is given with frames in memory: their keyframe times are in their manifest",
                             path=source.where, field="t_s")
        return RateSource(source)
    if isinstance(source, (str, os.PathLike)):
        src = RateSource(source)
        if t_s is not None:
            try:
                if src.kind == "frames" or src.t_s is not None:
                    what = "a frames folder" if src.kind == "frames" else "an .npz with its own 't_s'"
                    raise InputError(f"is {what}: its keyframe times are in the file; do not pass t_s",
                                     path=src.path, field="t_s")
                times = np.asarray(t_s, np.float64)
                _check_array((src.n,) + tuple(src.shape), times, src.path)
            except BaseException:
                src.close()
                raise
            src.t_s, src.per_interval = times, False
        return src
    return ArraySource(source, t_s)


#: largest read of one simulator block's keyframes for block-aligned reads (else fixed-size chunks)
ALIGNED_MAX_BYTES = 64 << 20

#: most memory of chunk arrays faulted in ahead during the start-up (:func:`reserve_count`)
RESERVE_MAX_BYTES = 128 << 20


def reserve_count(n_chunks: int, depth: int, chunk_bytes: int) -> int:
    """How many chunk arrays a reader with ``depth`` chunks read ahead has faulted in while the command
    starts (:meth:`sensor.io.buffers.RecyclingPool.reserve`), not by the reader beside the running kernel
    (fresh memory costs its first writer the page faults and the zeroing).

    The run holds ``depth + 3`` at once (the read-ahead, the one in use, the one whose block the simulator
    has in flight, and the rows it keeps for the next block: see ``iter_feed_packed(lookahead=True)``); the
    reader takes its first at once, a new one, while the helper still holds the reserved ones. ``depth + 1``
    are reserved (no more than the chunks after the first): the one more chunk is made by the reader
    beside the kernel, once per run (20 MB for a frames folder at 400 x 250). Nothing past :data:`RESERVE_MAX_BYTES`
    in all: a helper that is still writing a large array when the reader needs one makes the reader
    take a new one beside it (one rate per interval: 400 MB chunks at 400 x 250).
    """
    return max(0, min(int(depth) + 1, int(n_chunks) - 1, RESERVE_MAX_BYTES // max(int(chunk_bytes), 1)))


def plan_reads(src, sim, chunk: int | None = None, max_bytes: int = 256 << 20):
    """(row ranges to read, chunks to keep read ahead) for ``src`` feeding ``sim``.

    * One rate per interval: whole simulator blocks per read (at least ``chunk`` rows), so the schedule
      takes views of them and never joins rows; one read ahead, none for a memory-mapped input when
      ``sim.looks_ahead`` (the block in flight then overlaps the main thread's check of the next one, and
      a read ahead would only hold a third block of rows: 400 MB at 400 x 250). A deflated ``.npz`` keeps
      its reader thread.
    * Keyframes, ``chunk`` None: one read per simulator block, its keyframes exactly
      (:func:`sensor.rates.block_keyframe_rows`; consecutive reads share the one or two keyframes at the
      block boundary, copied, not read again), so every block's keyframes are one array and the
      schedule never joins them -- a copy of every keyframe, serial with the kernel, when a block's
      keyframes spanned two reads. Two reads ahead. Falls back to fixed chunks of 32 when one block's
      keyframes exceed :data:`ALIGNED_MAX_BYTES`.
    * Keyframes, ``chunk`` = K: fixed chunks of K keyframes, about two blocks' worth read ahead (with one
      chunk ahead, a chunk smaller than a block that completes no block leaves the kernel waiting).

    At most ``max_bytes`` of keyframes are read ahead.
    """
    row_bytes = 4 * src.shape[0] * src.shape[1]
    if src.per_interval:
        size = sim.block * -(-max(1, chunk or 1) // sim.block)
        mapped = getattr(src, "rate", None) is not None  # rows are views of a memory map (.npy, stored .npz)
        return [(i, min(src.n, i + size)) for i in range(0, src.n, size)], \
            0 if mapped and getattr(sim, "looks_ahead", False) else 1
    if chunk is None:
        from sensor.rates import block_keyframe_rows
        bounds = block_keyframe_rows(src.t_s, sim.block, sim.interval_s)
        biggest = max((j - i for i, j in bounds), default=1) * row_bytes
        if biggest <= ALIGNED_MAX_BYTES:
            return bounds, int(max(1, min(2, max_bytes // max(biggest, 1))))
        chunk = 32
    size = max(1, int(chunk))
    bounds = [(i, min(src.n, i + size)) for i in range(0, src.n, size)]
    if src.n < 2:
        return bounds, 1
    spacing_s = (src.t_s[-1] - src.t_s[0]) / (src.n - 1)  # mean keyframe spacing
    per_block = sim.block * sim.interval_s / spacing_s
    return bounds, int(max(1, min(math.ceil(2 * per_block / size), max_bytes // max(size * row_bytes, 1))))
