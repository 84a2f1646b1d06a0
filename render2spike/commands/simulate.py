"""``render2spike simulate``: irradiance frames or a rate array -> spike stream."""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
import time
import zipfile
import zlib
from pathlib import Path

import numpy as np

from sensor.io.buffers import RecyclingPool

HELP = "simulate a spike stream from irradiance frames or a photoelectron-rate array"
DESCRIPTION = """\
Turn time-varying light into the spike stream of a spike camera.

INPUT is one of
  * a frames folder written by `render2spike render` (frames.json + EXR files with
    channel Phi in e-/(s m^2)); Phi is converted to photoelectrons per interval
    with the profile's pixel area x fill factor x T_r and interpolated
    piecewise-linearly between frame timestamps;
  * an .npz file with `rate_e` (K, H, W) [expected photoelectrons per interval]
    and optionally `t_s` (K,) [s] keyframe times (without `t_s`: one row per
    interval of T_r = 50 us);
  * an .npy file holding `rate_e` (T, H, W), one row per interval.

The output is an .npz container (bit-packed spikes + metadata: interval, model,
profile, seed, source) or a SpikeCV-compatible .dat file. Both are written as the
blocks come (memory stays flat in duration): the .npz deflated block by block
(level 1), the .dat around the page cache where the file system allows
(O_DIRECT; set RENDER2SPIKE_DIRECT_IO=0 to write through the page cache).
If INPUT is smaller than the profile, the centred window of the profile is used.
"""
EXAMPLES = """\
examples:
  render2spike simulate out/frames --out spikes.npz
  render2spike simulate rate.npz --out spikes.dat --model isi --seed 7
  render2spike simulate out/frames --out ref.npz --reference   # step-by-step reference simulator
  render2spike simulate rate.npz --out alg2.npz --reset interval  # Algorithm 2's end-of-interval reset
"""


