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

Other layouts (read by :func:`read_spikes`, listed by :func:`spike_layouts`)
---------------------------------------------------------------------------
``vidar-raw`` (250 x 416 .dat, 16 columns dropped), Spike-Zoo / UHSR ``.npz``
(``spk`` (T, H, W)), SpikingSIM ``.npz`` (``arr_0`` (H, W, T)), RSIR ``.npz``
(``seq`` bit-packed along time, ``length``) and render2spike HDF5 (``.h5``,
dataset ``spikes``, written by :func:`write_h5`). Every reader turns a corrupt,
truncated or inconsistent file into one :class:`SpikeFileError` naming the file
and what is wrong.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import sys
from pathlib import Path

import numpy as np

from sensor.errors import SpikeFileError, UnknownMethodError
from sensor.io.fileio import DirectStream, atomic_path, provenance
from sensor.units import INTERVAL_S

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
        # counted 8 bytes at a time (a uint64 view): 8x fewer counts and sums than byte by byte
        flat = np.ascontiguousarray(bits).reshape(-1)
        n8 = flat.size - flat.size % 8
        whole = int(np.bitwise_count(flat[:n8].view(np.uint64)).sum(dtype=np.int64)) if n8 else 0
        return whole + int(np.bitwise_count(flat[n8:]).sum(dtype=np.int64))
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
    meta = _container_meta_json(height, width, packed.shape[0], interval_s, model, implementation, profile_id, seed,
                                source, extra)
    buf = io.BytesIO()
    np.savez_compressed(buf, packed=packed, meta_json=meta)
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.getvalue())
    return path


def _container_meta_json(height, width, n_intervals, interval_s, model, implementation, profile_id, seed, source,
                         extra) -> np.ndarray:
    """A container's ``meta_json`` member: the metadata dict as UTF-8 JSON bytes, uint8 (n,)."""
    meta = {"format": SPIKES_FORMAT, "version": SPIKES_VERSION, "height": int(height), "width": int(width),
            "n_intervals": int(n_intervals), "interval_s": float(interval_s), "model": model,
            "implementation": implementation, "profile_id": profile_id, "seed": seed, "source": str(source),
            "provenance": provenance()}
    meta.update(extra or {})
    return np.frombuffer(json.dumps(meta, default=str).encode(), np.uint8)


def _npy_bytes(a) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=False)
    return buf.getvalue()


def _npy_header(shape) -> bytes:
    """The ``.npy`` header of a C-order uint8 array of ``shape`` (what ``np.save`` writes before the data)."""
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": "|u1", "fortran_order": False, "shape": tuple(shape)})
    return buf.getvalue()


#: deflate level of a container streamed by :class:`SpikeWriter` (``expected_intervals`` given): on packed
#: spikes (5 lux, 400 x 250) level 1 compresses 7.1x at ~240 MB/s of one core, level 6 (``np.savez_compressed``'s)
#: 9.7x at ~50 MB/s, 5 s per camera-second (250 MB of packed bits)
STREAM_COMPRESSLEVEL = 1


def read_spikes_meta(path) -> dict:
    """The metadata of a spike container (no spike data is decoded)."""
    path = Path(path)
    with _npz(path) as z:
        meta = _container_meta(z, path)
    return meta


