"""Import RSIR-style calibration maps (``Nd``, ``Nl``, ``D_light``) into a sensor profile.

RSIR (Recurrent Spike-based Image Restoration) calibrates a Vidar from flat captures at 0, 153 and
335 lux: each pixel's mean read-out ISI is ``1 + D`` intervals with ``D(lux) = q / (lux + Nd)``,
``q = D_light (335 + Nd)``. The maps:

* ``Nd``: the dark current as an equivalent illuminance [lux], added to the light before the pixel's gain;
* ``D_light``: ``1 / rate - 1`` on the 335-lux flat [intervals];
* ``Nl``: the relative gain ``q_ref / q`` (RSIR normalises it to one pixel; only ratios matter here).

This module turns them into this project's units (``docs/sensor.md``, "Importing RSIR calibration maps"):
with the sensitivity ``s`` [e-/(interval lux)] of a base profile, a crossing-reset pixel's mean ISI is
``f + k / (lambda + d)`` (``k = theta / g``, ``lambda = s lux``, ``d = s Nd``, ``f`` the blind time after a
firing [intervals]), so ``theta / (g s) = (1 - f + D_light) (335 + Nd)`` per pixel. The maps cannot fix
``s`` (hence theta in electrons), the reset, QE, hot-pixel statistics or, beyond RSIR's assumed ``+1``,
the blind time.

Entry points: :func:`load_rsir_maps` (checked input), :func:`import_rsir` (the numbers, including the
dark current in e-/interval), :func:`rsir_profile` (the profile with today's fields) and
:func:`rsir_maps` (the inverse, for round trips).
"""

from __future__ import annotations

import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sensor.errors import CalibrationError, InputError
from sensor.profile import SensorProfile
from sensor.spectral import blackbody_spd, electrons_per_lux_second_m2
from sensor.units import photoelectron_scale

#: the keys of an RSIR maps file, each a (H, W) float map
RSIR_KEYS = ("Nd", "Nl", "D_light")
#: illuminance of RSIR's bright flat [lux], the level D_light was measured at
REFERENCE_LUX = 335.0
#: colour temperature assumed for the flats' light when converting lux to photoelectrons [K]
DEFAULT_KELVIN = 5000.0
#: where RSIR's "+1" (mean ISI = 1 + D) goes: a blind time of one interval after each firing, which
#: reproduces RSIR's law at every illuminance, or into the threshold at 335 lux, keeping the base
#: profile's blind time (the law then holds at 335 lux only)
PLUS_ONE = ("dead-time", "threshold")
#: largest relative spread allowed in Nl * D_light * (335 + Nd), which RSIR's definition makes constant
NL_TOLERANCE = 1e-3


def load_rsir_maps(path) -> dict:
    """Read and check an RSIR maps file (``.npz`` with ``Nd``, ``Nl``, ``D_light``).

    Returns the three maps as float64 arrays of one (H, W) shape. Raises :class:`InputError` naming the
    file and the key when the file is not a readable ``.npz``, a key is missing, a map is not 2-D, the
    shapes differ, or a value is not finite or out of range (``Nd >= 0``, ``Nl > 0``, ``D_light > 0``).
    """
    path = Path(path)
    if not path.exists():
        raise InputError("no such file", path=path)
    if path.is_dir():
        raise InputError("is a folder; expected an .npz file with keys " + ", ".join(RSIR_KEYS), path=path)
    try:
        z = np.load(path, allow_pickle=False)
        if not isinstance(z, np.lib.npyio.NpzFile):
            raise InputError("holds a single array; expected an .npz archive with keys " + ", ".join(RSIR_KEYS),
                             path=path)
        with z:
            missing = [k for k in RSIR_KEYS if k not in z.files]
            if missing:
                raise InputError(f"missing (has: {', '.join(z.files) or 'nothing'}); expected the RSIR maps "
                                 f"{', '.join(RSIR_KEYS)}", path=path, field=missing[0])
            raw = {k: z[k] for k in RSIR_KEYS}
    except InputError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise InputError(f"not a readable .npz archive ({type(exc).__name__}: {exc})", path=path) from exc
    maps = {}
    shape = None
    for k in RSIR_KEYS:
        a = raw[k]
        if a.ndim != 2 or a.size == 0:
            raise InputError(f"has shape {a.shape}; expected a non-empty 2-D (height, width) map", path=path, field=k)
        if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
            raise InputError(f"has dtype {a.dtype}; expected a real-valued map", path=path, field=k)
        if shape is None:
            shape = a.shape
        elif a.shape != shape:
            raise InputError(f"has shape {a.shape}, but {RSIR_KEYS[0]} has {shape}; the maps must share one shape",
                             path=path, field=k)
        a = a.astype(np.float64)
        bad = ~np.isfinite(a)
        if bad.any():
            r, c = np.argwhere(bad)[0]
            raise InputError(f"{int(bad.sum())} value(s) not finite (first at row {r}, column {c}); "
                             "expected finite numbers", path=path, field=k)
        maps[k] = a
    for k, lo, why in (("Nd", None, "a dark current as lux-equivalent, >= 0"),
                       ("Nl", 0.0, "a relative gain, > 0"), ("D_light", 0.0, "1 / rate - 1 at 335 lux, > 0")):
        a = maps[k]
        bad = (a < 0) if lo is None else (a <= lo)
        if bad.any():
            r, c = np.argwhere(bad)[0]
            raise InputError(f"{int(bad.sum())} value(s) out of range (first at row {r}, column {c}: "
                             f"{a[r, c]:g}); expected {why}", path=path, field=k)
    return maps