def register(sub) -> None:
    from sensor.models.registry import MODELS
    from sensor.profile import RESETS

    from render2spike.commands._common import add_overwrite
    p = sub.add_parser("simulate", help=HELP, description=DESCRIPTION, epilog=EXAMPLES,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("input", metavar="INPUT", help="frames folder, .npz (rate_e[, t_s]) or .npy (rate_e per interval)")
    p.add_argument("--out", required=True, metavar="SPIKES", help="output .npz (with metadata) or .dat")
    p.add_argument("--model", default="elssim", choices=MODELS, help="noise model (default: elssim)")
    p.add_argument("--profile", default="vidar-default", metavar="NAME|PATH",
                   help="sensor profile: bundled name or .npz file (default: vidar-default)")
    p.add_argument("--seed", type=int, default=0, help="spike seed: seeds every random draw of the simulation (default: 0)")
    p.add_argument("--reset", choices=RESETS, default=None,
                   help="pixel reset of elssim, overriding the profile's: 'crossing' (fires and resets the moment "
                        "the charge reaches the threshold; vidar-default) or 'interval' (Algorithm 2 as published)")
    p.add_argument("--reference", action="store_true",
                   help="use the step-by-step reference simulator instead of the fast event-driven one")
    p.add_argument("--chunk", type=int, default=None, metavar="K",
                   help="keyframes read per step (the result does not depend on it). Default: the keyframes of "
                        "one simulator block (1000 intervals) per read, so no block's keyframes are joined from "
                        "two reads, or 32 when a block's keyframes exceed 64 MB. A reader thread keeps about two "
                        "blocks of keyframes read ahead, at most 256 MB, and reuses up to 6 chunk buffers")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_overwrite(p)
    p.set_defaults(func=run)


def fit_profile(profile, shape, say=print):
    """The profile itself, or its centred window when the input is smaller."""
    from sensor.errors import ProfileError
    H, W = shape
    if (H, W) == profile.shape:
        return profile
    if H > profile.height or W > profile.width:
        raise ProfileError(f"input is {H}x{W} but profile '{profile.name}' is only {profile.height}x{profile.width}; "
                           "pass a profile of at least the input size (--profile)")
    top, left = (profile.height - H) // 2, (profile.width - W) // 2
    say(f"note: input is {H}x{W}; using the centred {H}x{W} window of profile '{profile.name}' "
        f"(rows {top}:{top + H}, cols {left}:{left + W})")
    return profile.window(top, left, H, W)


class _NpzMember:
    """One array of an .npz, read in row chunks straight from the zip stream (stored or deflated).

    Only the header is parsed up front; :meth:`rows` decodes the next rows, so memory stays at
    one chunk whatever the array's length (np.load would decompress the whole member).
    """

    def __init__(self, path: Path, name: str):
        import zipfile
        self.zf = zipfile.ZipFile(path)
        self.fh = self.zf.open(name + ".npy")
        version = np.lib.format.read_magic(self.fh)
        read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else \
            np.lib.format.read_array_header_2_0
        shape, fortran, dtype = read_header(self.fh)
        if fortran and len(shape) > 1:
            raise ValueError("Fortran-ordered arrays are not supported; save rate_e C-ordered")
        if dtype.hasobject:
            raise ValueError("object arrays are not supported")
        self.shape, self.dtype = tuple(shape), dtype
        self.row_bytes = int(np.prod(shape[1:], dtype=np.int64)) * dtype.itemsize
        self.pos = 0

    def rows(self, i: int, j: int, out=None) -> np.ndarray:
        """Rows [i, j) (the next ones), decoded into ``out`` (an array of this member's dtype and shape
        (j - i, ...)) when given, else into a new array."""
        if i != self.pos:
            raise ValueError("rows must be read in order")
        n = j - i
        if out is None:
            out = np.empty((n,) + self.shape[1:], self.dtype)
        view = memoryview(out.reshape(-1).view(np.uint8))
        got = 0
        while got < len(view):
            k = self.fh.readinto(view[got:])
            if not k:
                raise ValueError(f"truncated array: rows {i}..{j - 1} of {self.shape[0]}")
            got += k
        self.pos = j
        return out

    def close(self):
        self.fh.close()
        self.zf.close()


def _stored_member_map(path: Path, name: str):
    """A read-only memory map of array ``name`` of an .npz when it is stored (not deflated, not encrypted),
    like ``np.load(..., mmap_mode='r')`` of an .npy; else None.

    A stored member's bytes lie in the file as they are: the map spares reading them through the zip
    stream, which copies every byte twice. The member's CRC-32 is still checked: ``crc`` =
    (expected CRC, CRC of the member's bytes before the array) is returned with the map, and the reader
    folds in the rows as it hands them out (:meth:`RateSource._crc_rows`).
    Returns (map, crc) or None. Fortran-ordered arrays are left to the stream reader (which refuses
    them, as for a deflated member).
    """
    import struct
    with zipfile.ZipFile(path) as zf:
        try:
            info = zf.getinfo(name + ".npy")
        except KeyError:
            return None
        if info.compress_type != zipfile.ZIP_STORED or info.flag_bits & 0x1:
            return None
    with open(path, "rb") as fh:
        fh.seek(info.header_offset)
        local = fh.read(30)
        if len(local) < 30 or local[:4] != b"PK\x03\x04":
            return None
        n_name, n_extra = struct.unpack_from("<HH", local, 26)
        start = info.header_offset + 30 + n_name + n_extra
        fh.seek(start)
        version = np.lib.format.read_magic(fh)
        read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else \
            np.lib.format.read_array_header_2_0
        shape, fortran, dtype = read_header(fh)
        offset = fh.tell()
        if dtype.hasobject or fortran or len(shape) == 0 or \
                offset - start + int(np.prod(shape, dtype=np.int64)) * dtype.itemsize != info.file_size:
            return None
        fh.seek(start)
        crc = zlib.crc32(fh.read(offset - start))
    return np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=tuple(shape)), (info.CRC, crc)


