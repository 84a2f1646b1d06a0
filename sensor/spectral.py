"""Spectral data as typed objects with wavelengths in nanometres.

A :class:`SpectralCurve` is a tabulated function of wavelength [nm], linearly
interpolated and zero outside its domain. The render stage uses the profile's QE
curve to weight photon irradiance; tests use it to compute photometric integrals
independently of the renderer.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError
from .units import LUMINOUS_EFFICACY_LM_W, photons_per_joule


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


def photopic_v(wavelength_nm):
    """CIE 1924 photopic luminous efficiency V(lambda), Gaussian-sum approximation.

    Uses the widely used 3-term fit (error < 1 % of peak over 400-700 nm), good
    enough for the photometric checks of a low-light simulator and free of any
    downloaded table. Peak 1.0 at 555 nm.
    """
    x = np.asarray(wavelength_nm, dtype=np.float64)
    v = 1.019 * np.exp(-285.4 * (x / 1000.0 - 0.559) ** 2)
    return np.clip(v, 0.0, None)


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
    h, c, k = 6.62607015e-34, 299_792_458.0, 1.380649e-23
    b = 1.0 / (lam ** 5 * np.expm1(h * c / (lam * k * temperature_k)))
    return SpectralCurve(wl, b / b.max(), unit="relative", name=f"blackbody {temperature_k:g} K")


def flat_spd(lo_nm: float = 380.0, hi_nm: float = 780.0) -> SpectralCurve:
    """Equal-energy (illuminant E) spectrum over [lo_nm, hi_nm]."""
    return SpectralCurve(np.array([lo_nm, hi_nm]), np.array([1.0, 1.0]), unit="relative", name="equal-energy")
