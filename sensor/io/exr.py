"""One frame file: a float32 single-part scanline OpenEXR image per timestamp.

Channels ``Phi`` (QE-weighted photon irradiance at the focal plane [e-/(s m^2)]) and ``E`` (focal-plane
illuminance [lux]); header attributes ``time_s`` (float64), ``units`` and any extra attributes (see
:mod:`sensor.io.frames` for the folder that holds the frames).

:func:`write_frame` assembles the file in memory (:func:`_encode_exr`: the bytes the OpenEXR binding would
write) and falls back to the binding for headers the encoder does not express; :func:`read_frame` reads any
EXR through the binding; :func:`read_phi` and the ``_exr_*`` layout helpers slice ``Phi`` straight out of an
uncompressed scanline file's bytes (what the sensor stage reads, see ``FrameSequence.read_scaled``).
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sensor.errors import FrameFileError
from sensor.io.fileio import atomic_path, write_bytes_atomic

CHANNEL_UNITS = {"Phi": "e-/(s m^2)", "E": "lux"}
UNITS_STRING = "Phi: QE-weighted photon irradiance at the focal plane [e-/(s m^2)]; E: focal-plane illuminance [lux]"


def _openexr():
    try:
        import OpenEXR
    except ImportError as exc:  # pragma: no cover - declared dependency
        from sensor.errors import DependencyError
        raise DependencyError("OpenEXR is not installed: run `pip install OpenEXR`") from exc
    return OpenEXR


def write_frame(path, phi, illuminance_lux=None, *, time_s: float, attrs: dict | None = None) -> Path:
    """Write one irradiance frame as a float32 single-part OpenEXR file, atomically.

    Parameters
    ----------
    path : path-like
        Destination ``.exr`` file.
    phi : array (H, W)
        QE-weighted photon irradiance at the focal plane [e-/(s m^2)].
    illuminance_lux : array (H, W), optional
        Focal-plane illuminance [lux]; zeros when omitted.
    time_s : float
        Timestamp of the frame [s].
    attrs : dict, optional
        Extra header attributes. Floats are stored as float64 (``double``), ints as ``int``,
        bools as the strings ``true``/``false``, strings as strings, anything else as a JSON string.

    The file is uncompressed (rendered float32 frames carry Monte Carlo noise in every mantissa, so
    ZIP saved ~2 % of the size for ~3x the write time). It is assembled in memory by
    :func:`_encode_exr` (numpy; the same bytes as the OpenEXR binding writes, header and pixels) and
    written with one ``write`` to a temp name beside ``path``, then renamed
    (:func:`~sensor.io.fileio.write_bytes_atomic`); a header that encoder does not handle goes through
    the OpenEXR binding instead (:func:`~sensor.io.fileio.atomic_path`). Cost per frame: see
    ``benchmarks/results/render.md`` ("Frame write").
    """
    phi = np.ascontiguousarray(phi, dtype=np.float32)
    if phi.ndim != 2:
        raise FrameFileError(f"Phi must be a 2-D (H, W) array, got shape {phi.shape}", path=path, field="Phi")
    E = np.zeros_like(phi) if illuminance_lux is None else np.ascontiguousarray(illuminance_lux, dtype=np.float32)
    if E.shape != phi.shape:
        raise FrameFileError(f"E shape {E.shape} differs from Phi shape {phi.shape}", path=path, field="E")
    header = {"time_s": ("double", float(time_s)), "units": ("string", UNITS_STRING)}
    header.update((key, _attr_kind(value)) for key, value in (attrs or {}).items())
    buf = _encode_exr({"E": E, "Phi": phi}, header)
    if buf is not None:
        return write_bytes_atomic(path, buf)
    path = Path(path)
    with atomic_path(path) as tmp:
        _write_frame_openexr(tmp, phi, E, header)
    return path


def _attr_kind(value) -> tuple[str, object]:
    """(EXR attribute type, Python value) of an extra frame attribute: the one type mapping of both writers."""
    if isinstance(value, bool):
        return "string", str(value).lower()
    if isinstance(value, (int, np.integer)):
        return "int", int(value)
    if isinstance(value, (float, np.floating)):
        return "double", float(value)
    if isinstance(value, str):
        return "string", value
    return "string", json.dumps(value, default=str)


def _write_frame_openexr(tmp, phi, E, header: dict) -> None:
    """Write the frame through the OpenEXR binding (the fallback of :func:`write_frame`)."""
    OpenEXR = _openexr()
    h = {"compression": OpenEXR.NO_COMPRESSION, "type": OpenEXR.scanlineimage}
    for key, (kind, value) in header.items():
        h[key] = np.array(value, dtype=np.float64) if kind == "double" else value
    with OpenEXR.File(h, {"Phi": phi, "E": E}) as f:
        f.write(str(tmp))


#: attribute names the OpenEXR library sets or interprets itself: a frame attribute of one of these names
#: goes through the binding (which decides what it means), never through :func:`_encode_exr`
_EXR_RESERVED = frozenset({
    "channels", "compression", "dataWindow", "displayWindow", "lineOrder", "pixelAspectRatio",
    "screenWindowCenter", "screenWindowWidth", "type", "tiles", "chunkCount", "name", "version", "view",
    "multiView", "deepImageState", "maxSamplesPerPixel", "originalDataWindow"})


def _encode_exr(channels: dict, header: dict):
    """The bytes (a uint8 array) of an uncompressed single-part scanline OpenEXR file, or None.

    ``channels``: name -> float32 (H, W) C-contiguous array; ``header``: name -> (``"double"``, float),
    (``"int"``, int) or (``"string"``, str). The layout is what the OpenEXR library (3.x) writes for
    the same header through the Python binding, byte for byte in the header (tested): magic and version
    (2, plus the long-names flag 0x400 when a name exceeds 31 bytes), the attributes sorted by name
    (``channels`` - sorted by name too -, ``compression`` NONE, ``dataWindow`` and ``displayWindow``
    (0, 0, W-1, H-1), ``lineOrder`` INCREASING_Y, ``pixelAspectRatio`` 1, ``screenWindowCenter``
    (0, 0), ``screenWindowWidth`` 1, ``type`` "scanlineimage" and ``header``'s), an empty name, the
    offset table (one uint64 per scanline), then per scanline ``y`` (int32), the pixel bytes (int32)
    and each channel's row in channel order, all little-endian. Returns None (the caller uses the
    binding) for what it does not express the way the binding would: an empty image, a name that is
    empty, not a ``str``, holds a NUL, is longer than 255 bytes or is one the library sets itself
    (:data:`_EXR_RESERVED`), a string with a NUL, an int outside int32.
    """
    names = sorted(channels, key=lambda n: n.encode())
    H, W = channels[names[0]].shape
    if H < 1 or W < 1:
        return None
    chunks = dict(_exr_fixed_chunks(tuple(names), H, W))
    for key, (kind, value) in header.items():
        chunk = _exr_attr_chunk(key, kind, value)
        if chunk is None:
            return None
        chunks[key.encode()] = chunk
    long_names = max(map(len, chunks)) > 31
    head = b"".join([_exr_preamble(long_names), *(chunks[n] for n in sorted(chunks)), b"\0"])
    first = len(head) + 8 * H
    row, offsets, ys = _exr_layout(H, W, len(names), first)
    buf = np.empty(first + row.itemsize * H, np.uint8)
    buf[:len(head)] = np.frombuffer(head, np.uint8)
    buf[len(head):first] = offsets
    rows = buf[first:].view(row)
    rows["y"] = ys
    rows["size"] = row.itemsize - 8
    for i, n in enumerate(names):
        rows[f"c{i}"] = channels[n]
    return buf


# Encoded pieces of an EXR header, built once per (layout, attribute value) and reused: a render writes
# thousands of frames whose headers differ only in their time and a few numbers (about 25 us of a small
# frame's write otherwise). The bytes are exactly those built directly (tested).


@functools.lru_cache(maxsize=2)
def _exr_preamble(long_names: bool) -> bytes:
    """Magic number and version field (2: single-part scanline; 0x400: attribute names over 31 bytes)."""
    return _EXR_MAGIC.to_bytes(4, "little") + (2 | (0x400 if long_names else 0)).to_bytes(4, "little")

_ATTR_CHUNKS: dict = {}  # (name, kind, type, value) -> encoded attribute (or None), ints and short strings
_ATTR_CHUNKS_MAX = 4096


def _chunk(name: bytes, kind: bytes, payload: bytes) -> bytes:
    return name + b"\0" + kind + b"\0" + len(payload).to_bytes(4, "little", signed=True) + payload


@functools.lru_cache(maxsize=64)
def _exr_fixed_chunks(names: tuple, H: int, W: int) -> tuple:
    """The attributes every frame of this layout carries: (name bytes, encoded attribute) pairs."""
    import struct
    return (
        (b"channels", _chunk(b"channels", b"chlist", b"".join(
            n.encode() + b"\0" + struct.pack("<iB3xii", 2, 0, 1, 1) for n in names) + b"\0")),
        (b"compression", _chunk(b"compression", b"compression", b"\0")),
        (b"dataWindow", _chunk(b"dataWindow", b"box2i", struct.pack("<4i", 0, 0, W - 1, H - 1))),
        (b"displayWindow", _chunk(b"displayWindow", b"box2i", struct.pack("<4i", 0, 0, W - 1, H - 1))),
        (b"lineOrder", _chunk(b"lineOrder", b"lineOrder", b"\0")),
        (b"pixelAspectRatio", _chunk(b"pixelAspectRatio", b"float", struct.pack("<f", 1.0))),
        (b"screenWindowCenter", _chunk(b"screenWindowCenter", b"v2f", struct.pack("<2f", 0.0, 0.0))),
        (b"screenWindowWidth", _chunk(b"screenWindowWidth", b"float", struct.pack("<f", 1.0))),
        (b"type", _chunk(b"type", b"string", b"scanlineimage")),
    )


def _exr_attr_chunk(key, kind: str, value):
    """One header attribute encoded, or None for what :func:`_encode_exr` leaves to the binding."""
    import struct
    if kind == "double":  # new values every frame (time): packed each time, never cached
        if not isinstance(key, str) or key in _EXR_RESERVED:
            return None
        name = key.encode()
        if not name or b"\0" in name or len(name) > 255:
            return None
        return _chunk(name, b"double", struct.pack("<d", value))
    try:
        # the value's type is part of the key (1.0 == 1 and -0.0 == 0 must not share an int's bytes); long
        # strings are not kept (the cache would hold them and their bytes; a render's varying strings are short)
        cache_key = (key, kind, type(value), value) if not (isinstance(value, str) and len(value) > 256) else None
        hit = _ATTR_CHUNKS.get(cache_key, _MISSING) if cache_key is not None else _MISSING
    except TypeError:  # an unhashable value: encoded without the cache
        cache_key, hit = None, _MISSING
    if hit is not _MISSING:
        return hit
    chunk = None
    if isinstance(key, str) and key not in _EXR_RESERVED:
        name = key.encode()
        if name and b"\0" not in name and len(name) <= 255:
            if kind == "int":
                if -2 ** 31 <= value < 2 ** 31:
                    chunk = _chunk(name, b"int", struct.pack("<i", value))
            else:
                payload = value.encode()
                if b"\0" not in payload:
                    chunk = _chunk(name, kind.encode(), payload)
    if cache_key is not None:
        if len(_ATTR_CHUNKS) >= _ATTR_CHUNKS_MAX:
            _ATTR_CHUNKS.clear()
        _ATTR_CHUNKS[cache_key] = chunk
    return chunk


_MISSING = object()


@functools.lru_cache(maxsize=64)
def _exr_layout(H: int, W: int, n_channels: int, first: int):
    """(row dtype, offset table as uint8, row numbers) of an uncompressed scanline file whose pixels start at
    byte ``first`` (read-only arrays, shared between calls)."""
    row = np.dtype([("y", "<i4"), ("size", "<i4")] + [(f"c{i}", "<f4", (W,)) for i in range(n_channels)])
    offsets = (first + row.itemsize * np.arange(H, dtype=np.uint64)).astype("<u8").view(np.uint8)
    ys = np.arange(H, dtype=np.int32)
    offsets.flags.writeable = False
    ys.flags.writeable = False
    return row, offsets, ys


def _header_value(v):
    if isinstance(v, np.ndarray) and v.size == 1:
        return float(v.reshape(-1)[0]) if v.dtype.kind == "f" else v.reshape(-1)[0].item()
    return v


@dataclass
class Frame:
    """One frame read back: arrays [units in :data:`CHANNEL_UNITS`] and its header."""

    time_s: float
    phi: np.ndarray
    illuminance_lux: np.ndarray
    header: dict = field(default_factory=dict)


def read_frame(path) -> Frame:
    """Read one frame file written by :func:`write_frame` (or any EXR with ``Phi``/``E``)."""
    OpenEXR = _openexr()
    path = Path(path)
    if not path.is_file():
        raise FrameFileError("frame file does not exist", path=path)
    try:
        with OpenEXR.File(str(path)) as f:
            header = {k: _header_value(v) for k, v in f.header().items()
                      if k not in ("channels", "dataWindow", "displayWindow", "compression", "type", "lineOrder",
                                   "pixelAspectRatio", "screenWindowCenter", "screenWindowWidth")}
            channels = {k: np.asarray(c.pixels) for k, c in f.channels().items()}
    except FrameFileError:
        raise
    except Exception as exc:
        raise FrameFileError(f"not a readable OpenEXR file ({exc})", path=path) from exc
    if "Phi" not in channels:
        raise FrameFileError(f"missing channel 'Phi' (has: {', '.join(sorted(channels))})", path=path, field="Phi")
    if "time_s" not in header:
        raise FrameFileError("header has no 'time_s' attribute (frame timestamp in seconds)", path=path,
                             field="time_s")
    phi = channels["Phi"].astype(np.float32, copy=False)
    E = channels.get("E", np.zeros_like(phi)).astype(np.float32, copy=False)
    return Frame(time_s=float(header["time_s"]), phi=phi, illuminance_lux=E, header=header)


_EXR_MAGIC = 20000630
_EXR_PIXEL_TYPES = {0: "<u4", 1: "<f2", 2: "<f4"}  # UINT, HALF, FLOAT


def _nul(data, pos: int) -> int:
    """Index of the next NUL byte in ``data`` (bytes, bytearray or mmap) from ``pos``; ValueError if none."""
    end = data.find(b"\0", pos)
    if end < 0:
        raise ValueError("unterminated string")
    return end


def _exr_header(data, name: str):
    """The layout of channel ``name`` in an uncompressed single-part scanline EXR held in ``data`` (bytes,
    bytearray or mmap), from its header alone: ``(pos, H, W, y0, line, offset, dtype, time_attr)`` -- the
    offset table's position, the size, the first scanline's ``y``, the bytes of one scanline's channel data,
    the channel's byte offset in it, its dtype and the ``time_s`` attribute's (type, position, size) or None.
    None for any other file (compressed, tiled, deep, multi-part, subsampled, without that channel).

    Layout (OpenEXR file format): magic, version, header attributes (name, type, size, value) up to an
    empty name, an offset table of one uint64 per scanline block, then per scanline ``y`` (int32), the
    data size (int32) and every channel's row in the header's channel order.
    """
    import struct
    try:
        magic, version = struct.unpack_from("<iI", data, 0)
        if magic != _EXR_MAGIC or version & 0xFF != 2 or version & ~0x4FF:
            return None  # not EXR 2.0 single-part scanline (0x400 = long names, allowed)
        pos, attrs = 8, {}
        while True:
            end = _nul(data, pos)
            if end == pos:
                pos += 1
                break
            tend = _nul(data, end + 1)
            (size,) = struct.unpack_from("<i", data, tend + 1)
            if size < 0:  # damaged: a negative size would send the walk back over the header, forever
                return None
            attrs[bytes(data[pos:end])] = (bytes(data[end + 1:tend]), tend + 5, size)
            pos = tend + 5 + size
        if attrs[b"compression"][0] != b"compression" or data[attrs[b"compression"][1]] != 0:
            return None
        _, at, _ = attrs[b"dataWindow"]
        x0, y0, x1, y1 = struct.unpack_from("<4i", data, at)
        H, W = y1 - y0 + 1, x1 - x0 + 1
        _, at, size = attrs[b"channels"]
        stop, line, offset, dtype = at + size - 1, 0, None, None
        while at < stop:  # name\0, pixel type (int32), pLinear + 3 reserved bytes, x and y sampling (int32)
            end = _nul(data, at)
            ptype, _, xs, ys = struct.unpack_from("<iiii", data, end + 1)
            if ptype not in _EXR_PIXEL_TYPES or xs != 1 or ys != 1:
                return None
            if data[at:end] == name.encode():
                offset, dtype = line, np.dtype(_EXR_PIXEL_TYPES[ptype])
            line += W * np.dtype(_EXR_PIXEL_TYPES[ptype]).itemsize
            at = end + 17
        if offset is None or H < 1 or W < 1:
            return None
        return pos, H, W, y0, line, offset, dtype, attrs.get(b"time_s")
    except (KeyError, ValueError, IndexError, struct.error):
        return None


def _exr_views(data, hdr):
    """(offset table uint64 (H,), scanline heads int32 (H, 2) = (y, size), the channel (H, W)) as views of
    ``data`` for the layout ``hdr`` (:func:`_exr_header`), or None when ``data`` is too short. Nothing is
    checked here."""
    pos, H, W, _, line, offset, dtype, _ = hdr
    stride = 8 + line
    first = pos + 8 * H
    if len(data) < first + stride * H:
        return None
    table = np.frombuffer(data, "<u8", H, pos)
    rows = np.frombuffer(data, np.uint8, stride * H, first).reshape(H, stride)
    return table, rows[:, :8].view("<i4"), rows[:, 8 + offset:8 + offset + W * dtype.itemsize].view(dtype)


def _exr_time(data, time_attr):
    """The ``time_s`` attribute's value (double or float) or None."""
    import struct
    if time_attr is None:
        return None
    atype, at, size = time_attr
    if atype == b"double" and size == 8:
        return struct.unpack_from("<d", data, at)[0]
    if atype == b"float" and size == 4:
        return struct.unpack_from("<f", data, at)[0]
    return None