class _ChunkPool(RecyclingPool):
    """Float32 chunk arrays recycled once nobody else holds them (:class:`sensor.io.buffers.RecyclingPool`):
    chunks of one input share a shape, so the reader takes back an array the simulator has dropped."""

    def __init__(self, keep: int = 6):
        super().__init__(np.float32, keep)


class RateSource:
    """Chunks of (rate_e (k, H, W) [e-/interval], t_s (k,) or None) from any supported INPUT.

    Nothing is read whole: an ``.npy`` (and an ``.npz`` whose ``rate_e`` is stored, as ``np.savez`` writes
    it) is memory-mapped and handed out in row chunks whose pages are dropped again once used, a deflated
    ``.npz`` member (``np.savez_compressed``) is decoded chunk by chunk from the zip stream, and a
    frames folder's EXR files are read (the Phi channel only). A reader thread reads and checks the
    next chunk while the kernel (which releases the GIL) simulates the current one (:meth:`chunks`).
    Memory is a few chunks, flat in duration.
    """

    def __init__(self, path, profile_for_phi=None):
        from sensor.errors import InputError
        self.path = Path(path)
        self.kind = None
        self._member = None
        self._mm = None
        self._crc = None  # a memory-mapped stored .npz member: its CRC-32, folded in as rows are handed out
        self._pool = _ChunkPool()
        self.rate = None
        if self.path.is_dir():
            from sensor.io.frames import read_frames
            self.frames = read_frames(self.path)
            self.kind = "frames"
            self.shape = self.frames.shape
            self.n = len(self.frames)
            self.per_interval = False
            self.t_s = self.frames.times_s
        elif not self.path.exists():
            raise InputError("does not exist", path=self.path)
        elif self.path.suffix == ".npz":
            try:
                with np.load(self.path, allow_pickle=False) as z:
                    if "rate_e" not in z:
                        raise InputError(f"no array 'rate_e' (has: {', '.join(z.files)})", path=self.path,
                                         field="rate_e")
                    self.t_s = z["t_s"].astype(np.float64) if "t_s" in z else None
                mapped = _stored_member_map(self.path, "rate_e")
                if mapped is None:  # deflated (or otherwise not mappable): decoded chunk by chunk
                    self._member = _NpzMember(self.path, "rate_e")
                    shape = self._member.shape
                else:
                    self.rate, (want, crc) = mapped
                    self._crc = {"want": want, "crc": crc, "rows": 0}
                    shape = self.rate.shape
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
            shape = self.rate.shape
            self.t_s = None
            self.kind = "array"
        else:
            raise InputError("INPUT must be a frames folder, an .npz (rate_e[, t_s]) or an .npy rate array",
                             path=self.path)
        if self.kind == "array":
            if len(shape) != 3:
                raise InputError(f"rate_e must be (K, H, W); got shape {shape}", path=self.path, field="rate_e")
            if self.t_s is not None and self.t_s.shape != (shape[0],):
                raise InputError(f"t_s has shape {self.t_s.shape}; expected ({shape[0]},)", path=self.path,
                                 field="t_s")
            if shape[0] == 0 or 0 in shape[1:]:
                raise InputError(f"rate_e is empty (shape {shape})", path=self.path, field="rate_e")
            if self.t_s is not None:
                from sensor.rates import check_times
                check_times(self.t_s, path=self.path)
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
        from sensor.errors import InputError
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
        from sensor.errors import InputError
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
        if count_bad(rate[ov:]):  # one pass; the slow search for the first bad value only on failure
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
        if self._member is not None:
            self._member.close()
            self._member = None
        if self._mm is not None:
            try:
                self._mm.close()
            except BufferError:  # rows still referenced by the caller: the map closes with the last of them
                pass
            self._mm = None


def run(args) -> int:
    frozen = {}
    try:
        return _run(args, frozen)
    finally:
        if frozen.get("frozen"):  # the start-up's objects go back to the collector (see _start_up)
            import gc
            gc.unfreeze()


