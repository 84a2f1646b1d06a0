"""The frame contract between the render stage and the sensor stage.

A *frames folder* holds the time-varying irradiance of a scene:

``frames.json`` (the manifest)::

    {
      "format": "render2spike-frames", "version": 1,
      "height": H, "width": W,
      "channels": {"Phi": "e-/(s m^2)", "E": "lux"},
      "interpolation": "piecewise-linear",
      "frames": [{"file": "frame_000000.exr", "time_s": 0.0}, ...],   # sorted by time
      "provenance": {...}, ...any extra keys the writer adds
    }

``frame_NNNNNN.exr``: one single-part float32 OpenEXR image per timestamp with

* channel ``Phi``: QE-weighted photon irradiance at the focal plane [e-/(s m^2)],
  i.e. the photoelectrons per second per square metre that a pixel with 100 %
  fill factor would collect; :func:`sensor.units.photoelectron_rate` turns it
  into ``rate_e`` [e-/interval] for a given profile;
* channel ``E``: focal-plane illuminance [lux];
* header attributes ``time_s`` (float64) and ``units`` (a string), plus
  ``made_by`` (JSON string: how the frame was made) and any extra attributes.

Between timestamps the sensor interprets ``Phi`` piecewise-linearly in time
(see :mod:`sensor.rates`). Rows are stored top-down (row 0 is the top of the
image, as seen by the camera).
"""

from __future__ import annotations

import functools
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sensor.errors import FrameFileError
from sensor.io.fileio import atomic_path, provenance, write_bytes_atomic, write_json_atomic

MANIFEST_NAME = "frames.json"
FORMAT_NAME = "render2spike-frames"
FORMAT_VERSION = 1
CHANNEL_UNITS = {"Phi": "e-/(s m^2)", "E": "lux"}
UNITS_STRING = "Phi: QE-weighted photon irradiance at the focal plane [e-/(s m^2)]; E: focal-plane illuminance [lux]"


def _openexr():
    try:
        import OpenEXR
    except ImportError as exc:  # pragma: no cover - declared dependency
        from sensor.errors import DependencyError
        raise DependencyError("OpenEXR is not installed: run `pip install OpenEXR`") from exc
    return OpenEXR


def frame_filename(index: int) -> str:
    """File name of frame ``index`` inside a frames folder."""
    return f"frame_{index:06d}.exr"


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


def _read_files(paths, q: int, n: int, buf) -> int:
    """Read the files ``paths[q:q+n]`` whole into the rows of ``buf`` (uint8 (>= n, size)), in order;
    how many were read, each exactly ``size`` bytes long (the count stops at the first that is not, or
    cannot be read, which the caller then handles the general way)."""
    size = buf.shape[1]
    spare = bytearray(1)  # a file longer than size would put a byte here
    for k in range(n):
        try:
            fd = os.open(paths[q + k], os.O_RDONLY)
        except OSError:
            return k
        try:
            row, got = memoryview(buf[k]), 0
            while got < size:
                r = os.readv(fd, [row[got:], spare])
                if r <= 0:
                    break
                got += r
            if got != size:  # short, or longer than size
                return k
        except OSError:
            return k
        finally:
            os.close(fd)
    return n


def _time_agrees(time_s, manifest_s):
    """Whether a frame header's ``time_s`` [s] is the manifest's (1 ps + 1 ppb; scalars or arrays; NaN never)."""
    return np.abs(time_s - manifest_s) <= 1e-12 + 1e-9 * np.abs(manifest_s)


def _groupable(hdr) -> bool:
    """Whether frames of the layout ``hdr`` (:func:`_exr_header`) can be read in groups: float32 Phi and a
    double ``time_s``, as :func:`write_frame` writes them."""
    tattr = hdr[7]
    return hdr[6] == np.float32 and tattr is not None and tattr[0] == b"double" and tattr[2] == 8


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


