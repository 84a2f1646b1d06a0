"""Classic spike-camera reconstruction: plain functions on arrays.

Shapes: spikes are bool/uint8 (T, H, W), one row per interval of T_r seconds.
"""

from __future__ import annotations

import numpy as np

from sensor.errors import InputError


def tfp(spikes, window: int | None = None, center: int | None = None) -> np.ndarray:
    """Texture From Playback: mean spike count per interval over a window.

    Parameters
    ----------
    spikes : array (T, H, W)
        Spike stream (bool or 0/1).
    window : int, optional
        Window length in intervals; default all T.
    center : int, optional
        Interval at the window centre; default T // 2. The window is
        ``[center - window//2, center - window//2 + window)``, clipped to the stream.

    Returns
    -------
    numpy.ndarray float32 (H, W)
        Spikes per interval in [0, 1] (the firing probability estimate).
    """
    s = np.asarray(spikes)
    if s.ndim != 3:
        raise InputError(f"spikes must be (T, H, W); got shape {s.shape}", field="spikes")
    T = s.shape[0]
    if T == 0:
        raise InputError("empty spike stream (T = 0)", field="spikes")
    window = T if window is None else int(window)
    if window < 1:
        raise InputError(f"window must be >= 1 interval, got {window}", field="window")
    center = T // 2 if center is None else int(center)
    start = max(0, min(center - window // 2, T - window))
    stop = min(T, start + window)
    return s[start:stop].sum(axis=0, dtype=np.float32) / np.float32(stop - start)
