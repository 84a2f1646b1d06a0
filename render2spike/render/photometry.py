"""Photometry of the render stage: sensor response functions, the camera equation, the light level.

Render units
------------
Mitsuba renders *raw* radiance-like numbers: light sources carry relative
spectra (peak ~1) times their ``strength``; the film has two channels, each
the radiance weighted by a response function of wavelength (in nm):

* ``Phi`` raw: ``integral L_rel(l) QE(l) (l / LAMBDA_REF_NM) dl``
* ``E`` raw:   ``integral L_rel(l) V(l) dl``

The physical values follow from one global emitter scale ``k`` [W/(raw unit)]
fixed by the light level (:func:`emitter_scale`), the constant
``photons_per_joule(LAMBDA_REF_NM)`` = LAMBDA_REF/(h c) and the camera equation:

* ``Phi [e-/(s m^2)] = k * LAMBDA_REF/(h c) * Phi_raw * G``
* ``E [lux]         = k * 683 lm/W    * E_raw   * G``

with ``G = pi T cos^4(theta) / (4 N^2)`` (:func:`sensor.units.camera_equation_factor`),
applied here in :func:`to_physical` and nowhere else. The response functions
stay of order 1 so float32 films keep full precision at any light level.

The light level
---------------
``illuminance_lux`` is the illuminance [lux] on the reference surface element
(a point with a normal, or the front centre of a named rectangle/disk at t = 0):
all light arriving from the hemisphere in front of it, direct and
interreflected, weighted by 683 V(lambda). It is computed as the sum of

* the direct light of the point and directional lights, analytically
  (cosine law, inverse square, with a shadow ray), and
* everything else (environment, area emitters, all interreflected light),
  measured by Mitsuba's irradiance meter on a 0.1 mm disk at the reference.

All emitters are then scaled by one factor ``k`` (the render is linear in it),
keeping their relative strengths.
"""

from __future__ import annotations

import numpy as np

from sensor.spectral import SpectralCurve, photopic_v
from sensor.units import LUMINOUS_EFFICACY_LM_W, camera_equation_factor, photons_per_joule

LAMBDA_REF_NM = 555.0  #: reference wavelength that keeps the Phi response O(1) [nm]
SRF_GRID_NM = np.arange(350.0, 1001.0, 5.0)  #: wavelength grid of the film responses [nm]
V_GRID_NM = np.arange(360.0, 831.0, 1.0)


def phi_response(qe: SpectralCurve, wl_nm=SRF_GRID_NM) -> tuple[np.ndarray, np.ndarray]:
    """Film response of the ``Phi`` channel: QE(l) * l / LAMBDA_REF (dimensionless, O(1))."""
    wl = np.asarray(wl_nm, np.float64)
    return wl, qe(wl) * wl / LAMBDA_REF_NM


def lux_response(wl_nm=V_GRID_NM) -> tuple[np.ndarray, np.ndarray]:
    """Film response of the ``E`` channel: V(l) (the 683 lm/W is applied in :func:`to_physical`)."""
    wl = np.asarray(wl_nm, np.float64)
    return wl, photopic_v(wl)


def v_integral(spd: SpectralCurve, strength: float = 1.0) -> float:
    """``strength * integral S(l) V(l) dl`` over 360-830 nm: the raw E of a relative SPD."""
    return float(strength) * float(np.trapezoid(spd(V_GRID_NM) * photopic_v(V_GRID_NM), V_GRID_NM))


def cos4_map(height: int, width: int, pixel_pitch_m: float, focal_length_m: float) -> np.ndarray:
    """cos^4 of the angle between the optical axis and each pixel centre's chief ray, float64 (H, W).

    Pixel (i, j) centre lies at ((j + 0.5 - W/2) p, (i + 0.5 - H/2) p) on a
    sensor at distance f behind a pinhole: cos(theta) = f / sqrt(f^2 + x^2 + y^2).
    """
    x = (np.arange(width) + 0.5 - width / 2.0) * pixel_pitch_m
    y = (np.arange(height) + 0.5 - height / 2.0) * pixel_pitch_m
    r2 = x[None, :] ** 2 + y[:, None] ** 2
    cos = focal_length_m / np.sqrt(focal_length_m ** 2 + r2)
    return cos ** 4


def fov_x_deg(width: int, pixel_pitch_m: float, focal_length_m: float) -> float:
    """Horizontal field of view [deg] of a W-pixel sensor of pitch p behind focal length f."""
    return float(np.degrees(2.0 * np.arctan(width * pixel_pitch_m / (2.0 * focal_length_m))))