@dataclass
class FrameSequence:
    """A frames folder: its manifest and lazy access to the frames, in time order."""

    folder: Path
    manifest: dict
    _buf: bytearray = field(default_factory=bytearray, repr=False, compare=False)  # read_scaled's file buffer
    _hdr: tuple | None = field(default=None, repr=False, compare=False)  # read_scaled's last header layout
    _group: np.ndarray | None = field(default=None, repr=False, compare=False)  # read_scaled_many's files
    _paths: list | None = field(default=None, repr=False, compare=False)  # the frames' paths as str
    _times: np.ndarray | None = field(default=None, repr=False, compare=False)  # times_s, made once

    @property
    def times_s(self) -> np.ndarray:
        """Timestamps [s], float64, strictly increasing."""
        return np.array([f["time_s"] for f in self.manifest["frames"]], dtype=np.float64)

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.manifest["height"]), int(self.manifest["width"])

    def __len__(self) -> int:
        return len(self.manifest["frames"])

    def path(self, i: int) -> Path:
        return self.folder / self.manifest["frames"][i]["file"]

    def read(self, i: int) -> Frame:
        """Frame ``i``, checked against the manifest (size, timestamp) and for finite, non-negative Phi and E."""
        fr = read_frame(self.path(i))
        self._check(i, fr.time_s, fr.phi.shape)
        check_light(fr.phi, self.path(i), "Phi")
        check_light(fr.illuminance_lux, self.path(i), "E")
        return fr

    def read_phi(self, i: int, out=None) -> np.ndarray:
        """Phi of frame ``i`` only, float32 (H, W) [e-/(s m^2)], with :meth:`read`'s checks of Phi
        (size, timestamp, finite and non-negative); the ``E`` channel is not read (:func:`read_phi`).
        ``out``: a float32 (H, W) array to fill and return instead of a new one."""
        path = self.path(i)
        time_s, phi = read_phi(path, out)
        self._check(i, time_s, phi.shape)
        check_light(phi, path, "Phi")
        return phi

    def read_scaled(self, i: int, scale: float, out) -> np.ndarray:
        """Phi of frame ``i`` times ``scale``, written into ``out`` (float32 (H, W)) and returned: what the
        sensor stage reads (``scale`` = :func:`sensor.units.photoelectron_scale` gives rate_e
        [e-/interval], bit for bit as :func:`sensor.units.photoelectron_rate` of :meth:`read_phi`).

        Same checks and errors as :meth:`read_phi` (size, timestamp, Phi finite and >= 0), in one pass:
        an uncompressed scanline file (what :func:`write_frame` writes) is read into a byte buffer that
        this sequence keeps and reuses (no fresh memory per frame); while a frame's header equals the
        previous one's but for ``time_s``, its parsed layout is reused, and one compiled pass checks the
        offset table and every scanline's ``y`` and size and scales and checks Phi straight out of the
        buffer (:func:`sensor.io.fastio.exr_scale_checked`). Other EXR files go through :meth:`read_phi`.
        The buffer makes this method for one thread at a time per sequence.
        """
        from sensor.io.fastio import exr_scale_checked, scale_checked
        path = self.path(i)
        fast, size = None, None
        try:
            with open(path, "rb", buffering=0) as fh:
                size = os.fstat(fh.fileno()).st_size
                if len(self._buf) != size:  # frames of one folder share a size: allocated once
                    self._buf = bytearray(size)
                view, got = memoryview(self._buf), 0
                while got < size:
                    k = fh.readinto(view[got:])
                    if not k:
                        break
                    got += k
        except OSError:
            got = -1
        if got == size:
            buf, hit = self._buf, self._hdr
            # the header of the previous frame, but for the time: same layout; the offset table, every
            # scanline's y and size, and Phi's values are checked while Phi is scaled (one compiled pass)
            if hit is not None and hit[0] == bytes(buf[:hit[2]]) and hit[1] == bytes(buf[hit[3]:hit[4]]):
                views = _exr_views(buf, hit[5])
                if views is not None and views[2].dtype == np.float32:
                    pos, H, _, y0, line, _, _, tattr = hit[5]
                    if out.shape != views[2].shape:
                        raise ValueError(f"out is {out.shape}; frame {i} is {views[2].shape}")
                    bad = exr_scale_checked(views[0], views[1], views[2], pos + 8 * H, 8 + line, y0, line, scale, out)
                    if bad >= 0:
                        self._check(i, float(_exr_time(buf, tattr)), views[2].shape)
                        if bad:
                            check_light(views[2], path, "Phi")  # names the first bad pixel
                        return out
            fast = _exr_channel_fast(buf, "Phi")
            hdr = _exr_header(buf, "Phi") if fast is not None and fast[0] is not None else None
            if hdr is not None and hdr[7] is not None:  # remember the layout, keyed by the header but for the time
                _, tat, tsize = hdr[7]
                self._hdr = (bytes(buf[:tat]), bytes(buf[tat + tsize:hdr[0]]), tat, tat + tsize, hdr[0], hdr)
        if fast is None or fast[0] is None:  # not our layout (or unreadable): the general path, same errors
            phi = self.read_phi(i)
            if out.shape != phi.shape:
                raise ValueError(f"out is {out.shape}; frame {i} is {phi.shape}")
            scale_checked(phi, scale, out)
            return out
        time_s, phi = float(fast[0]), fast[1]
        self._check(i, time_s, phi.shape)
        if out.shape != phi.shape:
            raise ValueError(f"out is {out.shape}; frame {i} is {phi.shape}")
        if phi.dtype != np.float32:
            phi = phi.astype(np.float32)
        if scale_checked(phi, scale, out):
            check_light(phi, path, "Phi")  # names the first bad pixel
        return out

    #: frames read by :meth:`read_scaled_many` before their compiled pass (6.4 MB at 400 x 250: still in cache)
    GROUP_FRAMES = 8

    def read_scaled_many(self, i: int, j: int, scale: float, out) -> np.ndarray:
        """:meth:`read_scaled` of frames ``i .. j-1`` into ``out`` (float32 (j - i, H, W)), returned: the
        same values, checks and errors, with the per-frame work of the interpreter cut to opening and
        reading each file. Frames are read :attr:`GROUP_FRAMES` at a time into a byte buffer that this
        sequence keeps; the group's headers are compared at once with the last frame's header (all but
        ``time_s``), their times with the manifest's, and one compiled pass checks each file's offset
        table and scanlines and scales and checks its Phi (:func:`sensor.io.fastio.exr_group_scale_checked`).
        A frame that does not fit (another size or layout, unreadable, a bad value or time) goes through
        :meth:`read_scaled`, which reads it or raises its error. One thread at a time per sequence.
        """
        n = j - i
        if out.shape != (n,) + self.shape or out.dtype != np.float32:
            raise ValueError(f"out must be float32 {(n,) + self.shape}; got {out.dtype} {out.shape}")
        if self._paths is None:
            self._paths = [str(self.path(q)) for q in range(len(self))]
        q = i
        while q < j:
            hit = self._hdr
            if hit is None or not _groupable(hit[5]):  # no layout known yet (this frame teaches it), or not
                self.read_scaled(q, scale, out[q - i])  # one that write_frame writes: the general way
                q += 1
                continue
            g = min(self.GROUP_FRAMES, j - q)
            size = len(self._buf)  # the last file read_scaled read: its size, not necessarily the layout's file
            pos, H, line = hit[5][0], hit[5][1], hit[5][4]
            if size < pos + 8 * H + (8 + line) * H:  # shorter than the layout: the general way (its own error)
                self.read_scaled(q, scale, out[q - i])
                q += 1
                continue
            if self._group is None or self._group.shape[0] < g or self._group.shape[1] != size:
                self._group = np.empty((max(g, self.GROUP_FRAMES), size), np.uint8)
            got = _read_files(self._paths, q, g, self._group)  # frames q .. q+got-1 read whole, of that size
            ok = self._group_pass(q, got, hit, scale, out[q - i:q - i + got])
            q += ok
            if ok < g:  # frame q does not fit the group: the general way (reads it, or raises its error)
                self.read_scaled(q, scale, out[q - i])
                q += 1
        return out

    def _group_pass(self, q: int, n: int, hit: tuple, scale: float, out) -> int:
        """Check and scale the n frames in ``self._group``'s first rows (frames q ..); how many, from the
        first, passed every check (their Phi scaled into ``out``)."""
        from sensor.io.fastio import exr_group_scale_checked
        if n == 0:
            return 0
        pre, suf, tat, tend, hend, hdr = hit
        buf = self._group[:n]
        same = (buf[:, :tat] == np.frombuffer(pre, np.uint8)).all(axis=1)
        same &= (buf[:, tend:hend] == np.frombuffer(suf, np.uint8)).all(axis=1)
        n = int(np.argmin(same)) if not same.all() else n
        if n == 0:
            return 0
        pos, H, W, y0, line, offset, dtype, tattr = hdr
        buf = buf[:n]
        bad = np.zeros(n, np.int64)
        n = exr_group_scale_checked(buf, pos, H, W, y0, line, offset, scale, out[:n], bad)
        if n == 0:
            return 0
        times = np.ascontiguousarray(buf[:n, tattr[1]:tattr[1] + 8]).view("<f8")[:, 0]
        if self._times is None:
            self._times = self.times_s
        t = self._times[q:q + n]
        fine = (bad[:n] == 0) & _time_agrees(times, t)
        return n if fine.all() else int(np.argmin(fine))

    def _check(self, i: int, time_s: float, shape) -> None:
        if shape != self.shape:
            raise FrameFileError(f"frame is {shape[0]}x{shape[1]} but {MANIFEST_NAME} says "
                                 f"{self.shape[0]}x{self.shape[1]}", path=self.path(i))
        t = float(self.manifest["frames"][i]["time_s"])
        if not _time_agrees(time_s, t):
            raise FrameFileError(f"header time_s = {time_s!r} but {MANIFEST_NAME} frames[{i}] says time_s = "
                                 f"{t!r}", path=self.path(i), field="time_s")

    def __iter__(self):
        for i in range(len(self)):
            yield self.read(i)

    def phi_stack(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        """Phi of frames ``start:stop`` as float32 (K, H, W) [e-/(s m^2)]."""
        stop = len(self) if stop is None else stop
        return np.stack([self.read_phi(i) for i in range(start, stop)]) if stop > start else \
            np.zeros((0,) + self.shape, np.float32)


def check_light(arr, path, name: str) -> None:
    """Raise FrameFileError naming ``path``, channel ``name`` and the first pixel that is non-finite or < 0."""
    from sensor.rates import bad_values
    found = bad_values(arr)
    if found:
        n, idx, v = found
        raise FrameFileError(f"{n} pixel(s) are non-finite or negative, first at (row, col) = {idx}: {v!r} "
                             "(expected finite values >= 0)", path=path, field=name)


def read_frames(folder) -> FrameSequence:
    """Open a frames folder and validate its manifest (no pixel data is read yet).

    Checks: a complete manifest (a render still writing into the folder is refused, naming it),
    times finite and strictly increasing, every file listed once, a positive frame size.
    :meth:`FrameSequence.read` checks each frame against its manifest entry.
    """
    folder = Path(folder)
    mpath = folder / MANIFEST_NAME
    if not folder.is_dir():
        raise FrameFileError("not a directory (expected a frames folder with frames.json)", path=folder)
    if not mpath.is_file():
        raise FrameFileError(f"no {MANIFEST_NAME} manifest in this folder; is it a render2spike frames folder?",
                             path=folder)
    try:
        manifest = json.loads(mpath.read_text())
    except json.JSONDecodeError as exc:
        raise FrameFileError(f"invalid JSON ({exc})", path=mpath) from exc
    for key in ("height", "width", "frames"):
        if key not in manifest:
            raise FrameFileError("missing required key", path=mpath, field=key)
    if manifest.get("format", FORMAT_NAME) != FORMAT_NAME:
        raise FrameFileError(f"format is '{manifest.get('format')}', expected '{FORMAT_NAME}'", path=mpath,
                             field="format")
    if int(manifest.get("version", 1)) > FORMAT_VERSION:
        raise FrameFileError(f"version {manifest['version']} is newer than this reader ({FORMAT_VERSION}); "
                             "upgrade render2spike", path=mpath, field="version")
    frames = manifest["frames"]
    if not frames:
        raise FrameFileError("manifest lists no frames", path=mpath, field="frames")
    from sensor.io.lock import describe, holder
    live = holder(folder)
    if live is not None:
        raise FrameFileError(f"a render is still writing into this folder ({describe(live)}); wait for it to finish",
                             path=folder)
    if manifest.get("complete") is False:
        raise FrameFileError("the manifest says the render is not complete; rerun the render to finish it",
                             path=mpath, field="complete")
    for key in ("height", "width"):
        v = manifest[key]
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise FrameFileError(f"must be a positive integer, got {v!r}", path=mpath, field=key)
    if not isinstance(frames, list):
        raise FrameFileError(f"must be a list of {{file, time_s}} entries, got {type(frames).__name__}", path=mpath,
                             field="frames")
    seen = {}
    for i, fr in enumerate(frames):
        if not isinstance(fr, dict) or "file" not in fr or "time_s" not in fr:
            raise FrameFileError("each entry needs 'file' and 'time_s'", path=mpath, field=f"frames[{i}]")
        if not isinstance(fr["file"], str) or not fr["file"]:
            raise FrameFileError(f"file must be a file name, got {fr['file']!r}", path=mpath,
                                 field=f"frames[{i}].file")
        if fr["file"] in seen:
            raise FrameFileError(f"file '{fr['file']}' is listed twice (also frames[{seen[fr['file']]}]); each frame "
                                 "file may be used once", path=mpath, field=f"frames[{i}].file")
        seen[fr["file"]] = i
        v = fr["time_s"]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
            raise FrameFileError(f"time_s must be a finite number of seconds, got {v!r}", path=mpath,
                                 field=f"frames[{i}].time_s")
    t = np.array([f["time_s"] for f in frames], dtype=np.float64)
    if np.any(np.diff(t) <= 0):
        i = int(np.argmax(np.diff(t) <= 0))
        raise FrameFileError(f"timestamps must increase strictly; frames[{i}] time_s={t[i]} and "
                             f"frames[{i + 1}] time_s={t[i + 1]}", path=mpath, field="frames")
    return FrameSequence(folder=folder, manifest=manifest)


def write_manifest(folder, height: int, width: int, frames: list[dict], **extra) -> Path:
    """Write ``frames.json`` atomically. ``frames``: [{"file": ..., "time_s": ...}, ...] (sorted here)."""
    return write_json_atomic(Path(folder) / MANIFEST_NAME, manifest_record(height, width, frames, **extra))


def manifest_record(height: int, width: int, frames: list[dict], **extra) -> dict:
    """The content :func:`write_manifest` writes (for a writer that prepares it before it may write it)."""
    frames = sorted(frames, key=lambda f: f["time_s"])
    manifest = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "height": int(height),
        "width": int(width),
        "channels": dict(CHANNEL_UNITS),
        "interpolation": "piecewise-linear",
        "frames": frames,
    }
    manifest.update(extra)
    manifest.setdefault("provenance", provenance())
    return manifest


def write_frames(folder, phi, times_s, focal_lux=None, attrs: dict | None = None, manifest: dict | None = None) -> Path:
    """Write a whole (K, H, W) Phi stack as a frames folder (convenience for tests and tools).

    ``focal_lux`` (K, H, W) is the ``E`` channel [lux]; ``manifest`` holds extra manifest keys
    (e.g. ``{"illuminance_lux": 100.0}``, the scene illuminance the frames correspond to).
    """
    folder = Path(folder)
    phi = np.asarray(phi, dtype=np.float32)
    times_s = np.asarray(times_s, dtype=np.float64)
    if phi.ndim != 3 or phi.shape[0] != times_s.shape[0]:
        raise FrameFileError(f"need Phi (K, H, W) with K timestamps; got Phi {phi.shape}, {times_s.shape[0]} times")
    entries = []
    for i, t in enumerate(times_s):
        name = frame_filename(i)
        E = None if focal_lux is None else focal_lux[i]
        write_frame(folder / name, phi[i], E, time_s=float(t), attrs=attrs)
        entries.append({"file": name, "time_s": float(t)})
    return write_manifest(folder, phi.shape[1], phi.shape[2], entries, **(manifest or {}))
