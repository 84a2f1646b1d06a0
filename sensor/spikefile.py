"""Spike files: SpikeCV/Spike-Zoo ``.dat`` and the metadata container ``.npz``.

``.dat`` layout (bit-compatible with SpikeCV and Spike-Zoo)
-----------------------------------------------------------
No header. Frame after frame, each ``H * W / 8`` bytes. Within a frame, pixel
``p = r * W + c`` of the *stored* frame is bit ``p % 8`` (least significant bit
first) of byte ``p // 8``. Rows are stored bottom-up: stored row ``r`` is image
row ``H - 1 - r`` (a vertical flip, no horizontal flip). Raw Vidar captures are
416 columns wide; ``drop_columns=16`` (or ``raw_width=416``) drops the 16 extra
columns on the right of the stored frame after reading.

Container ``.npz`` (``format: render2spike-spikes``, version 1)
--------------------------------------------------------------
``packed``: uint8 (T, ceil(H*W/8)) bit-packed frames in image orientation
(``numpy.packbits`` of the row-major frame, ``bitorder='little'``);
``meta_json``: UTF-8 JSON with ``height``, ``width``, ``n_intervals``,
``interval_s``, ``model``, ``implementation``, ``profile_id``, ``seed``,
``source`` and ``provenance``.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np

from .errors import SpikeFileError
from .fileio import atomic_path, provenance

SPIKES_FORMAT = "render2spike-spikes"
SPIKES_VERSION = 1


# ------------------------------------------------------------------ bit layout
def pack_frames(spikes) -> np.ndarray:
    """bool (n, H, W) -> uint8 (n, ceil(H*W/8)): pixel p = r*W + c in byte p//8, bit p%8 (LSB first).

    The in-memory and container layout (image orientation, no flip).
    """
    s = np.asarray(spikes, bool)
    return np.packbits(s.reshape(s.shape[0], -1), axis=1, bitorder="little")


def count_bits(bits) -> int:
    """Number of set bits in a uint8 array (spikes in packed frames); ``np.bitwise_count`` where numpy has it."""
    bits = np.asarray(bits, np.uint8)
    if not bits.size:
        return 0
    if hasattr(np, "bitwise_count"):  # numpy >= 2.0: ~10-20x faster than unpackbits
        return int(np.bitwise_count(bits).sum(dtype=np.int64))
    return int(np.unpackbits(bits).sum(dtype=np.int64))


def unpack_frames(bits, shape) -> np.ndarray:
    """Inverse of :func:`pack_frames`: uint8 (n, ceil(H*W/8)) -> bool (n, H, W)."""
    h, w = shape
    bits = np.asarray(bits, np.uint8)
    return np.unpackbits(bits, axis=1, count=h * w, bitorder="little").view(bool).reshape(bits.shape[0], h, w)


def packed_to_dat(bits, height: int, width: int) -> np.ndarray:
    """Packed image-orientation frames -> .dat frames (rows bottom-up), without unpacking when W % 8 == 0."""
    bits = np.asarray(bits, np.uint8)
    if width % 8 == 0:
        n = bits.shape[0]
        return np.ascontiguousarray(bits.reshape(n, height, width // 8)[:, ::-1, :]).reshape(n, -1)
    return pack_dat_frames(unpack_frames(bits, (height, width)))


# ----------------------------------------------------------------------- .dat
def pack_dat_frames(spikes) -> np.ndarray:
    """bool (T, H, W) image-orientation spikes -> uint8 (T, H*W/8) .dat frames (flipped, LSB first)."""
    s = np.asarray(spikes, dtype=bool)
    if s.ndim != 3:
        raise SpikeFileError(f"spikes must be (T, H, W); got {s.shape}")
    T, H, W = s.shape
    if (H * W) % 8:
        raise SpikeFileError(f"H*W = {H * W} is not a multiple of 8; .dat frames need whole bytes")
    return pack_frames(s[:, ::-1, :])


def unpack_dat_frames(frames, height: int, width: int) -> np.ndarray:
    """uint8 (T, H*W/8) .dat frames -> bool (T, H, W) in image orientation."""
    return unpack_frames(frames, (height, width))[:, ::-1, :]


def write_dat(path, spikes) -> Path:
    """Write bool spikes (T, H, W) [image orientation] to a SpikeCV-compatible .dat, atomically."""
    frames = pack_dat_frames(spikes)
    path = Path(path)
    with atomic_path(path) as tmp:
        frames.tofile(tmp)
    return path


def dat_frame_count(path, height: int = 250, width: int = 400) -> int:
    """Number of whole frames in a .dat file; error if the size is not a whole number of frames."""
    path = Path(path)
    if not path.is_file():
        raise SpikeFileError("file does not exist", path=path)
    if (height * width) % 8:
        raise SpikeFileError(f"height*width = {height * width} is not a multiple of 8", path=path)
    frame_bytes = height * width // 8
    size = path.stat().st_size
    if size % frame_bytes:
        raise SpikeFileError(f"file size {size} bytes is not a whole number of {height}x{width} frames "
                             f"({frame_bytes} bytes each; {size // frame_bytes} frames and {size % frame_bytes} "
                             f"bytes left over). Check --height/--width (raw Vidar captures are 416 wide)",
                             path=path)
    return size // frame_bytes


def read_dat(path, height: int = 250, width: int = 400, *, drop_columns: int = 0, start: int = 0,
             count: int | None = None) -> np.ndarray:
    """Read a SpikeCV-compatible .dat file as bool (T, H, W) in image orientation.

    Parameters
    ----------
    path : path-like
        The .dat file.
    height, width : int
        Stored frame size (use ``width=416, drop_columns=16`` for raw Vidar captures).
    drop_columns : int
        Columns to drop on the right after reading (416 -> 400 with 16).
    start, count : int
        Read frames ``start .. start+count-1`` only (memory-mapped).
    """
    n = dat_frame_count(path, height, width)
    frame_bytes = height * width // 8
    count = n - start if count is None else int(count)
    if start < 0 or count < 0 or start + count > n:
        raise SpikeFileError(f"frames {start}..{start + count - 1} requested but the file has {n}", path=path)
    if count == 0:
        return np.zeros((0, height, width - drop_columns), bool)
    mm = np.memmap(path, dtype=np.uint8, mode="r", offset=start * frame_bytes, shape=(count, frame_bytes))
    spikes = unpack_dat_frames(np.asarray(mm), height, width)
    if drop_columns:
        spikes = spikes[:, :, :width - drop_columns]
    return spikes


# --------------------------------------------------------------- container
def write_spikes(path, spikes=None, *, packed=None, height=None, width=None, interval_s: float, model: str,
                 profile_id: str, seed, source: str = "", implementation: str = "", extra: dict | None = None) -> Path:
    """Write spikes with their metadata to a compressed ``.npz`` container, atomically.

    Give either ``spikes`` bool (T, H, W) or ``packed`` uint8 (T, ceil(H*W/8))
    with ``height`` and ``width``.
    """
    if packed is None:
        s = np.asarray(spikes, bool)
        if s.ndim != 3:
            raise SpikeFileError(f"spikes must be (T, H, W); got {s.shape}")
        T, height, width = s.shape
        packed = pack_frames(s)
    meta = {"format": SPIKES_FORMAT, "version": SPIKES_VERSION, "height": int(height), "width": int(width),
            "n_intervals": int(packed.shape[0]), "interval_s": float(interval_s), "model": model,
            "implementation": implementation, "profile_id": profile_id, "seed": seed, "source": str(source),
            "provenance": provenance()}
    meta.update(extra or {})
    buf = io.BytesIO()
    np.savez_compressed(buf, packed=packed, meta_json=np.frombuffer(json.dumps(meta, default=str).encode(), np.uint8))
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.getvalue())
    return path


def read_spikes_meta(path) -> dict:
    """The metadata of a spike container (no spike data is decoded)."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(bytes(z["meta_json"]).decode())
    except (OSError, ValueError, KeyError) as exc:
        raise SpikeFileError(f"not a render2spike spike container ({exc})", path=path) from exc
    if meta.get("format") != SPIKES_FORMAT:
        raise SpikeFileError(f"format is '{meta.get('format')}', expected '{SPIKES_FORMAT}'", path=path,
                             field="format")
    return meta