def emitter_scale(target_lux: float, reference_raw_e: float) -> float:
    """k such that 683 * k * E_raw(reference) = target_lux [lux]."""
    if not reference_raw_e > 0:
        from sensor.errors import InputError
        raise InputError("no light reaches the reference (its raw illuminance is 0): check the light directions, "
                         "the reference normal and occluders", field="reference")
    return float(target_lux) / (LUMINOUS_EFFICACY_LM_W * float(reference_raw_e))


def physical_factors(k: float, f_number: float, transmission: float, cos4) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel factors (Phi, E) turning raw film channels into e-/(s m^2) and lux (the one place)."""
    g = camera_equation_factor(f_number, transmission, cos4)
    return k * float(photons_per_joule(LAMBDA_REF_NM)) * g, k * LUMINOUS_EFFICACY_LM_W * g


def to_physical(raw_phi, raw_e, k: float, f_number: float, transmission: float, cos4):
    """Raw film channels -> (Phi [e-/(s m^2)], E [lux]) at the focal plane, float64 (H, W)."""
    return apply_factors(raw_phi, raw_e, physical_factors(k, f_number, transmission, cos4))


def apply_factors(raw_phi, raw_e, factors) -> tuple[np.ndarray, np.ndarray]:
    """:func:`to_physical` with its factors (from :func:`physical_factors`) made beforehand, e.g. once per renderer."""
    fp, fe = factors
    return np.asarray(raw_phi, np.float64) * fp, np.asarray(raw_e, np.float64) * fe


def direct_raw_e(light: dict, spd: SpectralCurve, point, normal) -> tuple[float, np.ndarray | None, float]:
    """Unoccluded direct raw illuminance of a delta light at ``point`` with unit ``normal``.

    Returns (raw E, unit direction from the point towards the light, distance
    to the light or inf). Point light: I cos / r^2; directional: E_perp cos.
    """
    p = np.asarray(point, np.float64)
    n = np.asarray(normal, np.float64) / np.linalg.norm(normal)
    strength = float(light.get("strength", 1.0))
    if light["type"] == "directional":
        d = np.asarray(light["direction"], np.float64)
        to_light = -d / np.linalg.norm(d)
        cos = max(0.0, float(n @ to_light))
        return v_integral(spd, strength) * cos, to_light, float("inf")
    if light["type"] == "point":
        v = np.asarray(light["position"], np.float64) - p
        r = float(np.linalg.norm(v))
        to_light = v / r
        cos = max(0.0, float(n @ to_light))
        return v_integral(spd, strength) * cos / r ** 2, to_light, r
    return 0.0, None, 0.0


class ShadowedReferenceWarning(UserWarning):
    """The light-level reference point is shadowed from a delta (point/directional) light at t = 0."""


def shadowed_reference_lights(calibration: dict) -> list[str]:
    """Names of the delta lights that would light the reference point but are blocked by an object at t = 0.

    ``calibration`` is the record of :meth:`SceneRenderer.measure_reference` (its ``delta_lights`` list, each
    with ``raw_e_unshadowed``, the light's direct illuminance without occlusion, and ``visible``).
    """
    return [p["light"] for p in calibration.get("delta_lights", [])
            if float(p.get("raw_e_unshadowed", 0.0)) > 0 and not p.get("visible", True)]


def warn_if_reference_shadowed(calibration: dict, scene_path=None) -> list[str]:
    """Warn (:class:`ShadowedReferenceWarning`) when the reference point lies in a delta light's shadow.

    Then ``illuminance_lux`` counts only the remaining light (e.g. the sky), and the lit parts of the scene are
    far brighter than the stated light level. Returns the shadowing lights' names.
    """
    import warnings
    names = shadowed_reference_lights(calibration)
    if names:
        total = float(calibration.get("raw_e_total", 0.0))
        lost = sum(float(p["raw_e_unshadowed"]) for p in calibration["delta_lights"] if p["light"] in names)
        ratio = (total + lost) / total if total > 0 else float("inf")
        warnings.warn(f"{scene_path or 'scene'}: the light-level reference point {calibration.get('point')} lies in "
                      f"the shadow of {', '.join(names)} at t = 0, so illuminance_lux counts only the other light; "
                      f"unshadowed, the same point would receive {ratio:.3g}x as much. Move 'reference' to a lit "
                      "point.", ShadowedReferenceWarning, stacklevel=3)
    return names
