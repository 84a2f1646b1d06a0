"""Physical constants, timing constants and the unit conversions of render2spike.

Every conversion between physical quantities used anywhere in the project lives
here, once. Other modules import these functions instead of re-deriving them.

Timing (the exact reading of the ELSSim paper's loose units)
-------------------------------------------------------------
* ``CLOCK_HZ`` = 10 MHz: the sensor's operating clock (paper, Refractory Period).
* ``TIME_UNIT_S`` = dt = 2 / CLOCK_HZ = 0.2 us: the smallest time unit.
* ``INTERVAL_S`` = T_r = 50 us: one read-out interval (20 kHz spike frames).
  One interval therefore holds ``T_r / dt = 250`` time units.

Quantities
----------
* ``rate_e``: expected photoelectrons per interval per pixel [e-/interval].
* ``phi``: QE-weighted photon irradiance at the focal plane [e-/(s m^2)]
  (photons that *would* become photoelectrons in a 100 % fill-factor pixel).
* ``lux``: illuminance [lm/m^2].
* threshold: electrons [e-].
"""

from __future__ import annotations

import numpy as np

# --- exact SI constants (2019 SI) -------------------------------------------
PLANCK_J_S = 6.62607015e-34  #: Planck constant h [J s]
SPEED_OF_LIGHT_M_S = 299_792_458.0  #: speed of light c [m/s]
BOLTZMANN_J_K = 1.380649e-23  #: Boltzmann constant k_B [J/K]
LUMINOUS_EFFICACY_LM_W = 683.002  #: K_m, peak luminous efficacy at 555 nm [lm/W]

# --- spike camera timing ----------------------------------------------------
CLOCK_HZ = 10.0e6  #: sensor clock CLK [Hz]
TIME_UNIT_S = 2.0 / CLOCK_HZ  #: dt = 2 / CLK [s] (0.2 us)
INTERVAL_S = 50.0e-6  #: T_r, one spike read-out interval [s] (20 kHz)
#: Largest photoelectron rate accepted as input [e- per interval]: 2e13 e-/s, about 60,000 times the rate at
#: which a vidar-default pixel (threshold 16,000 e-) fires in every interval, and over 1,000 times a white
#: target in full daylight (1e5 lux at f/2, ~7e5 e-/interval with docs/sensor.md's photometry). The read-out
#: saturates at one spike per interval long before; larger rates only make the event-driven ``isi`` model walk
#: ever more firings per interval (about rate / threshold of them), so they are refused.
MAX_RATE_E = 1.0e9


def time_units_per_interval(interval_s: float = INTERVAL_S, clock_hz: float = CLOCK_HZ) -> float:
    """Number of clock time units dt = 2/CLK in one interval T_r (250 by default)."""
    return float(interval_s) / (2.0 / float(clock_hz))


def photon_energy_j(wavelength_nm):
    """Energy of one photon [J] at ``wavelength_nm`` [nm]: E = h c / lambda."""
    return PLANCK_J_S * SPEED_OF_LIGHT_M_S / (np.asarray(wavelength_nm, dtype=np.float64) * 1e-9)


def photons_per_joule(wavelength_nm):
    """Photons per joule [1/J] at ``wavelength_nm`` [nm]: lambda / (h c)."""
    return 1.0 / photon_energy_j(wavelength_nm)


def photoelectron_scale(pixel_pitch_m: float, fill_factor: float, interval_s: float = INTERVAL_S) -> float:
    """The factor [m^2 s / interval] that turns Phi [e-/(s m^2)] into rate_e [e-/interval]:
    ``pixel_pitch_m ** 2 * fill_factor * interval_s`` (float64).

    :func:`photoelectron_rate` multiplies by it (each product in float64, rounded once to
    float32); streaming readers that fuse the conversion into their read
    (:meth:`sensor.io.frames.FrameSequence.read_scaled`) take it from here, so the factor is
    defined once.
    """
    return float(pixel_pitch_m) ** 2 * float(fill_factor) * float(interval_s)


