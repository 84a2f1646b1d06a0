"""Compile the numba spike kernels once, so the first simulation of a process does not pay for it.

``python3 -m sensor.models.precompile`` (run by ``scripts/setup.sh``) simulates a tiny sensor with every
fast model, reset and dark mode, and streams it through the ``.dat`` writer; numba caches each compiled
kernel beside its source (``cache=True``), where every later process finds it.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np


def precompile() -> int:
    """Run every fast kernel once on an 8 x 16 sensor; returns the number of simulations run."""
    import sensor
    from sensor.io.spikefile import write_dat
    rate_e = np.full((64, 8, 16), 40.0, np.float32)
    n = 0
    for reset in ("interval", "crossing"):
        for dark in ("events", "current"):
            kw = {"dark_rate": 0.01} if dark == "events" else {"dark_current_e": 2.0}
            prof = sensor.SensorProfile.synthetic(8, 16, threshold_e=400.0, prnu_sigma=0.05, hot_pixel_fraction=0.1,
                                                  reset=reset, dark=dark, seed=0, **kw)
            for model in ("elssim", "isi", "ideal"):
                spikes = sensor.simulate(rate_e, prof, model, seed=0)
                n += 1
    with tempfile.TemporaryDirectory() as d:
        write_dat(Path(d) / "s.dat", spikes)
    return n


if __name__ == "__main__":  # pragma: no cover
    print(f"precompile: {precompile()} simulations, the spike kernels are compiled and cached")
