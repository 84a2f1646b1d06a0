"""SpikeCV / Spike-Zoo ``.dat`` files: reading, writing and counting frames.

No header. Frame after frame, each ``H * W / 8`` bytes, in the ``.dat`` bit layout of
:mod:`sensor.io.bits` (LSB first, rows stored bottom-up). Raw Vidar captures are 416
columns wide; ``drop_columns=16`` drops the 16 extra columns on the right after reading.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sensor.errors import SpikeFileError
from sensor.io.bits import pack_dat_frames, unpack_dat_frames
from sensor.io.fileio import write_bytes_atomic


def write_dat(path, spikes) -> Path:
    """Write bool spikes (T, H, W) [image orientation] to a SpikeCV-compatible .dat, atomically."""
    frames = pack_dat_frames(spikes)
    path = Path(path)
    # os.write (not ndarray.tofile, whose short write on a full disk carries no errno): a full disk is a
    # DiskFullError naming ``path``, and nothing is left behind
    write_bytes_atomic(path, np.ascontiguousarray(frames).reshape(-1))  # flat: 0 frames are 0 bytes
    return path


def check_frame_dims(height, width, path=None) -> None:
    """Refuse a frame height or width (of a headerless .dat file) that is given but not a positive integer."""
    for name, v in (("height", height), ("width", width)):
        if v is None:
            continue
        try:
            ok = int(v) == v and int(v) > 0
        except (TypeError, ValueError, OverflowError):
            ok = False
        if not ok:
            raise SpikeFileError(f"the frame {name} must be a positive number of pixels; got {v!r}", path=path,
                                 field=f"--{name}")


def dat_frame_count(path, height: int = 250, width: int = 400) -> int:
    """Number of whole frames in a .dat file; error if the size is not a whole number of frames."""
    path = Path(path)
    check_frame_dims(height, width, path)
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
    if not 0 <= drop_columns < width:
        raise SpikeFileError(f"must be 0 or more and fewer than the frame width {width}; got {drop_columns}",
                             path=path, field="--drop-columns")
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