def photoelectron_rate(phi, pixel_pitch_m: float, fill_factor: float, interval_s: float = INTERVAL_S, *, out=None):
    """Convert focal-plane QE-weighted photon irradiance to photoelectrons per interval.

    Parameters
    ----------
    phi : array_like
        QE-weighted photon irradiance at the focal plane [e-/(s m^2)], any shape.
    pixel_pitch_m : float
        Pixel pitch [m]; the pixel area is ``pixel_pitch_m ** 2``.
    fill_factor : float
        Fraction of the pixel area that is photosensitive, in (0, 1].
    interval_s : float
        Interval length T_r [s].

    out : numpy.ndarray (float32), optional
        Where to write the result (may be ``phi`` itself); a new array by default.

    Returns
    -------
    numpy.ndarray (float32), same shape as ``phi``
        ``rate_e`` = expected photoelectrons per interval per pixel [e-/interval]
        = phi * pitch^2 * fill_factor * T_r.
    """
    scale = photoelectron_scale(pixel_pitch_m, fill_factor, interval_s)
    phi = np.asarray(phi)
    if out is None:
        out = np.empty(phi.shape, np.float32)
    # each product in float64, rounded once to float32: one buffered pass, no float64 temporaries
    # (``out`` may be ``phi`` itself when that is float32: converted in place)
    np.multiply(phi, scale, out=out, dtype=np.float64, casting="same_kind")
    return out if out.ndim else out[()]


def rate_e_to_phi(rate_e, pixel_pitch_m: float, fill_factor: float, interval_s: float = INTERVAL_S):
    """Inverse of :func:`photoelectron_rate`: e-/interval -> e-/(s m^2)."""
    scale = photoelectron_scale(pixel_pitch_m, fill_factor, interval_s)
    return np.asarray(rate_e, dtype=np.float64) / scale


def hz_to_per_interval(rate_hz, interval_s: float = INTERVAL_S):
    """Event rate [Hz] -> expected events per interval (e.g. a dark rate -> mu_DC)."""
    return np.asarray(rate_hz, dtype=np.float64) * float(interval_s)


def per_interval_to_hz(per_interval, interval_s: float = INTERVAL_S):
    """Expected events per interval -> event rate [Hz]."""
    return np.asarray(per_interval, dtype=np.float64) / float(interval_s)


def mm_to_m(length_mm):
    """Millimetres -> metres (focal lengths are given in mm in scene files)."""
    return np.asarray(length_mm, dtype=np.float64) * 1e-3


def seconds_to_intervals(t_s, interval_s: float = INTERVAL_S):
    """Time [s] -> time in units of intervals (float)."""
    return np.asarray(t_s, dtype=np.float64) / float(interval_s)


def intervals_to_seconds(n, interval_s: float = INTERVAL_S):
    """Time in intervals -> seconds."""
    return np.asarray(n, dtype=np.float64) * float(interval_s)


def image_plane_illuminance_lux(scene_luminance_cd_m2, f_number: float, transmission: float = 1.0,
                                cos4_theta=1.0):
    """Camera equation: focal-plane illuminance [lux] from scene luminance [cd/m^2].

    E_img = pi * L * T * cos^4(theta) / (4 N^2). The same factor
    ``camera_equation_factor`` converts radiance to irradiance for any radiometric
    or photometric quantity; this is the one place it is defined.
    """
    return np.asarray(scene_luminance_cd_m2, dtype=np.float64) * camera_equation_factor(
        f_number, transmission, cos4_theta)


def camera_equation_factor(f_number: float, transmission: float = 1.0, cos4_theta=1.0):
    """pi * T * cos^4(theta) / (4 N^2): focal-plane irradiance per unit scene radiance [sr]."""
    return np.pi * float(transmission) * np.asarray(cos4_theta, dtype=np.float64) / (4.0 * float(f_number) ** 2)


def lambertian_radiance(illuminance, reflectance: float):
    """Radiance of a Lambertian surface of ``reflectance`` under ``illuminance``: L = rho E / pi.

    Works for photometric (lux -> cd/m^2) and radiometric (W/m^2 -> W/(m^2 sr)) units alike.
    """
    return float(reflectance) * np.asarray(illuminance, dtype=np.float64) / np.pi