def _container_meta(z, path) -> dict:
    if "meta_json" not in z.files:
        raise SpikeFileError(f"not a render2spike spike container: no 'meta_json' (has: {', '.join(z.files)})",
                             path=path, field="meta_json")
    try:
        meta = json.loads(bytes(_member(z, "meta_json", path)).decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SpikeFileError(f"'meta_json' is not UTF-8 JSON ({exc})", path=path, field="meta_json") from exc
    if not isinstance(meta, dict) or meta.get("format") != SPIKES_FORMAT:
        fmt = meta.get("format") if isinstance(meta, dict) else None
        raise SpikeFileError(f"format is '{fmt}', expected '{SPIKES_FORMAT}'", path=path, field="format")
    for key in ("height", "width"):
        v = meta.get(key)
        if not isinstance(v, int) or v < 1:
            raise SpikeFileError(f"must be a positive integer; got {v!r}", path=path, field=key)
    return meta


# ------------------------------------------------------------------ layouts
#: name -> one-line description of every spike-file layout :func:`read_spikes` understands
LAYOUTS = {
    "container": "render2spike container .npz: 'packed' uint8 (T, ceil(H*W/8)) bit-packed frames (image "
                 "orientation, LSB first) + 'meta_json' (height, width, interval_s, ...)",
    "dat": "SpikeCV / Spike-Zoo / Vidar .dat: no header, H*W/8 bytes per frame, LSB first, rows stored "
           "bottom-up; any H x W (default 250 x 400; pass height/width otherwise)",
    "vidar-raw": "raw Vidar .dat capture 250 x 416: the 16 extra columns on the right are dropped (-> 250 x 400)",
    "spikezoo": "Spike-Zoo / UHSR .npz: key 'spk' uint8 or bool (T, H, W), values 0/1",
    "spikingsim": "SpikingSIM .npz: key 'arr_0' (H, W, T), values 0/1 (time is the LAST axis)",
    "rsir": "RSIR .npz: 'seq' uint8 (ceil(T/8), H, W) with interval i in bit (i % 8) of seq[i // 8] (LSB first), "
            "'length' = T, optional 'tag' (H, W) ground truth",
    "h5": "render2spike HDF5 (.h5/.hdf5, from `render2spike convert`): dataset 'spikes', bit-packed uint8 "
          "(T, ceil(H*W/8)) or uint8 (T, H, W), with height/width/encoding/interval_s attributes",
}

H5_FORMAT = "render2spike-spikes-h5"
_NPZ_KEYS = {"container": ("packed", "meta_json"), "spikezoo": ("spk",), "rsir": ("seq", "length"),
             "spikingsim": ("arr_0",)}
_VIDAR_H, _VIDAR_W, _VIDAR_RAW_W = 250, 400, 416


def spike_layouts() -> dict:
    """The spike-file layouts :func:`read_spikes` reads: ``{name: description}`` (pass a name as ``layout=``)."""
    return dict(LAYOUTS)


class _npz:
    """``np.load`` of an .npz whose every failure is a :class:`SpikeFileError` naming the file."""

    def __init__(self, path):
        self.path = Path(path)

    def __enter__(self):
        if not self.path.is_file():
            raise SpikeFileError("file does not exist", path=self.path)
        try:
            self.z = np.load(self.path, allow_pickle=False)
        except Exception as exc:  # BadZipFile, EOFError, OSError, ValueError, zlib.error ...
            raise SpikeFileError(f"not a readable .npz archive (corrupt or truncated: {type(exc).__name__}: {exc})",
                                 path=self.path) from exc
        if not hasattr(self.z, "files"):
            raise SpikeFileError("is a single .npy array, not an .npz archive", path=self.path)
        return self.z

    def __exit__(self, *exc):
        self.z.close()
        return False


def _member(z, key, path) -> np.ndarray:
    """One array of an open .npz; a damaged member is a :class:`SpikeFileError` naming file and key."""
    if key not in z.files:
        raise SpikeFileError(f"missing array '{key}' (has: {', '.join(z.files) or 'nothing'})", path=path, field=key)
    try:
        return z[key]
    except Exception as exc:  # truncated member: EOFError, BadZipFile, zlib.error, ValueError
        raise SpikeFileError(f"array '{key}' cannot be read (corrupt or truncated: {type(exc).__name__}: {exc})",
                             path=path, field=key) from exc


def _binary(a, path, key) -> np.ndarray:
    """0/1 array -> bool, or an error naming the key when other values occur."""
    a = np.asarray(a)
    if a.dtype == bool:
        return a
    if not (np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)):
        raise SpikeFileError(f"dtype {a.dtype} is not a spike array (expected bool or 0/1 integers)", path=path,
                             field=key)
    if a.size and (a.min() < 0 or a.max() > 1 or (np.issubdtype(a.dtype, np.floating) and np.any(a % 1))):
        raise SpikeFileError(f"holds values other than 0 and 1 (min {a.min()}, max {a.max()}); spike arrays are "
                             "binary (counts per window are not spikes)", path=path, field=key)
    return a.astype(bool)


