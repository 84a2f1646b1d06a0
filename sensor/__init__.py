"""render2spike sensor stage: spike-camera noise models, profiles, calibration and spike files.

Units at this boundary: ``rate_e`` is expected photoelectrons per interval per
pixel [e-/interval]; one interval is T_r = 50 us; thresholds are electrons.
This package never imports Mitsuba.
"""

from sensor.errors import (CalibrationError, DependencyError, FrameFileError, InputError, ProfileError,
                     Render2SpikeError, SpikeFileError, UnknownMethodError)
from sensor.io.frames import FrameSequence, read_frame, read_frames, write_frame, write_frames, write_manifest
from sensor.models.registry import MODELS, get_model
from sensor.profile import SensorProfile, bundled_profiles
from sensor.rates import RateSchedule, interval_rates
from sensor.simulator import SpikeSimulator, simulate
from sensor.spectral import SpectralCurve
from sensor.io.spikefile import (read_dat, read_spikes, read_spikes_meta, read_spikes_with_meta, spike_layouts,
                                 write_dat, write_h5, write_spikes)
from sensor.units import INTERVAL_S, CLOCK_HZ, TIME_UNIT_S


def photoelectron_rate(phi, profile: SensorProfile, *, out=None):
    """Phi [e-/(s m^2)] -> rate_e [e-/interval] for ``profile`` (pixel area x fill factor x T_r).

    Thin wrapper of :func:`sensor.units.photoelectron_rate`, the one place the
    conversion is defined (``out``: a float32 array to write into, e.g. ``phi`` itself).
    """
    from sensor.units import photoelectron_rate as _per
    return _per(phi, profile.pixel_pitch_m, profile.fill_factor, profile.interval_s, out=out)


__all__ = [
    "SensorProfile", "SpectralCurve", "SpikeSimulator", "simulate", "photoelectron_rate", "read_dat", "write_dat",
    "read_spikes", "read_spikes_meta", "read_spikes_with_meta", "spike_layouts", "write_h5",
    "write_spikes", "read_frames", "read_frame", "write_frame", "write_frames",
    "write_manifest", "FrameSequence", "RateSchedule", "interval_rates", "MODELS", "get_model", "bundled_profiles",
    "INTERVAL_S", "CLOCK_HZ", "TIME_UNIT_S", "Render2SpikeError", "InputError", "ProfileError", "SpikeFileError",
    "FrameFileError", "CalibrationError", "UnknownMethodError", "DependencyError",
]
