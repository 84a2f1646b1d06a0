"""The benchmark input: photoelectron-rate keyframes of a moving textured scene at a given illuminance.

Light -> rate_e (exact units, the same chain as the render stage):

* scene illuminance E [lux] on a Lambertian texture of reflectance rho (mean 0.5):
  radiance L = rho E / pi (:func:`sensor.units.lambertian_radiance`);
* f/2 lens with transmission T = 0.9, on axis: focal-plane illuminance
  E_f = L * pi T / (4 N^2) = rho E T / (4 N^2) (:func:`sensor.units.camera_equation_factor`);
* 5000 K black-body light and the profile's QE: photoelectrons per second per m^2
  per lux (:func:`sensor.spectral.electrons_per_lux_second_m2`);
* pixel pitch^2 x fill factor x T_r: e- per interval (:func:`sensor.units.photoelectron_rate`).

The scene: a reflectance texture (gratings, a checkerboard and smooth noise, rho in
[0.1, 0.9], mean 0.5) translating diagonally at about 300 px/s, sampled as keyframes
at 1 kHz (one every 20 intervals) with sub-pixel (bilinear) motion.
"""

from __future__ import annotations

import numpy as np

from sensor.spectral import blackbody_spd, electrons_per_lux_second_m2
from sensor.units import camera_equation_factor, lambertian_radiance, photoelectron_rate

F_NUMBER = 2.0
TRANSMISSION = 0.9
MEAN_REFLECTANCE = 0.5
CCT_K = 5000.0
KEYFRAME_HZ = 1000.0
VELOCITY_PX_S = (150.0, 300.0)  # (rows, cols) per second


def rate_e_per_reflectance(lux: float, profile) -> float:
    """e- per interval of a reflectance-1 Lambertian surface under ``lux`` (multiply by rho)."""
    e_focal = lambertian_radiance(lux, 1.0) * camera_equation_factor(F_NUMBER, TRANSMISSION)
    phi = float(e_focal) * electrons_per_lux_second_m2(blackbody_spd(CCT_K), profile.qe)
    return float(photoelectron_rate(phi, profile.pixel_pitch_m, profile.fill_factor, profile.interval_s))


def lux_to_rate_e(lux: float, profile, reflectance: float = MEAN_REFLECTANCE) -> float:
    """Mean photoelectrons per interval for a surface of ``reflectance`` under scene illuminance ``lux``."""
    return reflectance * rate_e_per_reflectance(lux, profile)


class MovingScene:
    """Keyframes (K, H, W) float32 [e-/interval] of a translating texture; ``chunk(i0, n)`` is cheap."""

    def __init__(self, profile, lux: float, seed: int = 0, duration_s: float = 2.0):
        self.h, self.w = profile.shape
        self.scale = rate_e_per_reflectance(lux, profile)
        self.dt = 1.0 / KEYFRAME_HZ
        pad_r = int(np.ceil(VELOCITY_PX_S[0] * duration_s)) + 2
        pad_c = int(np.ceil(VELOCITY_PX_S[1] * duration_s)) + 2
        H, W = self.h + pad_r, self.w + pad_c
        rng = np.random.default_rng(seed)
        y, x = np.mgrid[0:H, 0:W].astype(np.float32)
        tex = 0.5 + 0.2 * np.sin(2 * np.pi * x / 37.0) * np.sin(2 * np.pi * y / 23.0)
        tex += 0.12 * np.where(((x // 48) + (y // 48)) % 2 == 0, 1.0, -1.0)
        noise = rng.normal(0.0, 1.0, (H // 8 + 2, W // 8 + 2)).astype(np.float32)
        noise = np.kron(noise, np.ones((8, 8), np.float32))[:H, :W]
        tex += 0.06 * noise
        tex = np.clip(tex, 0.1, 0.9)
        tex *= MEAN_REFLECTANCE / tex.mean()
        self.texture = (tex * self.scale).astype(np.float32)
        self.n_keyframes = int(round(duration_s * KEYFRAME_HZ)) + 1

    def frame(self, i: int) -> np.ndarray:
        return self.frame_at(i * self.dt)

    def frame_at(self, t: float) -> np.ndarray:
        """The rate image [e-/interval] at time ``t`` [s] (0 <= t <= duration)."""
        oy, ox = VELOCITY_PX_S[0] * t, VELOCITY_PX_S[1] * t
        iy, ix = int(oy), int(ox)
        fy, fx = np.float32(oy - iy), np.float32(ox - ix)
        T = self.texture
        a = T[iy:iy + self.h + 1, ix:ix + self.w + 1]
        top = (1 - fx) * a[:-1, :-1] + fx * a[:-1, 1:]
        bot = (1 - fx) * a[1:, :-1] + fx * a[1:, 1:]
        return (1 - fy) * top + fy * bot

    def chunk(self, i0: int, n: int):
        """Keyframes i0 .. i0+n-1 (clipped to the scene) and their times [s]."""
        i1 = min(i0 + n, self.n_keyframes)
        frames = np.stack([self.frame(i) for i in range(i0, i1)]) if i1 > i0 else np.zeros((0, self.h, self.w),
                                                                                             np.float32)
        return frames.astype(np.float32, copy=False), np.arange(i0, i1) * self.dt