def _three_d(a, path, key, axes) -> None:
    if a.ndim != 3:
        raise SpikeFileError(f"has shape {a.shape}; expected 3 axes {axes}", path=path, field=key)


def detect_layout(path, *, height=None, width=None) -> str:
    """The layout of a spike file, or a :class:`SpikeFileError` saying why it is ambiguous (pass ``layout=``)."""
    path = Path(path)
    if not path.exists():
        raise SpikeFileError("file does not exist", path=path)
    if path.is_dir():
        raise SpikeFileError("is a folder, not a spike file", path=path)
    suffix = path.suffix.lower()
    if suffix in (".h5", ".hdf5"):
        return "h5"
    if suffix == ".dat":
        if height is not None or width is not None:
            return "dat"
        size = path.stat().st_size
        fits = [name for name, w in (("dat", _VIDAR_W), ("vidar-raw", _VIDAR_RAW_W))
                if size and size % (_VIDAR_H * w // 8) == 0]
        if len(fits) == 1:
            return fits[0]
        if not fits:
            raise SpikeFileError(f"file size {size} bytes is a whole number of neither 250x400 (12500 bytes) nor "
                                 "raw 250x416 (13000 bytes) frames; pass height= and width= (CLI: --height/--width)",
                                 path=path)
        raise SpikeFileError(f"ambiguous layout: {size} bytes is a whole number of both 250x400 and raw 250x416 "
                             "frames; pass layout='dat' or layout='vidar-raw' (CLI: --layout)", path=path)
    if suffix == ".npz":
        with _npz(path) as z:
            files = set(z.files)
        found = [name for name, keys in _NPZ_KEYS.items() if all(k in files for k in keys)]
        if "container" in found:
            return "container"
        if len(found) == 1:
            return found[0]
        if not found:
            raise SpikeFileError(f"no known spike layout: arrays {', '.join(sorted(files)) or 'none'}; known: "
                                 + "; ".join(f"{n} ({', '.join(k)})" for n, k in _NPZ_KEYS.items()), path=path)
        raise SpikeFileError(f"ambiguous layout: the archive matches {', '.join(found)}; pass layout= "
                             f"(one of {', '.join(found)}; CLI: --layout)", path=path)
    raise SpikeFileError(f"unknown spike file type '{suffix}' (expected .dat, .npz, .h5/.hdf5); pass layout= "
                         f"(one of {', '.join(LAYOUTS)})", path=path)


def _read_h5(path):
    try:
        import h5py
    except ImportError as exc:  # pragma: no cover - h5py is a core dependency
        from sensor.errors import DependencyError
        raise DependencyError("reading .h5 spike files needs h5py: pip install h5py") from exc
    try:
        with h5py.File(path, "r") as f:
            if "spikes" not in f:
                raise SpikeFileError(f"no dataset 'spikes' (has: {', '.join(f.keys()) or 'nothing'})", path=path,
                                     field="spikes")
            d = f["spikes"]
            attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in d.attrs.items()}
            data = d[()]
    except SpikeFileError:
        raise
    except Exception as exc:  # OSError (truncated / not HDF5), KeyError
        raise SpikeFileError(f"not a readable HDF5 file (corrupt or truncated: {type(exc).__name__}: {exc})",
                             path=path) from exc
    enc = attrs.get("encoding")
    meta = {}
    if "meta_json" in attrs:
        try:
            meta = json.loads(attrs["meta_json"])
        except (TypeError, json.JSONDecodeError) as exc:
            raise SpikeFileError(f"attribute 'meta_json' is not JSON ({exc})", path=path, field="meta_json") from exc
    if enc == "packbits-little":
        try:
            H, W = int(attrs["height"]), int(attrs["width"])
        except (KeyError, TypeError, ValueError) as exc:
            raise SpikeFileError("packed 'spikes' needs integer 'height' and 'width' attributes", path=path,
                                 field="spikes.attrs") from exc
        if data.ndim != 2 or data.dtype != np.uint8 or data.shape[1] != (H * W + 7) // 8:
            raise SpikeFileError(f"packed 'spikes' has shape {data.shape} ({data.dtype}); expected uint8 "
                                 f"(T, {(H * W + 7) // 8}) for {H} x {W} frames", path=path, field="spikes")
        s = unpack_frames(data, (H, W))
    elif enc == "uint8" or (enc is None and data.ndim == 3):  # (another tool's file: 0/1 (T, H, W), no encoding)
        _three_d(data, path, "spikes", "(T, H, W)")
        s = _binary(data, path, "spikes")
    else:
        raise SpikeFileError(f"attribute 'encoding' is {enc!r}; expected 'packbits-little' or 'uint8'", path=path,
                             field="spikes.attrs.encoding")
    meta.setdefault("height", s.shape[1])
    meta.setdefault("width", s.shape[2])
    meta["n_intervals"] = s.shape[0]
    return s, meta


def _read_layout(path, layout, height, width, drop_columns):
    """(spikes bool (T, H, W) in image orientation, meta dict) for one named layout."""
    if layout in ("dat", "vidar-raw"):
        if layout == "vidar-raw":
            h, w = height or _VIDAR_H, width or _VIDAR_RAW_W
            drop = drop_columns or (w - _VIDAR_W if w == _VIDAR_RAW_W else 0)
        else:
            h, w, drop = height or _VIDAR_H, width or _VIDAR_W, drop_columns
        s = read_dat(path, h, w, drop_columns=drop)
        return s, {"height": s.shape[1], "width": s.shape[2], "n_intervals": s.shape[0], "stored_width": w,
                   "drop_columns": drop}
    if layout == "h5":
        return _read_h5(path)
    with _npz(path) as z:
        if layout == "container":
            meta = _container_meta(z, path)
            packed = _member(z, "packed", path)
            H, W = meta["height"], meta["width"]
            if packed.ndim != 2 or packed.dtype != np.uint8 or packed.shape[1] != (H * W + 7) // 8:
                raise SpikeFileError(f"'packed' has shape {packed.shape} ({packed.dtype}) but meta says {H} x {W} "
                                     f"frames, which need uint8 (T, {(H * W + 7) // 8}); the file is inconsistent",
                                     path=path, field="packed")
            n = meta.get("n_intervals")
            if n is not None and n != packed.shape[0]:
                raise SpikeFileError(f"meta says n_intervals = {n} but 'packed' holds {packed.shape[0]} frames",
                                     path=path, field="n_intervals")
            s = unpack_frames(packed, (H, W))
        elif layout == "spikezoo":
            a = _member(z, "spk", path)
            _three_d(a, path, "spk", "(T, H, W)")
            s, meta = _binary(a, path, "spk"), {}
        elif layout == "spikingsim":
            a = _member(z, "arr_0", path)
            _three_d(a, path, "arr_0", "(H, W, T)")
            s, meta = np.ascontiguousarray(np.moveaxis(_binary(a, path, "arr_0"), 2, 0)), {}
        elif layout == "rsir":
            seq = _member(z, "seq", path)
            length = _member(z, "length", path)
            if seq.ndim != 3 or seq.dtype != np.uint8:
                raise SpikeFileError(f"'seq' has shape {seq.shape} ({seq.dtype}); expected uint8 (ceil(T/8), H, W)",
                                     path=path, field="seq")
            if length.size != 1 or not np.issubdtype(length.dtype, np.integer) or int(length) < 0:
                raise SpikeFileError(f"'length' must be one non-negative integer; got {length!r}", path=path,
                                     field="length")
            T = int(length)
            if seq.shape[0] != (T + 7) // 8:
                raise SpikeFileError(f"'length' = {T} needs {(T + 7) // 8} packed planes in 'seq' but it has "
                                     f"{seq.shape[0]}; the file is inconsistent", path=path, field="seq")
            # interval i is bit (i % 8) of plane i // 8 (LSB first), as in RSIR's load_spike_numpy
            bits = np.unpackbits(seq[:, None], axis=1, bitorder="little")  # (P, 8, H, W)
            s = bits.reshape(-1, *seq.shape[1:])[:T].astype(bool)
            meta = {}
        else:
            raise UnknownMethodError("spike-file layout", layout, LAYOUTS)
    meta = dict(meta)
    meta.update({"height": s.shape[1], "width": s.shape[2], "n_intervals": s.shape[0]})
    return s, meta


def read_spikes_with_meta(path, *, layout: str | None = None, height: int | None = None, width: int | None = None,
                          drop_columns: int = 0):
    """Like :func:`read_spikes`, returning ``(spikes bool (T, H, W), meta dict)``.

    ``meta`` holds the container's / HDF5 file's metadata when it has any, and
    always ``height``, ``width``, ``n_intervals``, ``layout`` and ``source``.
    """
    path = Path(path)
    if layout is None:
        layout = detect_layout(path, height=height, width=width)
    elif layout not in LAYOUTS:
        raise UnknownMethodError("spike-file layout", layout, LAYOUTS)
    if not path.is_file():
        raise SpikeFileError("file does not exist", path=path)
    s, meta = _read_layout(path, layout, height, width, int(drop_columns or 0))
    meta.setdefault("source", str(path))
    meta["layout"] = layout
    return s, meta


def read_spikes(path, *, layout: str | None = None, height: int | None = None, width: int | None = None,
                drop_columns: int = 0) -> np.ndarray:
    """Read a spike file of any supported layout as bool (T, H, W) in image orientation (row 0 = top).

    Parameters
    ----------
    path : path-like
        ``.dat``, ``.npz`` or ``.h5``/``.hdf5``.
    layout : str, optional
        One of :func:`spike_layouts` (``container``, ``dat``, ``vidar-raw``,
        ``spikezoo``, ``spikingsim``, ``rsir``, ``h5``). Detected from the
        suffix, the archive's keys and (for .dat) the file size when omitted;
        an ambiguous file is a :class:`SpikeFileError` asking for ``layout=``.
    height, width : int, optional
        Frame size of headerless ``.dat`` files (any H x W with H*W a multiple
        of 8; default 250 x 400, or 250 x 416 for ``vidar-raw``). Layouts that
        store their shape ignore them.
    drop_columns : int
        ``.dat`` only: columns to drop on the right after reading (raw
        416-wide captures: 16; ``vidar-raw`` does it by itself).

    Every corrupt, truncated or inconsistent file raises :class:`SpikeFileError`
    naming the file and what is wrong. Use :func:`read_spikes_with_meta` for
    the metadata.
    """
    return read_spikes_with_meta(path, layout=layout, height=height, width=width, drop_columns=drop_columns)[0]


def write_h5(path, spikes, *, encoding: str = "packbits-little", meta: dict | None = None) -> Path:
    """Write bool spikes (T, H, W) [image orientation] to HDF5, atomically.

    Dataset ``spikes``: ``encoding="packbits-little"`` stores uint8
    (T, ceil(H*W/8)) in the :func:`pack_frames` layout (1 bit per
    pixel-interval); ``"uint8"`` stores uint8 (T, H, W) of 0/1 (8x larger, but
    readable by any HDF5 tool without unpacking). Attributes: ``format``,
    ``version``, ``encoding``, ``height``, ``width``, ``n_intervals``,
    ``interval_s``, ``orientation`` and ``meta_json`` (all metadata as JSON).
    Compressed with gzip.
    """
    import h5py
    s = np.asarray(spikes, bool)
    if s.ndim != 3:
        raise SpikeFileError(f"spikes must be (T, H, W); got {s.shape}")
    if encoding not in ("packbits-little", "uint8"):
        raise UnknownMethodError("HDF5 spike encoding", encoding, ("packbits-little", "uint8"))
    T, H, W = s.shape
    meta = dict(meta or {})
    meta.update({"height": H, "width": W, "n_intervals": T})
    data = pack_frames(s) if encoding == "packbits-little" else s.astype(np.uint8)
    path = Path(path)
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            d = f.create_dataset("spikes", data=data, compression="gzip", compression_opts=4,
                                 chunks=(max(1, min(T, 256)),) + data.shape[1:] if T else None)
            d.attrs.update({"format": H5_FORMAT, "version": 1, "encoding": encoding, "height": H, "width": W,
                            "n_intervals": T, "interval_s": float(meta.get("interval_s", INTERVAL_S)),
                            "orientation": "image (row 0 = top), pixel p = r*W + c; packbits bitorder little",
                            "meta_json": json.dumps(meta, default=str)})
    return path


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
