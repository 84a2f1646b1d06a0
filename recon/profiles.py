"""Sensor profiles of the reconstruction stage: the sensor assumed for data and recordings, and its maps.

:func:`resolve_profile` gives the profile of exactly the data's size (a
bundled name or file, centre-windowed, or the synthetic vidar-like sensor
:data:`DEFAULT_SYNTHETIC`); :func:`uniform_profile` and
:func:`recording_profile` the sensor assumed for a real recording without a
calibrated profile; :func:`sensor_maps` the per-pixel maps the network and the
output head read.
"""

from __future__ import annotations

import numpy as np

from sensor.calibration.vidar import VIDAR_SYNTHETIC
from sensor.profile import SensorProfile

#: the synthetic sensor drawn when no profile is named (values of the bundled vidar-default profile, see
#: docs/sensor.md: threshold 16,000 e-, dark current as charge, median 78.6 e- per 50 us interval (98 Hz of
#: dark firing), log spread 0.46, PRNU sigma 0.056, 0.1 % hot pixels)
DEFAULT_SYNTHETIC = dict(VIDAR_SYNTHETIC, reset="crossing")  # vidar-default's reset (docs/sensor.md)


def sensor_maps(profile: SensorProfile) -> np.ndarray:
    """float32 (4, H, W): expected dark spikes per interval, PRNU gain, hot-pixel indicator, dark-as-charge indicator.

    Channel 0 is the dark floor of each pixel's rate in either dark mode
    (:attr:`sensor.SensorProfile.dark_spike_rate`). The network's map features
    use the first ``n_maps`` channels (2, or 1 for the ``rsir`` preset); the
    hot-pixel indicator (1 where the profile's pixel is hot, else 0) tells the
    output head's classic estimates which pixels to leave out of their
    smoothing, and the last channel (1 where the profile's dark current is a
    charge, ``dark == "current"``, 0 for dark events) how to take the dark
    floor off (:func:`recon.nets.classic_bank`).
    """
    charge = np.full(profile.shape, 1.0 if profile.dark == "current" else 0.0)
    return np.stack([profile.dark_spike_rate, profile.prnu_gain, profile.hot_mask, charge]).astype(np.float32)


def uniform_profile(height: int, width: int) -> SensorProfile:
    """The default sensor where none is known (real recordings without a profile): every pixel alike.

    The vidar-like threshold, refractory time, reset, dark mode and the *mean*
    dark current (or dark rate) of :data:`DEFAULT_SYNTHETIC`, with no PRNU, no
    dark spread and no hot pixels (nothing drawn at random: the pixels' real
    fixed pattern is unknown).
    """
    d = DEFAULT_SYNTHETIC
    dark = d.get("dark", "events")
    level = {"dark_current_e": d["dark_current_e"]} if dark == "current" else {"dark_rate": d["dark_rate"]}
    return SensorProfile.synthetic(height, width, threshold_e=d["threshold_e"], dark=dark, **level,
                                   refractory_s=d["refractory_s"], reset=d["reset"],
                                   name=f"recon-uniform-{height}x{width}")


def resolve_profile(spec: str | SensorProfile | None, height: int, width: int, seed: int = 0) -> SensorProfile:
    """A profile of exactly ``height x width``: a bundled name / path (centre window if larger) or 'synthetic'."""
    if isinstance(spec, SensorProfile):
        prof = spec
    elif spec in (None, "", "synthetic"):
        return SensorProfile.synthetic(height, width, seed=seed, name=f"recon-synthetic-{height}x{width}-s{seed}",
                                       **DEFAULT_SYNTHETIC)
    else:
        prof = SensorProfile.load(spec)
    return prof.centred(height, width)


def recording_profile(spikes, source="the recording", warn: bool = True):
    """The sensor assumed for a recording that comes without a profile (``--profile`` not given).

    :func:`uniform_profile` (vidar-like threshold, refractory
    time and reset, the mean dark rate, no PRNU) with the hot pixels found in
    the recording itself (:func:`sensor.calibration.estimate.scene_hot_pixels`), so
    the dead-time correction and the network's output head leave them out.
    Warns (unless ``warn=False``), naming how many were found: a calibrated profile is better.
    """
    import warnings

    from sensor.calibration.estimate import scene_hot_pixels

    s = np.asarray(spikes)
    hot = scene_hot_pixels(s)
    prof = uniform_profile(s.shape[1], s.shape[2]).replace(hot_mask=hot)
    if warn:
        warnings.warn(f"{source}: no --profile given; assuming a uniform vidar-like sensor, with {int(hot.sum())} "
                      f"hot pixel(s) found as isolated outliers of the recording's spike counts (pass --profile "
                      f"with a calibrated profile, see render2spike calibrate)", stacklevel=2)
    return prof
