"""Row access to one array of an ``.npz`` without loading it whole: a decoder of the zip stream
(stored or deflated members) and a memory map of a stored member."""

from __future__ import annotations

import struct
import zipfile
import zlib
from pathlib import Path

import numpy as np


def _read_header(fh):
    """(shape, fortran_order, dtype) of the .npy header at ``fh``'s position."""
    version = np.lib.format.read_magic(fh)
    read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
    return read(fh)


class NpzMember:
    """One array of an .npz, read in row chunks straight from the zip stream (stored or deflated).

    Only the header is parsed up front; :meth:`rows` decodes the next rows, so memory stays at
    one chunk whatever the array's length (np.load would decompress the whole member).
    """

    def __init__(self, path: Path, name: str):
        self.zf = zipfile.ZipFile(path)
        self.fh = self.zf.open(name + ".npy")
        shape, fortran, dtype = _read_header(self.fh)
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


def stored_member_map(path: Path, name: str):
    """A read-only memory map of array ``name`` of an .npz when it is stored (not deflated, not encrypted),
    like ``np.load(..., mmap_mode='r')`` of an .npy; else None.

    A stored member's bytes lie in the file as they are: the map spares reading them through the zip
    stream, which copies every byte twice. The member's CRC-32 is still checked: ``crc`` =
    (expected CRC, CRC of the member's bytes before the array) is returned with the map, and the reader
    folds in the rows as it hands them out (:meth:`sensor.io.reader.RateSource._crc_rows`).
    Returns (map, crc) or None. Fortran-ordered arrays are left to the stream reader (which refuses
    them, as for a deflated member).
    """
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
        shape, fortran, dtype = _read_header(fh)
        offset = fh.tell()
        if dtype.hasobject or fortran or len(shape) == 0 or \
                offset - start + int(np.prod(shape, dtype=np.int64)) * dtype.itemsize != info.file_size:
            return None
        fh.seek(start)
        crc = zlib.crc32(fh.read(offset - start))
    return np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=tuple(shape)), (info.CRC, crc)