def sensitivity_e_per_lux(base: SensorProfile, kelvin: float = DEFAULT_KELVIN) -> float:
    """Photoelectrons per interval per lux of focal-plane illuminance for ``base``'s pixel [e-/(interval lux)].

    ``electrons_per_lux_second_m2`` (black body at ``kelvin``, the profile's QE) times the pixel's
    ``photoelectron_scale`` (pitch^2 x fill factor x T_r): the project's one conversion, in float64.
    """
    if not kelvin > 0:
        raise InputError(f"must be > 0 K, got {kelvin}", field="--kelvin")
    per_lux = electrons_per_lux_second_m2(blackbody_spd(float(kelvin)), base.qe)
    return float(per_lux * photoelectron_scale(base.pixel_pitch_m, base.fill_factor, base.interval_s))


@dataclass
class RsirImport:
    """RSIR maps in this project's units (all maps (H, W) float64).

    threshold_e : float
        theta [e-]: the median over pixels of ``s q_model``.
    prnu_gain : ndarray
        g = theta / (s q_model), median 1 [1].
    q_model : ndarray
        theta / (g s) [lux intervals]: the light-intervals a pixel integrates per firing.
    dark_current_e : ndarray
        s Nd [e-/interval], photoelectron-equivalent: counted with the photoelectrons (with their shot
        noise) and multiplied by the pixel's gain like them; ``g s Nd`` is the same charge after the gain.
    dark_rate : ndarray
        Nd / q_model [events/interval]: the dark current's firing rate as Poisson dark events (``dark = events``).
    refractory_s : ndarray
        Blind time after a firing [s].
    """

    shape: tuple
    sensitivity_e_per_lux: float
    kelvin: float
    plus_one: str
    threshold_e: float
    prnu_gain: np.ndarray
    q_model: np.ndarray
    dark_current_e: np.ndarray
    dark_rate: np.ndarray
    refractory_s: np.ndarray
    nl_spread: float
    source: str = ""
    provenance: dict = field(default_factory=dict)

    def summary(self) -> dict:
        """Scalar statistics for the CLI and the profile's metadata."""
        q = np.percentile
        return {
            "source": self.source,
            "resolution": f"{self.shape[0]} x {self.shape[1]}",
            "sensitivity_e_per_lux": self.sensitivity_e_per_lux,
            "kelvin": self.kelvin,
            "plus_one": self.plus_one,
            "reference_lux": REFERENCE_LUX,
            "illuminance": "focal plane",
            "threshold_e": self.threshold_e,
            "prnu_sd_over_mean": float(self.prnu_gain.std() / self.prnu_gain.mean()),
            "dark_current_e_median": float(np.median(self.dark_current_e)),
            "dark_current_e_p1_p99": [float(q(self.dark_current_e, 1)), float(q(self.dark_current_e, 99))],
            "dark_current_e_max": float(self.dark_current_e.max()),
            "dark_rate_median": float(np.median(self.dark_rate)),
            "nl_relative_spread": self.nl_spread,
        }


