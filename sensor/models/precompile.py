"""Compile the numba spike kernels once, so the first simulation of a process does not pay for it.

``python3 -m sensor.models.precompile`` (run by ``scripts/setup.sh``) simulates a tiny sensor with every
fast model, reset and dark mode, and streams a frames folder, a keyframe ``.npz`` and a per-interval ``.npy``
into ``.dat`` and ``.npz`` files; numba caches each compiled kernel beside its source (``cache=True``), where
every later process finds it.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np


def precompile() -> int:
    """Run every fast kernel and fused IO pass once on an 8 x 16 sensor; returns the number of runs."""
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
        n += _stream_files(Path(d))
    return n


def _stream_files(folder: Path) -> int:
    """The readers' and writers' fused passes: a frames folder, a keyframe .npz and a per-interval .npy, each
    streamed into a ``.dat`` and an ``.npz`` through the one frames-to-spikes path."""
    from sensor.io.frames import write_frames
    from sensor.io.spikefile import SpikeWriter
    from sensor.io.stream import open_stream
    prof = "vidar-default"
    times = np.arange(4) * 1e-3
    phi = np.full((4, 8, 16), 5e15, np.float32)  # e-/(s m^2)
    write_frames(folder / "frames", phi, times, focal_lux=np.full((4, 8, 16), 1.0, np.float32))
    np.savez(folder / "k.npz", rate_e=np.full((4, 8, 16), 40.0, np.float32), t_s=times)
    np.save(folder / "r.npy", np.full((64, 8, 16), 40.0, np.float32))
    n = 0
    for src in (folder / "frames", folder / "k.npz", folder / "r.npy"):
        for out in ("s.dat", "s.npz"):
            stream = open_stream(src, prof, "elssim", 0).start()
            path = folder / f"{src.stem}-{out}"
            with SpikeWriter(path, interval_s=stream.profile.interval_s, model="elssim",
                             profile_id=stream.profile.name, seed=0, expected_intervals=stream.total) as writer:
                stream.write(writer)
            n += 1
    return n


if __name__ == "__main__":  # pragma: no cover
    print(f"precompile: {precompile()} simulations, the spike kernels are compiled and cached")