def read_spikes(path, height: int = 250, width: int = 400, drop_columns: int = 0):
    """Read spikes from a container (.npz) or a .dat file: returns (bool (T, H, W), meta dict).

    For .dat files (no metadata) ``height``/``width``/``drop_columns`` give the
    layout and the meta dict holds only those.
    """
    path = Path(path)
    if path.suffix.lower() == ".dat":
        s = read_dat(path, height, width, drop_columns=drop_columns)
        return s, {"height": s.shape[1], "width": s.shape[2], "n_intervals": s.shape[0], "source": str(path)}
    meta = read_spikes_meta(path)
    with np.load(path, allow_pickle=False) as z:
        packed = z["packed"]
    return unpack_frames(packed, (meta["height"], meta["width"])), meta


class SpikeWriter:
    """Write a spike stream block by block to ``.dat`` or ``.npz``; the file appears only on :meth:`close`.

    ``.dat`` streams to a temporary file beside the target (bounded memory);
    ``.npz`` keeps the bit-packed blocks (1 bit per pixel-interval) in memory
    until close. On an exception inside a ``with`` block nothing is left behind.
    """

    def __init__(self, path, *, interval_s: float, model: str, profile_id: str, seed, source: str = "",
                 implementation: str = "", extra: dict | None = None):
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
        if self.kind == "dat":
            self._ctx = atomic_path(self.path)
            self._tmp = self._ctx.__enter__()
            self._fh = open(self._tmp, "wb")

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
        shape = tuple(int(x) for x in shape)
        if self.shape is None:
            self.shape = shape
        elif shape != self.shape:
            raise SpikeFileError(f"frame shape changed from {self.shape} to {shape}", path=self.path)
        self.n_intervals += bits.shape[0]
        self.n_spikes += count_bits(bits)
        if self.kind == "dat":
            packed_to_dat(bits, *shape).tofile(self._fh)
        else:
            self._blocks.append(bits)

    def close(self) -> Path:
        if self.kind == "dat":
            self._fh.close()
            self._ctx.__exit__(None, None, None)
            return self.path
        H, W = self.shape if self.shape is not None else (0, 0)
        packed = np.concatenate(self._blocks) if self._blocks else np.zeros((0, (H * W + 7) // 8), np.uint8)
        m = self.meta
        return write_spikes(self.path, packed=packed, height=H, width=W, interval_s=m["interval_s"], model=m["model"],
                            profile_id=m["profile_id"], seed=m["seed"], source=m["source"],
                            implementation=m["implementation"], extra=m["extra"])

    def abort(self) -> None:
        if self.kind == "dat" and self._fh is not None:
            self._fh.close()
            try:
                self._ctx.__exit__(SpikeFileError, SpikeFileError("aborted"), None)
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


class PackedSpikes:
    """A spike stream held bit-packed in memory (1 bit per pixel-interval), unpacked window by window.

    ``packed`` is uint8 (T, ceil(H*W/8)) in the :func:`pack_frames` layout; ``shape`` is (H, W).
    """

    def __init__(self, packed, shape):
        self.packed = np.asarray(packed, np.uint8)
        self.frame_shape = (int(shape[0]), int(shape[1]))

    @property
    def shape(self) -> tuple[int, int, int]:
        """(T, H, W)."""
        return (self.packed.shape[0],) + self.frame_shape

    def __len__(self) -> int:
        return self.packed.shape[0]

    def window(self, start: int, stop: int) -> np.ndarray:
        """bool (stop - start, H, W): intervals ``start .. stop-1``."""
        return unpack_frames(self.packed[max(start, 0):stop], self.frame_shape)

    def counts(self, start: int = 0, stop: int | None = None, chunk: int = 4096) -> np.ndarray:
        """Spikes per pixel over intervals ``start .. stop-1``, int64 (H, W), in bounded memory."""
        stop = len(self) if stop is None else stop
        out = np.zeros(self.frame_shape, np.int64)
        for a in range(start, stop, chunk):
            out += self.window(a, min(a + chunk, stop)).sum(axis=0)
        return out

    def total(self) -> int:
        """Total number of spikes."""
        return int(np.unpackbits(self.packed).sum(dtype=np.int64)) if self.packed.size else 0
