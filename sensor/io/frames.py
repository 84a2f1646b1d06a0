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

``frame_NNNNNN.exr``: one single-part float32 OpenEXR image per timestamp (:mod:`sensor.io.exr`) with

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

:class:`MemoryFrameSequence` holds the same frames in memory (float32 Phi, a manifest, no file) and is read
like a folder, to the same values.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sensor.errors import FrameFileError
from sensor.io.exr import CHANNEL_UNITS, UNITS_STRING, Frame, read_frame, read_phi, write_frame  # noqa: F401
from sensor.io.exr import _exr_channel_fast, _exr_header, _exr_time, _exr_views
from sensor.io.fileio import provenance, write_json_atomic

MANIFEST_NAME = "frames.json"
FORMAT_NAME = "render2spike-frames"
FORMAT_VERSION = 1


def frame_filename(index: int) -> str:
    """File name of frame ``index`` inside a frames folder."""
    return f"frame_{index:06d}.exr"


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


class _ManifestLayout:
    """What a frame sequence reads off its manifest (the timestamps and the frame shape), and what it builds
    on its own ``read`` / ``read_phi``: iteration and a stack of Phi."""

    manifest: dict

    @property
    def times_s(self) -> np.ndarray:
        """Timestamps [s], float64, strictly increasing."""
        return np.array([f["time_s"] for f in self.manifest["frames"]], dtype=np.float64)

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.manifest["height"]), int(self.manifest["width"])

    def __iter__(self):
        for i in range(len(self)):
            yield self.read(i)

    def phi_stack(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        """Phi of frames ``start:stop`` as float32 (K, H, W) [e-/(s m^2)]."""
        stop = len(self) if stop is None else stop
        return np.stack([self.read_phi(i) for i in range(start, stop)]) if stop > start else \
            np.zeros((0,) + self.shape, np.float32)


@dataclass
class FrameSequence(_ManifestLayout):
    """A frames folder: its manifest and lazy access to the frames, in time order."""

    folder: Path
    manifest: dict
    _buf: bytearray = field(default_factory=bytearray, repr=False, compare=False)  # read_scaled's file buffer
    _hdr: tuple | None = field(default=None, repr=False, compare=False)  # read_scaled's last header layout
    _group: np.ndarray | None = field(default=None, repr=False, compare=False)  # read_scaled_many's files
    _paths: list | None = field(default=None, repr=False, compare=False)  # the frames' paths as str
    _times: np.ndarray | None = field(default=None, repr=False, compare=False)  # times_s, made once

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


class MemoryFrameSequence(_ManifestLayout):
    """Frames held in memory, read like a frames folder (:class:`FrameSequence`'s reading interface).

    ``phi``: one float32 (H, W) Phi array [e-/(s m^2)] per frame (a list, or a (K, H, W) stack), in the
    order of ``manifest["frames"]`` (sorted by ``time_s`` [s], as :func:`manifest_record` makes it); the
    arrays are held as given, not copied (the caller must not change them). ``lux``: the ``E`` channel
    [lux], the same way, or None (frames read back then have ``illuminance_lux`` None). ``where`` names the
    frames in error messages (there is no file).

    The values handed out are those a frames folder written from the same float32 arrays gives back (EXR
    stores float32): :meth:`read_scaled_many` scales and checks each frame exactly as
    :meth:`FrameSequence.read_scaled_many` does (:func:`sensor.io.fastio.scale_checked`), so the same
    frames and seed give the same spikes bit for bit, in memory or through a folder. Memory: 4 H W bytes
    per frame for Phi (400 kB at 400 x 250), as much again for ``lux`` when held.
    """

    def __init__(self, phi, manifest: dict, lux=None, where: str = "frames in memory"):
        self.manifest = manifest
        self.folder = None
        self.where = str(where)
        self._phi = list(phi)
        self._lux = None if lux is None else list(lux)
        if len(self._phi) != len(manifest["frames"]) or (self._lux is not None and len(self._lux) != len(self._phi)):
            raise ValueError(f"{len(self._phi)} Phi arrays for {len(manifest['frames'])} manifest frames")
        for i, a in enumerate(self._phi):
            if a.dtype != np.float32 or a.shape != self.shape:
                raise ValueError(f"frame {i} is {a.dtype} {a.shape}; expected float32 {self.shape}")

    def __len__(self) -> int:
        return len(self._phi)

    def path(self, i: int) -> Path:
        """A name for frame ``i`` in messages: ``where`` and the frame's manifest name (no such file exists)."""
        return Path(self.where) / str(self.manifest["frames"][i].get("file", f"frame {i}"))

    def read(self, i: int) -> Frame:
        """Frame ``i`` (float32 Phi, and E or None), checked for finite, non-negative values."""
        phi = self._phi[i]
        check_light(phi, self.path(i), "Phi")
        lux = None if self._lux is None else self._lux[i]
        if lux is not None:
            check_light(lux, self.path(i), "E")
        return Frame(float(self.manifest["frames"][i]["time_s"]), phi, lux, {})

    def read_phi(self, i: int, out=None) -> np.ndarray:
        """Phi of frame ``i``, float32 (H, W), checked (into ``out`` when given)."""
        check_light(self._phi[i], self.path(i), "Phi")
        if out is None:
            return self._phi[i].copy()
        out[...] = self._phi[i]
        return out

    def read_scaled(self, i: int, scale: float, out) -> np.ndarray:
        """``out[...] = float32(float64(Phi_i) * scale)`` (:func:`sensor.io.fastio.scale_checked`), Phi checked."""
        from sensor.io.fastio import scale_checked
        phi = self._phi[i]
        if out.shape != phi.shape:
            raise ValueError(f"out is {out.shape}; frame {i} is {phi.shape}")
        if scale_checked(phi, scale, out):
            check_light(phi, self.path(i), "Phi")  # names the first bad pixel
        return out

    def read_scaled_many(self, i: int, j: int, scale: float, out) -> np.ndarray:
        """:meth:`read_scaled` of frames ``i .. j-1`` into ``out`` (float32 (j - i, H, W)), returned."""
        if out.shape != (j - i,) + self.shape or out.dtype != np.float32:
            raise ValueError(f"out must be float32 {(j - i,) + self.shape}; got {out.dtype} {out.shape}")
        for q in range(i, j):
            self.read_scaled(q, scale, out[q - i])
        return out


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
