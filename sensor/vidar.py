"""The bundled ``vidar-default`` profile: how it is built and where every value comes from.

Run ``python -m sensor.vidar`` to rebuild ``sensor/data/vidar-default.npz``
(deterministic: seed 20250101). The provenance of each value is stored in the
profile itself (``profile.provenance``) and listed in ``docs/sensor.md``.
"""

from __future__ import annotations

from pathlib import Path

from .profile import DATA_DIR, SensorProfile, generic_cmos_qe
from .units import CLOCK_HZ, INTERVAL_S, TIME_UNIT_S, hz_to_per_interval

VIDAR_SEED = 20250101
DARK_RATE_HZ = 94.0  # mean dark spike rate per pixel [Hz]
DARK_RATE_SIGMA_HZ = 36.0  # pixel-to-pixel spread [Hz]

PROVENANCE = {
    "height/width": "400 x 250 active pixels: published (SpikeCV recVidarReal2019/config.yaml spike_w/spike_h; "
                    "RSIR and SpikeCV loaders read 250 x 416 raw frames and keep 400 columns).",
    "raw_width": "416: constant in public loader code (SpikeCV load_dat.py get_row_index uses columns 400..415 as "
                 "non-image; RSIR utils.py RawToSpike(seq, 250, 416)[:, :, :400]; Spike-Zoo spike_utils.py [:, :, :-16]).",
    "interval_s": "50 us (20 kHz read-out): published (RSIR abstract '20,000 Hz'; SpikeCV device fps 20000); the "
                  "ELSSim paper's T_r.",
    "clock_hz": "10 MHz: the ELSSim paper (Refractory Period paragraph) and SpikingSIM Source/sim.py (CLK = 10 MHz, "
                "250 sub-steps of 2/CLK per read-out).",
    "refractory_s": "0.2 us = one time unit 2/CLK: the ELSSim paper (charging completes within one time unit after a "
                    "spike). SCSim v2s.py comments a 100 ns reset instead; we follow the paper.",
    "prnu_gain": "Gaussian, sigma 0.058 around 1: constant in public simulator code (SCSim v2s.py photo-gain "
                 "AlphaE = 1.0128, Alphas_sigma = 0.0584, normalised by AlphaE).",
    "dark_rate": f"log-normal map, mean {DARK_RATE_HZ:g} Hz, spread {DARK_RATE_SIGMA_HZ:g} Hz (sigma of log 0.37): "
                 "derived by us from SCSim v2s.py constants (dark increment 0.05 * IE = 0.0222 per read-out against a "
                 "threshold CE * (Vrst - Vref + VE) = 4.75 -> ~214 read-outs per dark spike; Is_sigma 0.1731 -> ~36 Hz). "
                 "Converted to mu_DC = rate * T_r expected dark events per interval.",
    "hot_mask/hot_mu/hot_sigma": "estimate: 0.1 % hot pixels, median charge 0.05 threshold per interval (about "
                                 "1 kHz firing), log spread 0.5, sigma 0.02 threshold per interval. No public Vidar "
                                 "hot-pixel statistics were found; calibrate your own camera (render2spike calibrate).",
    "threshold_e": "estimate, 2000 e-. Circuit constants in public code imply 3.0e4 e- (SCSim: 4.35 fF x 1.09 V) or "
                   "1.9e5 e- (SpikingSIM: 15 fF x 2 V), but with any plausible pixel area those would make indoor "
                   "scenes fire far more slowly than public Vidar recordings do. 2000 e- with the pitch/fill below "
                   "makes a reflectance-0.5 surface at 400 lux (f/2, T = 0.9, 5000 K light) fire 0.37 spikes per "
                   "interval and puts the 5-lux signal rate at the dark rate, the regime the ELSSim paper studies. "
                   "Only threshold_e / (pixel_pitch_m^2 * fill_factor) matters for light; calibrate with "
                   "flat fields of known illuminance to pin it for your camera.",
    "pixel_pitch_m": "estimate, 20 um: no published Vidar pitch was found.",
    "fill_factor": "estimate, 0.5 (typical of 3T/4T-style pixels with in-pixel comparators): not published.",
    "qe": "estimate: generic front-side-illuminated CMOS QE shape (peak 0.55 near 550 nm); no Vidar QE is published.",
}


#: the statistics of ``vidar-default`` as :meth:`SensorProfile.synthetic` arguments (also used to draw
#: vidar-like sensors of other sizes, e.g. by the datasets and the benchmark)
VIDAR_SYNTHETIC = dict(
    threshold_e=2000.0,
    dark_rate=float(hz_to_per_interval(DARK_RATE_HZ, INTERVAL_S)), dark_rate_spread=0.37,
    prnu_sigma=0.058,
    hot_pixel_fraction=1e-3, hot_mu=0.05, hot_mu_spread=0.5, hot_sigma=0.02,
    refractory_s=TIME_UNIT_S,
)


def build_vidar_default() -> SensorProfile:
    """Draw the ``vidar-default`` instance (deterministic)."""
    p = SensorProfile.synthetic(
        250, 400, **VIDAR_SYNTHETIC, seed=VIDAR_SEED, name="vidar-default",
        interval_s=INTERVAL_S, clock_hz=CLOCK_HZ, pixel_pitch_m=20e-6, fill_factor=0.5, raw_width=416,
        qe=generic_cmos_qe(), provenance=dict(PROVENANCE),
    )
    return p


def main(out: str | Path | None = None) -> Path:
    path = Path(out) if out else DATA_DIR / "vidar-default.npz"
    return build_vidar_default().save(path)


if __name__ == "__main__":  # pragma: no cover
    print(main())
