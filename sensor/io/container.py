"""The render2spike spike container ``.npz``: writing it and reading its metadata.

``format: render2spike-spikes``, version 1. ``packed``: uint8 (T, ceil(H*W/8)) bit-packed
frames in image orientation (:func:`sensor.io.bits.pack_frames`); ``meta_json``: UTF-8 JSON
with ``height``, ``width``, ``n_intervals``, ``interval_s``, ``model``, ``implementation``,
``profile_id``, ``seed``, ``source`` and ``provenance``.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np

from sensor.errors import SpikeFileError
from sensor.io.bits import pack_frames
from sensor.io.fileio import provenance, write_bytes_atomic


SPIKES_FORMAT = "render2spike-spikes"
SPIKES_VERSION = 1


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
    write_bytes_atomic(path, buf.getbuffer())  # one atomic write (a full disk: DiskFullError naming path)
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
    check_meta_numbers(meta, path)
    return meta


def check_meta_numbers(meta: dict, path=None) -> None:
    """Refuse a spike file's metadata whose ``interval_s`` [s] is given but not a finite number above 0, or whose
    ``n_intervals`` is given but not an integer >= 0 (:class:`SpikeFileError` naming the file and the field)."""
    import math
    v = meta.get("interval_s")
    if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0):
        raise SpikeFileError(f"must be a finite number of seconds above 0; got {v!r}", path=path, field="interval_s")
    n = meta.get("n_intervals")
    if n is not None and (isinstance(n, bool) or not isinstance(n, int) or n < 0):
        raise SpikeFileError(f"must be an integer >= 0; got {n!r}", path=path, field="n_intervals")


def check_zip_start(path, error=SpikeFileError) -> None:
    """Refuse an ``.npz`` that does not begin as a zip archive, before ``np.load`` would take it for a pickle
    (its message then speaks of ``allow_pickle``): ``error`` naming the file."""
    try:
        with open(path, "rb") as fh:
            magic = fh.read(2)
    except OSError as exc:
        raise error(f"cannot be read ({exc.strerror or exc})", path=path) from exc
    if magic != b"PK":
        raise error("is not an .npz archive (not a zip file: empty, damaged at the start, or another format)",
                    path=path)


class _npz:
    """``np.load`` of an .npz whose every failure is a :class:`SpikeFileError` naming the file."""

    def __init__(self, path):
        self.path = Path(path)

    def __enter__(self):
        if not self.path.is_file():
            raise SpikeFileError("file does not exist", path=self.path)
        check_zip_start(self.path)
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
