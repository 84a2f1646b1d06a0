"""Image reading and writing for the reconstruction stage: sRGB decoding, luminance, PNG/EXR/npy outputs.

Conventions
-----------
* Linear images are float32 (H, W), row 0 at the top.
* sRGB decoding uses the IEC 61966-2-1 piecewise curve; luminance uses the
  Rec. 709 / sRGB primaries: ``Y = 0.2126 R + 0.7152 G + 0.0722 B`` on
  *linear* values.
* Display PNGs divide a linear image by a white level, clip to [0, 1] and
  encode with the sRGB curve (8 bit).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from sensor.errors import InputError
from sensor.io.fileio import atomic_path

REC709_LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)


def srgb_to_linear(v) -> np.ndarray:
    """sRGB-encoded values in [0, 1] -> linear values in [0, 1] (IEC 61966-2-1)."""
    v = np.asarray(v, np.float32)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(v) -> np.ndarray:
    """Linear values in [0, 1] -> sRGB-encoded values in [0, 1]."""
    v = np.clip(np.asarray(v, np.float32), 0.0, 1.0)
    return np.where(v <= 0.0031308, v * 12.92, 1.055 * v ** (1 / 2.4) - 0.055).astype(np.float32)


def luminance(rgb_linear) -> np.ndarray:
    """Linear RGB (H, W, 3) -> relative luminance Y (H, W), Rec. 709 weights; (H, W) passes through."""
    a = np.asarray(rgb_linear, np.float32)
    if a.ndim == 2:
        return a
    if a.ndim == 3 and a.shape[2] >= 3:
        return a[..., :3] @ REC709_LUMA
    if a.ndim == 3 and a.shape[2] in (1, 2):
        return a[..., 0]
    raise InputError(f"expected an (H, W) or (H, W, 3) image, got shape {a.shape}")


def read_srgb_luminance(path) -> np.ndarray:
    """An 8-bit sRGB image (JPEG/PNG) -> linear luminance float32 (H, W) in [0, 1]."""
    from PIL import Image
    path = Path(path)
    try:
        with Image.open(path) as im:
            rgb = np.asarray(im.convert("RGB"), np.float32) / 255.0
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read image ({exc})", path=path) from exc
    return luminance(srgb_to_linear(rgb))


def read_exr_luminance(path) -> np.ndarray:
    """A float OpenEXR image -> linear luminance float32 (H, W): channel Y, else R/G/B, else the only channel."""
    import OpenEXR
    path = Path(path)
    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            ch = {k: np.asarray(v.pixels, np.float32) for k, v in f.channels().items()}
    except Exception as exc:
        raise InputError(f"not a readable OpenEXR file ({exc})", path=path) from exc
    if "Y" in ch:
        return ch["Y"]
    if all(c in ch for c in "RGB"):
        return luminance(np.stack([ch["R"], ch["G"], ch["B"]], axis=-1))
    if len(ch) == 1:
        return next(iter(ch.values()))
    raise InputError(f"no Y or R/G/B channels (has {', '.join(sorted(ch))})", path=path, field="channels")


def read_reference(path, transfer: str | None = None) -> np.ndarray:
    """A reference image -> linear luminance float32 (H, W) (arbitrary linear units).

    ``transfer``: ``"srgb"`` or ``"linear"``; default by file type: EXR and
    16-bit / float TIFF or PNG are linear, 8-bit PNG/JPEG/TIFF are sRGB.
    8-bit and 16-bit integer values are divided by 255 / 65535.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("reference image does not exist", path=path)
    if transfer not in (None, "srgb", "linear"):
        raise InputError(f"transfer must be 'srgb' or 'linear', got '{transfer}'", path=path, field="transfer")
    suffix = path.suffix.lower()
    if suffix == ".exr":
        img = read_exr_luminance(path)
        return srgb_to_linear(img) if transfer == "srgb" else img
    if suffix == ".npy":
        return luminance(np.load(path))
    from PIL import Image
    try:
        with Image.open(path) as im:
            if im.mode in ("I;16", "I;16B", "I;16L", "I"):
                arr, default = np.asarray(im, np.float32) / 65535.0, "linear"
            elif im.mode == "F":
                arr, default = np.asarray(im, np.float32), "linear"
            else:
                arr, default = np.asarray(im.convert("RGB"), np.float32) / 255.0, "srgb"
    except (OSError, ValueError) as exc:
        try:  # 16-bit RGB TIFF/PNG that PIL cannot open: imageio
            import imageio.v3 as iio
            arr = np.asarray(iio.imread(path))
        except Exception:
            raise InputError(f"cannot read image ({exc})", path=path) from exc
        if arr.dtype == np.uint16:
            arr, default = arr.astype(np.float32) / 65535.0, "linear"
        elif arr.dtype == np.uint8:
            arr, default = arr.astype(np.float32) / 255.0, "srgb"
        else:
            arr, default = arr.astype(np.float32), "linear"
    tr = transfer or default
    if tr == "srgb":
        arr = srgb_to_linear(arr)
    return luminance(arr).astype(np.float32)


def white_level(img, percentile: float = 99.5) -> float:
    """The white level of a linear image: its ``percentile`` (positive; 1e-12 floor)."""
    w = float(np.percentile(np.asarray(img, np.float64), percentile))
    return max(w, 1e-12)


def to_display(img, white: float) -> np.ndarray:
    """Linear (H, W) -> uint8 sRGB display image: divide by ``white``, clip, encode."""
    return np.round(linear_to_srgb(np.asarray(img, np.float32) / float(white)) * 255.0).astype(np.uint8)


def show_image_row(axes_row, panels, white: float, *, titles: bool = False, ylabel: str | None = None,
                   title_size: float = 7, label_size: float = 7) -> None:
    """Draw one row of a figure grid: ``panels`` [(label, linear (H, W) image)] on matplotlib ``axes_row``.

    Every image is shown with :func:`to_display` at the same ``white`` level, without ticks; ``titles``
    puts the labels above (the first row), ``ylabel`` names the row at the left.
    """
    for c, (lab, img) in enumerate(panels):
        ax = axes_row[c]
        ax.imshow(to_display(img, white), cmap="gray", vmin=0, vmax=255, interpolation="nearest")
        ax.set_xticks([])
        ax.set_yticks([])
        if titles:
            ax.set_title(lab, fontsize=title_size)
        if c == 0 and ylabel is not None:
            ax.set_ylabel(ylabel, fontsize=label_size)


def write_png(path, img_u8) -> Path:
    """Write a uint8 (H, W) or (H, W, 3) array as PNG, atomically."""
    from PIL import Image
    path = Path(path)
    with atomic_path(path) as tmp:
        Image.fromarray(np.asarray(img_u8, np.uint8)).save(tmp, format="PNG")
    return path


def write_exr(path, img, attrs: dict | None = None) -> Path:
    """Write a linear float32 (H, W) image as a single-channel ('Y') OpenEXR file with string attributes."""
    import OpenEXR
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    for k, v in (attrs or {}).items():
        header[k] = v if isinstance(v, str) else json.dumps(v, default=str)
    path = Path(path)
    with atomic_path(path) as tmp:
        with OpenEXR.File(header, {"Y": np.ascontiguousarray(img, np.float32)}) as f:
            f.write(str(tmp))
    return path


def write_npy(path, img) -> Path:
    """Write an array as .npy, atomically."""
    path = Path(path)
    with atomic_path(path) as tmp:
        np.save(tmp, np.asarray(img))
    return path