def _exr_channel_fast(data, name: str):
    """(time_s or None, channel ``name`` (H, W)) of an uncompressed single-part scanline EXR held in ``data``
    (bytes, bytearray or mmap): a view of ``data`` (float32, float16 or uint32 as stored); None for any
    other file (compressed, tiled, deep, multi-part, subsampled, without that channel, damaged), which the
    caller then hands to OpenEXR.

    Every block's offset, ``y`` and size is checked before the channel is sliced out of the rows
    (:func:`_exr_header` gives the layout); the other channels are never converted.
    """
    hdr = _exr_header(data, name)
    views = None if hdr is None else _exr_views(data, hdr)
    if views is None:
        return None
    table, heads, arr = views
    pos, H, _, y0, line, _, _, time_attr = hdr
    first = pos + 8 * H
    if np.any(table != first + (8 + line) * np.arange(H, dtype=np.uint64)):
        return None  # blocks not stored back to back in scanline order
    if np.any(heads[:, 0] != y0 + np.arange(H)) or np.any(heads[:, 1] != line):
        return None
    return _exr_time(data, time_attr), arr


def read_phi(path, out=None) -> tuple[float, np.ndarray]:
    """Only the ``Phi`` channel of a frame file: (time_s [s], Phi float32 (H, W) [e-/(s m^2)]).

    What the sensor stage needs of a frame. Uncompressed scanline files (as :func:`write_frame`
    writes them) are sliced straight from the file's bytes, which is ~15x faster than a full
    OpenEXR decode and leaves the ``E`` channel untouched; any other EXR goes through
    :func:`read_frame` (same values, same errors). ``out``: a float32 (H, W) array to fill
    (returned) when the frame has that shape, else a new array is returned.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError:
        data = b""
    fast = _exr_channel_fast(data, "Phi") if data else None
    if fast is None or fast[0] is None:
        fr = read_frame(path)
        time_s, phi = fr.time_s, fr.phi
    else:
        time_s, phi = float(fast[0]), fast[1]
    if out is not None and out.shape == phi.shape:
        np.copyto(out, phi)
        return time_s, out
    return time_s, np.array(phi, dtype=np.float32)
