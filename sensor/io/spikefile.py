"""Spike files of every layout: detection, reading, the HDF5 writer, and the whole spike-file API.

The layouts below are read here; the bit layouts live in :mod:`sensor.io.bits`, ``.dat`` files in
:mod:`sensor.io.dat`, the container in :mod:`sensor.io.container` and the streaming writer in
:mod:`sensor.io.writer`, all re-exported from this module.

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

import io
import json
from pathlib import Path

import numpy as np

from sensor.errors import SpikeFileError, UnknownMethodError
# the spike-file API, re-exported (F401): bit layouts, .dat, container and streaming writer
from sensor.io.bits import (PackedSpikes, count_bits, pack_dat_frames, pack_frames, packed_to_dat,  # noqa: F401
                            unpack_dat_frames, unpack_frames)  # noqa: F401
from sensor.io.container import (SPIKES_FORMAT, SPIKES_VERSION, STREAM_COMPRESSLEVEL, _container_meta,  # noqa: F401
                                 _member, _npz, read_spikes_meta, write_spikes)  # noqa: F401
from sensor.io.dat import check_frame_dims, dat_frame_count, read_dat, write_dat  # noqa: F401
from sensor.io.fileio import write_bytes_atomic
from sensor.io.writer import SpikeWriter  # noqa: F401
from sensor.units import INTERVAL_S


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
    from sensor.io.container import check_meta_numbers
    check_meta_numbers(meta, path)
    return s, meta


def _read_layout(path, layout, height, width, drop_columns):
    """(spikes bool (T, H, W) in image orientation, meta dict) for one named layout."""
    if layout in ("dat", "vidar-raw"):
        if layout == "vidar-raw":
            if width is not None and width != _VIDAR_RAW_W and not drop_columns:
                raise SpikeFileError(f"the vidar-raw layout is {_VIDAR_RAW_W} columns wide ({_VIDAR_W} and "
                                     f"{_VIDAR_RAW_W - _VIDAR_W} dropped); got {width}: read it with the dat "
                                     "layout, or give the columns to drop", path=path, field="--width")
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
    check_frame_dims(height, width, path)
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
    # built in memory, then written in one atomic write: the HDF5 library never writes to the disk itself, so a
    # full disk is a DiskFullError naming ``path`` (HDF5 writing a file on a full disk can crash the process)
    image = io.BytesIO()
    with h5py.File(image, "w") as f:
        d = f.create_dataset("spikes", data=data, compression="gzip", compression_opts=4,
                             chunks=(max(1, min(T, 256)),) + data.shape[1:] if T else None)
        d.attrs.update({"format": H5_FORMAT, "version": 1, "encoding": encoding, "height": H, "width": W,
                        "n_intervals": T, "interval_s": float(meta.get("interval_s", INTERVAL_S)),
                        "orientation": "image (row 0 = top), pixel p = r*W + c; packbits bitorder little",
                        "meta_json": json.dumps(meta, default=str)})
    write_bytes_atomic(path, image.getbuffer())
    return path
