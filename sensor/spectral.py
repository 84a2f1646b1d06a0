"""Spectral data as typed objects with wavelengths in nanometres.

A :class:`SpectralCurve` is a tabulated function of wavelength [nm], linearly
interpolated and zero outside its domain. The render stage uses the profile's QE
curve to weight photon irradiance; tests use it to compute photometric integrals
independently of the renderer.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sensor.errors import InputError
from sensor.units import BOLTZMANN_J_K, LUMINOUS_EFFICACY_LM_W, PLANCK_J_S, SPEED_OF_LIGHT_M_S, photons_per_joule


@dataclass(frozen=True)
class SpectralCurve:
    """A tabulated spectral quantity.

    Attributes
    ----------
    wavelength_nm : ndarray (N,)
        Strictly increasing wavelengths [nm].
    values : ndarray (N,)
        The quantity at those wavelengths, in ``unit``.
    unit : str
        Unit of ``values`` (e.g. ``"1"`` for a QE fraction, ``"W/(m^2 nm)"``).
    name : str
        Human-readable name.
    """

    wavelength_nm: np.ndarray
    values: np.ndarray
    unit: str = "1"
    name: str = ""

    def __post_init__(self):
        wl = np.asarray(self.wavelength_nm, dtype=np.float64)
        v = np.asarray(self.values, dtype=np.float64)
        if wl.ndim != 1 or v.shape != wl.shape or wl.size < 2:
            raise InputError(f"spectral curve '{self.name}' needs two 1-D arrays of equal length >= 2; "
                             f"got wavelength {wl.shape}, values {v.shape}")
        if np.any(np.diff(wl) <= 0):
            raise InputError(f"spectral curve '{self.name}': wavelengths must increase strictly")
        object.__setattr__(self, "wavelength_nm", wl)
        object.__setattr__(self, "values", v)

    def __call__(self, wavelength_nm):
        """Linear interpolation at ``wavelength_nm`` [nm]; 0 outside the tabulated range."""
        return np.interp(np.asarray(wavelength_nm, np.float64), self.wavelength_nm, self.values, left=0.0, right=0.0)

    def to_dict(self) -> dict:
        return {"wavelength_nm": self.wavelength_nm.tolist(), "values": self.values.tolist(),
                "unit": self.unit, "name": self.name}

    @classmethod
    def from_dict(cls, d: dict) -> "SpectralCurve":
        return cls(np.asarray(d["wavelength_nm"]), np.asarray(d["values"]), d.get("unit", "1"), d.get("name", ""))


#: CIE 1924 photopic luminous efficiency V(lambda) (= the CIE 1931 y-bar), 380-780 nm in 5 nm steps.
#: Public standard data (CIE 018, ISO 23539 / CIE S 010); V(555 nm) = 1.
_V_1924_NM0, _V_1924_STEP = 380.0, 5.0
_V_1924 = np.array([
    0.000039, 0.000064, 0.00012, 0.000217, 0.000396, 0.00064, 0.00121, 0.00218, 0.004, 0.0073,      # 380-425
    0.0116, 0.01684, 0.023, 0.0298, 0.038, 0.048, 0.06, 0.0739, 0.09098, 0.1126,                   # 430-475
    0.13902, 0.1693, 0.20802, 0.2586, 0.323, 0.4073, 0.503, 0.6082, 0.71, 0.7932,                  # 480-525
    0.862, 0.91485, 0.954, 0.9803, 0.99495, 1.0, 0.995, 0.9786, 0.952, 0.9154,                     # 530-575
    0.87, 0.8163, 0.757, 0.6949, 0.631, 0.5668, 0.503, 0.4412, 0.381, 0.321,                       # 580-625
    0.265, 0.217, 0.175, 0.1382, 0.107, 0.0816, 0.061, 0.04458, 0.032, 0.0232,                     # 630-675
    0.017, 0.01192, 0.00821, 0.005723, 0.004102, 0.002929, 0.002091, 0.001484, 0.001047, 0.00074,  # 680-725
    0.00052, 0.000361, 0.000249, 0.000172, 0.00012, 0.000085, 0.00006, 0.000042, 0.00003, 0.000021,  # 730-775
    0.000015,                                                                                      # 780
])


def photopic_v(wavelength_nm):
    """CIE 1924 photopic luminous efficiency V(lambda) [1], peak 1.0 at 555 nm.

    Linear interpolation of the standard 5 nm table (380-780 nm), 0 outside it.
    """
    wl = _V_1924_NM0 + _V_1924_STEP * np.arange(_V_1924.size)
    return np.interp(np.asarray(wavelength_nm, dtype=np.float64), wl, _V_1924, left=0.0, right=0.0)


def electrons_per_lux_second_m2(spectrum: SpectralCurve, qe: SpectralCurve, wl_nm=None) -> float:
    """Photoelectrons per second per m^2 per lux for a light of spectral shape ``spectrum``.

    = integral(S(l) QE(l) l/(h c) dl) / (683 integral(S(l) V(l) dl)), the factor
    that turns illuminance [lux] into QE-weighted photon irradiance [e-/(s m^2)]
    for a given relative spectral power distribution S (any scale).
    """
    wl = np.arange(360.0, 830.5, 1.0) if wl_nm is None else np.asarray(wl_nm, np.float64)
    s = spectrum(wl)
    num = np.trapezoid(s * qe(wl) * photons_per_joule(wl), wl)
    den = LUMINOUS_EFFICACY_LM_W * np.trapezoid(s * photopic_v(wl), wl)
    if den <= 0:
        raise InputError(f"spectrum '{spectrum.name}' has no visible power; cannot convert lux")
    return float(num / den)


def blackbody_spd(temperature_k: float, wl_nm=None) -> SpectralCurve:
    """Relative spectral power of a black body at ``temperature_k`` [K] (peak-normalised)."""
    wl = np.arange(300.0, 1101.0, 5.0) if wl_nm is None else np.asarray(wl_nm, np.float64)
    lam = wl * 1e-9
    b = 1.0 / (lam ** 5 * np.expm1(PLANCK_J_S * SPEED_OF_LIGHT_M_S / (lam * BOLTZMANN_J_K * temperature_k)))
    return SpectralCurve(wl, b / b.max(), unit="relative", name=f"blackbody {temperature_k:g} K")


def flat_spd(lo_nm: float = 380.0, hi_nm: float = 780.0) -> SpectralCurve:
    """Equal-energy (illuminant E) spectrum over [lo_nm, hi_nm]."""
    return SpectralCurve(np.array([lo_nm, hi_nm]), np.array([1.0, 1.0]), unit="relative", name="equal-energy")
