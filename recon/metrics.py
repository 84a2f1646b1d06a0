"""Image quality metrics of the reconstruction stage: PSNR and SSIM on white-normalised linear images.

Reference and reconstruction are both divided by the reference's white level
(its :data:`WHITE_PERCENTILE`-th percentile, :func:`recon.imageio.white_level`)
and clipped to [0, 1]; PSNR (``skimage.metrics.peak_signal_noise_ratio``) and
SSIM (``skimage.metrics.structural_similarity``, 7x7 uniform window, or the
largest odd window that fits) use ``data_range = 1`` on these linear values.
No per-method gain or offset is fitted.
"""

from __future__ import annotations

import numpy as np

from .imageio import white_level

WHITE_PERCENTILE = 99.5
#: PSNR reported for an exact reconstruction [dB] (10 log10(1 / 1e-12)): keeps averages finite
PSNR_CAP_DB = 120.0


def normalise(img, white: float) -> np.ndarray:
    """Divide by the reference white level and clip to [0, 1] (the metric domain)."""
    return np.clip(np.asarray(img, np.float64) / white, 0.0, 1.0)


def psnr_ssim(pred, ref) -> tuple[float, float]:
    """PSNR [dB] and SSIM of ``pred`` against ``ref`` (both linear, same units) after :func:`normalise`."""
    try:
        from skimage.metrics import peak_signal_noise_ratio, structural_similarity
    except ImportError as exc:
        from sensor.errors import DependencyError
        raise DependencyError("PSNR/SSIM need scikit-image (a core dependency of render2spike): "
                              "pip install 'scikit-image>=0.22'") from exc
    w = white_level(ref, WHITE_PERCENTILE)
    p, r = normalise(pred, w), normalise(ref, w)
    # an exact match would give +inf and poison averages: cap at the PSNR of a 1e-6 RMS error (120 dB)
    psnr = PSNR_CAP_DB if np.array_equal(p, r) else min(float(peak_signal_noise_ratio(r, p, data_range=1.0)), PSNR_CAP_DB)
    win = min(7, min(r.shape) - (1 - min(r.shape) % 2))
    ssim = float(structural_similarity(r, p, data_range=1.0, win_size=max(win, 3))) if min(r.shape) >= 3 else float("nan")
    return psnr, ssim