def import_rsir(maps: dict, base: SensorProfile, *, plus_one: str = "dead-time", kelvin: float = DEFAULT_KELVIN,
                source: str = "", nl_tolerance: float = NL_TOLERANCE) -> RsirImport:
    """Convert checked RSIR maps (:func:`load_rsir_maps`) into this project's units with ``base``'s photometry.

    Raises :class:`CalibrationError` (field ``Nl``) when Nl is not ``const / (D_light (335 + Nd))`` within
    ``nl_tolerance`` (relative), i.e. not the gain the other two maps imply.
    """
    if plus_one not in PLUS_ONE:
        raise InputError(f"unknown choice '{plus_one}'; valid choices: {', '.join(PLUS_ONE)}", field="--plus-one")
    nd, nl, d_light = (np.asarray(maps[k], np.float64) for k in RSIR_KEYS)
    q_rsir = d_light * (REFERENCE_LUX + nd)  # RSIR's q: lux intervals per firing, before the "+1"
    r = nl * q_rsir  # constant (q_ref) by RSIR's definition of Nl
    spread = float(np.max(np.abs(r / np.median(r) - 1.0)))
    if not spread <= nl_tolerance:
        i = np.unravel_index(np.argmax(np.abs(r / np.median(r) - 1.0)), r.shape)
        raise CalibrationError(f"Nl * D_light * (335 + Nd) varies by {spread:.3g} (relative, at row {i[0]}, column "
                               f"{i[1]}); RSIR's gain Nl = q_ref / (D_light (335 + Nd)) makes it constant (tolerance "
                               f"{nl_tolerance:g}): these maps do not come from one RSIR calibration",
                               path=source or None, field="Nl")
    s = sensitivity_e_per_lux(base, kelvin)
    shape = nd.shape
    if plus_one == "dead-time":
        refr = np.full(shape, base.interval_s)
    else:
        refr = base.refractory_s.astype(np.float64) if base.shape == shape else \
            np.full(shape, float(np.median(base.refractory_s)))  # the base's blind time, per pixel when it fits
    f = _fraction(refr, base.interval_s)
    q_model = (1.0 - f + d_light) * (REFERENCE_LUX + nd)  # mean ISI f + q_model / (lux + Nd) = 1 + D_light at 335 lux
    if base.reset != "crossing":
        raise CalibrationError(f"the import models a crossing-reset pixel (RSIR's law is its mean ISI); the base "
                               f"profile '{base.name}' has reset '{base.reset}'", field="--base")
    bad = ~(q_model > 1e-6 * (REFERENCE_LUX + nd))
    if np.any(bad):
        i = np.unravel_index(int(np.argmax(bad)), bad.shape)
        raise CalibrationError(f"D_light = {d_light[i]:.3g} at row {i[0]}, column {i[1]} leaves no light per firing "
                               f"once the blind time ({f[i]:.3g} interval) is taken off: the pixel would fire at "
                               "the read-out's limit at any light (use --plus-one threshold, or check the maps)",
                               path=source or None, field="D_light")
    theta = float(s * np.median(q_model))
    gain = theta / (s * q_model)
    dark_e = s * nd
    dark_rate = nd / q_model
    prov = _provenance(source, base, s, kelvin, plus_one, spread)
    return RsirImport(shape=shape, sensitivity_e_per_lux=s, kelvin=float(kelvin), plus_one=plus_one,
                      threshold_e=theta, prnu_gain=gain, q_model=q_model, dark_current_e=dark_e,
                      dark_rate=dark_rate, refractory_s=refr, nl_spread=spread, source=str(source), provenance=prov)


def _fraction(refractory_s, interval_s) -> np.ndarray:
    """Blind time as a fraction of the interval, as the profile stores and reads it (float32 seconds)."""
    return np.asarray(refractory_s, np.float32).astype(np.float64) / float(interval_s)