def _run(args, frozen: dict) -> int:
    from tqdm import tqdm

    from sensor.io.spikefile import SpikeWriter

    t0 = time.perf_counter()
    say = (lambda m: None) if args.quiet else print
    with _start_up(frozen):
        src, profile, sim, chunks = _prepare(args, say)
    desc = sim.describe()
    extra = {"input_kind": src.kind, "simulator": desc}
    total = src.n_intervals(profile.interval_s)
    with SpikeWriter(args.out, interval_s=profile.interval_s, model=args.model, profile_id=profile.name,
                     seed=args.seed, source=str(Path(args.input).resolve()), implementation=sim.implementation,
                     extra=extra, background=True, expected_intervals=total) as writer, \
            tqdm(total=total, unit="interval", disable=args.quiet, desc="simulate") as bar:
        for rate, t, overlap in chunks:
            # the reader checked the rates (naming file and row) and hands each fresh chunk over; its first
            # `overlap` keyframes repeat the last ones of the previous chunk (block-aligned reads)
            # lookahead: the kernel's threads start on each block while this thread hands over the one before
            for bits in sim.iter_feed_packed(rate, t, checked=True, owned=True, overlap=overlap, lookahead=True):
                writer.write_packed(bits, profile.shape)  # counted, re-ordered and written by a writer thread
                bar.update(bits.shape[0])
        for bits in sim.iter_finish_packed():  # the block in flight, then the last, partial one
            writer.write_packed(bits, profile.shape)
            bar.update(bits.shape[0])
    dt = time.perf_counter() - t0
    n = writer.n_intervals
    rate_hz = writer.n_spikes / max(n * profile.height * profile.width, 1) / profile.interval_s
    say(f"wrote {args.out}: {n} intervals ({n * profile.interval_s:.4f} s of camera time), {profile.height}x"
        f"{profile.width}, model {args.model} ({sim.implementation}), seed {args.seed}; mean spike rate "
        f"{rate_hz:.1f} Hz per pixel; {dt:.1f} s wall")
    return 0


#: largest read of one simulator block's keyframes for block-aligned reads (else fixed-size chunks)
ALIGNED_MAX_BYTES = 64 << 20

#: most memory of chunk arrays faulted in ahead during the start-up (:func:`reserve_count`)
RESERVE_MAX_BYTES = 128 << 20


