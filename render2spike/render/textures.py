"""Reflectance textures made in code (or read from scikit-image's bundled data / a local file).

Every texture is a float32 (R, R) array of *linear* reflectances in
[low, high] (defaults 0.05 and 0.85), row 0 at v = 0. Nothing is downloaded.
"""

from __future__ import annotations

import numpy as np

from sensor.errors import DependencyError, InputError

DEFAULT_LOW, DEFAULT_HIGH = 0.05, 0.85


def _scale(img, low, high):
    img = np.asarray(img, np.float64)
    lo, hi = float(img.min()), float(img.max())
    u = (img - lo) / (hi - lo) if hi > lo else np.zeros_like(img)
    return (low + (high - low) * u).astype(np.float32)


def _resize(img, res):
    if img.shape[0] == res and img.shape[1] == res:
        return img
    try:
        from skimage.transform import resize
    except ImportError as exc:  # pragma: no cover
        raise DependencyError("scikit-image is needed to resize textures: pip install scikit-image") from exc
    return resize(img, (res, res), anti_aliasing=True, preserve_range=True)


def make_texture(spec: dict, folder=None) -> np.ndarray:
    """Reflectance texture for a scene ``material.reflectance`` mapping (schema-checked)."""
    kind = spec["texture"]
    res = int(spec.get("resolution", 256))
    low, high = float(spec.get("low", DEFAULT_LOW)), float(spec.get("high", DEFAULT_HIGH))
    if low > high:
        raise InputError(f"texture low ({low}) must be <= high ({high})", field="material.reflectance")
    if kind == "checker":
        n = int(spec.get("squares", 8))
        idx = (np.arange(res) * n // res)
        img = (idx[:, None] + idx[None, :]) % 2
    elif kind == "stripes":
        n = int(spec.get("squares", 8))
        img = np.broadcast_to(((np.arange(res) * n // res) % 2)[None, :], (res, res))
    elif kind == "noise":
        from scipy.ndimage import gaussian_filter
        rng = np.random.Generator(np.random.PCG64(int(spec.get("seed", 0))))
        img = gaussian_filter(rng.standard_normal((res, res)), float(spec.get("smooth_px", 4.0)), mode="wrap")
    elif kind == "skimage":
        try:
            import skimage.data as skd
            from skimage.color import rgb2gray
        except ImportError as exc:
            raise DependencyError("texture 'skimage' needs scikit-image: pip install scikit-image") from exc
        name = spec["name"]
        fn = getattr(skd, name, None)
        if fn is None or not callable(fn):
            raise InputError(f"scikit-image has no data image '{name}' (try camera, brick, grass, gravel, "
                             "coffee, astronaut)", field="material.reflectance.name")
        try:
            img = fn()
        except Exception as exc:  # data that would need a download
            raise InputError(f"scikit-image image '{name}' is not available offline ({exc}); try camera, brick, "
                             "grass, gravel", field="material.reflectance.name") from exc
        img = np.asarray(img, np.float64)
        if img.ndim == 3:
            img = rgb2gray(img[..., :3])
        side = min(img.shape)
        img = _resize(img[:side, :side], res)
    elif kind == "image":
        import imageio.v3 as iio
        from pathlib import Path
        p = Path(spec["file"])
        p = p if p.is_absolute() or folder is None else Path(folder) / p
        try:
            img = np.asarray(iio.imread(p), np.float64)
        except Exception as exc:
            raise InputError(f"cannot read texture image ({exc})", path=p) from exc
        if img.ndim == 3:
            img = img[..., :3].mean(axis=2)
        side = min(img.shape)
        img = _resize(img[:side, :side], res)
    else:  # pragma: no cover - schema prevents it
        raise InputError(f"unknown texture '{kind}'", field="material.reflectance.texture")
    return _scale(img, low, high)