def _provenance(source, base: SensorProfile, s, kelvin, plus_one, spread) -> dict:
    src = f"RSIR calibration maps {source}" if source else "RSIR calibration maps"
    law = "mean ISI 1 + D_light (335 + Nd) / (lux + Nd) [intervals]"
    blind = ("one interval: carries RSIR's '+1', so the crossing-reset pixel's mean ISI f + theta / (g s (lux + Nd)) "
             "is RSIR's law at every illuminance" if plus_one == "dead-time" else
             f"copied from the base profile '{base.name}'; RSIR's '+1' is folded into the threshold at 335 lux")
    return {
        "maps": f"imported from {src} ({law}) by sensor.calibration.rsir",
        "height/width": f"the shape of the maps in {src}",
        "threshold_e": f"median over pixels of s q_model, q_model = (1 - f + D_light) (335 + Nd) lux intervals "
                       f"(f = blind time / T_r), s = {s:.6g} e-/(interval lux) of focal-plane illuminance from the "
                       f"base profile '{base.name}' (pitch, fill factor, QE, T_r; {kelvin:g} K black body); the "
                       "maps fix only theta / s",
        "prnu_gain": f"theta / (s q_model), median 1; equals RSIR's Nl up to its normalisation when the blind time "
                     f"is one interval (Nl consistent with D_light and Nd to {spread:.2g})",
        "dark_current_e": "s Nd [e-/interval]: RSIR's lux-equivalent dark current as a charge counted with the "
                          "photoelectrons, before the gain (dark = current)",
        "refractory_s": blind,
        "hot_mask/hot_mu/hot_sigma": "none: the maps hold no hot-pixel statistics (bright pixels of Nd are dark "
                                     "current)",
        "raw_width": f"copied from the base profile '{base.name}' when its resolution matches, else none",
        "interval_s": f"copied from the base profile '{base.name}' (RSIR's Vidar: 20 kHz)",
        "clock_hz": f"copied from the base profile '{base.name}'",
        "pixel_pitch_m": f"copied from the base profile '{base.name}' (not fixed by the maps)",
        "fill_factor": f"copied from the base profile '{base.name}' (not fixed by the maps)",
        "qe": f"copied from the base profile '{base.name}' (not fixed by the maps)",
        "reset": f"copied from the base profile '{base.name}' (not fixed by the maps)",
    }


def rsir_profile(imp: RsirImport, base: SensorProfile, name: str | None = None) -> SensorProfile:
    """The sensor profile of an import: dark current as charge (``dark = "current"``), RSIR's own model."""
    h, w = imp.shape
    return SensorProfile(
        name=name or "rsir-import", height=h, width=w, threshold_e=imp.threshold_e, dark="current",
        dark_current_e=imp.dark_current_e, dark_rate=np.zeros(imp.shape), hot_mask=np.zeros(imp.shape, bool), hot_mu=np.zeros(imp.shape),
        hot_sigma=np.zeros(imp.shape), prnu_gain=imp.prnu_gain, refractory_s=imp.refractory_s,
        interval_s=base.interval_s, clock_hz=base.clock_hz, pixel_pitch_m=base.pixel_pitch_m,
        fill_factor=base.fill_factor, raw_width=base.raw_width if base.shape == imp.shape else None, qe=base.qe,
        reset=base.reset, provenance=dict(imp.provenance), meta={"rsir_import": imp.summary()})


def rsir_maps(profile: SensorProfile, base: SensorProfile | None = None, *, kelvin: float | None = None) -> dict:
    """The RSIR maps (``Nd``, ``Nl``, ``D_light``, float64) that ``profile`` implies: the inverse of the import.

    ``s`` comes from ``base`` (default: the profile's own photometry, which the import copies from its base)
    and ``kelvin`` (default: the one stored by the import, else 5000 K). ``Nd`` is read from the dark current
    when the profile holds one (``dark == "current"``), else from ``dark_rate`` (``Nd = dark_rate q_model``).
    ``Nl`` is normalised to 1 at pixel (0, 0), as RSIR does.
    """
    info = profile.meta.get("rsir_import", {}) if isinstance(profile.meta, dict) else {}
    kelvin = float(kelvin if kelvin is not None else info.get("kelvin", DEFAULT_KELVIN))
    s = sensitivity_e_per_lux(base if base is not None else profile, kelvin)
    g = profile.prnu_gain.astype(np.float64)
    q_model = profile.threshold_e / (g * s)
    if getattr(profile, "dark", "events") == "current":
        nd = np.asarray(profile.dark_current_e, np.float64) / s
    else:
        nd = profile.dark_rate.astype(np.float64) * q_model
    f = _fraction(profile.refractory_s, profile.interval_s)
    d_light = q_model / (REFERENCE_LUX + nd) - (1.0 - f)
    q_rsir = d_light * (REFERENCE_LUX + nd)
    return {"Nd": nd, "Nl": q_rsir[0, 0] / q_rsir, "D_light": d_light}