def reserve_count(n_chunks: int, depth: int, chunk_bytes: int) -> int:
    """How many chunk arrays a reader with ``depth`` chunks read ahead has faulted in while the command
    starts (:meth:`sensor.io.buffers.RecyclingPool.reserve`), not by the reader beside the running kernel
    (0.1-0.2 s of CPU over 4 s of frames on the project's VM, where a first touch runs at ~0.4 GB/s).

    The run holds ``depth + 3`` at once (the read-ahead, the one in use, the one whose block the simulator
    has in flight, and the rows it keeps for the next block: see ``iter_feed_packed(lookahead=True)``); the
    reader takes its first at once, a new one, while the helper still holds the reserved ones. ``depth + 1``
    are reserved (no more than the chunks after the first), as before the lookahead: the one more chunk
    it holds is made by the reader beside the kernel, once per run (20 MB for a frames folder at
    400 x 250; not measured separately). Nothing past :data:`RESERVE_MAX_BYTES`
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


@contextlib.contextmanager
def _start_up(frozen: dict | None = None):
    """No cyclic garbage collection while the command starts: imports and numba's cache load make
    only long-lived objects, and the collector's passes over them cost ~0.15 s of start-up.

    With a ``frozen`` dict, they are then also kept out of the run's collections (``gc.freeze``;
    ``frozen["frozen"]`` set, and :func:`run` calls ``gc.unfreeze`` when it ends, so a process that
    calls the command in-process gets its collector back as it was). Otherwise the ~100,000 objects
    made with the collector off land in its youngest generation and the run's first collections scan
    them all (0.09 s over 4 s of frames, on the main thread between kernel blocks; 0.009 s frozen).
    The price: garbage the start-up made is not freed until the run ends (a few hundred objects with
    numba's cache warm; ~30 MB when numba compiles the kernels afresh). Nothing is frozen when the
    collector was off, or when the process froze objects itself (its freeze is left alone).
    """
    import gc
    was = gc.isenabled()
    freeze = frozen is not None and was and gc.get_freeze_count() == 0
    gc.disable()
    try:
        yield
    finally:
        if freeze:
            gc.freeze()
            frozen["frozen"] = True
        if was:
            gc.enable()


def _lean_numba() -> None:
    """In the ``render2spike`` command only: numba's optional extras stay unloaded.

    When numba first loads a kernel it imports its NumPy support, which looks for SciPy's BLAS (for
    ``np.dot`` and ``np.linalg`` in compiled code) and for cffi; importing ``scipy.linalg`` and cffi for
    that took 0.10 of the command's 0.4-0.5 s start-up, and the spike kernels use neither. Here that
    support is imported first with both hidden, so numba records them as absent for this process.
    A program that imports the package (and may compile its own linear algebra) is left alone, as is a
    process that has SciPy already."""
    import importlib.abc

    import render2spike
    if not render2spike.cli_process() or "scipy" in sys.modules or "numba.np.arraymath" in sys.modules:
        return

    class _Hide(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path, target=None):
            if name.split(".")[0] in ("scipy", "cffi"):
                raise ImportError(f"{name} is not loaded by render2spike simulate")
            return None

    hide = _Hide()
    sys.meta_path.insert(0, hide)
    try:
        import numba.core.typing.cffi_utils  # noqa: F401
        import numba.np.arraymath  # noqa: F401
    except ImportError:  # no numba: the reference simulator runs
        pass
    finally:
        sys.meta_path.remove(hide)


def _prepare(args, say):
    """Open INPUT and the profile, make the simulator, start reading, load the kernels."""
    _lean_numba()
    from sensor import SensorProfile, SpikeSimulator
    from sensor.errors import InputError

    from render2spike.commands._common import check_output
    check_output(args.out, inputs=[args.input], overwrite=args.overwrite, say=say)
    src = RateSource(args.input)
    profile = fit_profile(SensorProfile.load(args.profile), src.shape, say)
    if getattr(args, "reset", None):
        profile = profile.replace(reset=args.reset)
    rendered_for = (src.frames.manifest.get("profile") or {}).get("name") if src.kind == "frames" else None
    if rendered_for and rendered_for != profile.name:
        say(f"warning: the frames were rendered for profile '{rendered_for}' (its QE weights Phi); simulating "
            f"with '{profile.name}' uses that QE but this profile's pixel area and noise maps")
    sim = SpikeSimulator(profile, args.model, args.seed, implementation="reference" if args.reference else "fast",
                         per_interval=src.per_interval)
    total = src.n_intervals(profile.interval_s)
    if total < 1:
        what = "keyframes span" if not src.per_interval else "input holds"
        span = (f"{src.t_s[-1] - src.t_s[0]:.6g} s ({src.n} keyframe(s))" if not src.per_interval else "no rows")
        raise InputError(f"the {what} {span}: less than one whole interval of {profile.interval_s * 1e6:g} us "
                         "(need at least two keyframes one interval apart)", path=args.input,
                         field="frames" if src.kind == "frames" else "t_s")
    if args.chunk is not None and args.chunk < 1:
        raise InputError(f"--chunk must be a positive number of keyframes, got {args.chunk}", field="--chunk")
    bounds, ahead = plan_reads(src, sim, args.chunk)
    chunks = src.chunks(profile, bounds, ahead)  # the reader thread starts now ...
    sim.warm_up()  # ... while numba loads the kernels from its cache here
    return src, profile, sim, chunks
