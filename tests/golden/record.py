"""Run the golden cases and print their hashes as JSON: ``python3 -m tests.golden.record > tests/golden/golden.json`` (the commands' own output goes to stderr).

The cases (tests/test_golden.py runs the same ones):
* the README's main job, ``render2spike run rotating_disk``, on a 16 x 24 window for 10 ms, with ``--dat``, on
  the CPU's LLVM variant with the frozen launch (what ``auto`` takes on a machine without a GPU);
* ``render2spike simulate`` of its frames with each other model and reset, and the reference simulator;
* ``sensor.simulate`` of an in-memory rate with each model and reset.
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

from tests.golden.hashes import _sha, run_hashes, spike_hash

#: the CPU's LLVM variant and the frozen launch, named (not ``auto``): the hashes are of that back end's frames
VARIANT = "llvm_ad_spectral"
RUN_ARGS = ["run", "rotating_disk", "--set", "camera.profile.window=[120,180,16,24]",
            "--duration", "0.01", "--dat", "--quiet", "--variant", VARIANT, "--launch", "frozen", "--keep-frames"]

SIMULATE_CASES = {
    "isi": ["--model", "isi", "--seed", "3"],
    "ideal": ["--model", "ideal"],
    "interval": ["--reset", "interval", "--seed", "1"],
    "reference": ["--reference", "--seed", "2"],
}


def cli(argv) -> None:
    from render2spike.cli import main
    rc = main([str(a) for a in argv])
    if rc not in (0, None):
        raise RuntimeError(f"render2spike {' '.join(map(str, argv))} exited {rc}")


def in_memory_cases() -> dict[str, str]:
    """Hashes of sensor.simulate on a fixed rate array for every model and reset."""
    import numpy as np

    import sensor
    rng = np.random.default_rng(11)
    rate_e = rng.gamma(2.0, 20.0, size=(300, 12, 20)).astype(np.float32)
    full = sensor.SensorProfile.load("vidar-default")
    prof = full.window((full.height - 12) // 2, (full.width - 20) // 2, 12, 20)
    out = {}
    for name, kw in {"elssim": {}, "elssim-interval": {"reset": "interval"}, "isi": {"model": "isi"},
                     "ideal": {"model": "ideal"}}.items():
        kw = dict(kw)
        model = kw.pop("model", "elssim")
        p = prof.replace(**kw) if kw else prof
        s = sensor.simulate(rate_e, p, model=model, seed=5)
        out[name] = _sha(np.packbits(np.asarray(s, bool), axis=-1).tobytes())
    return out


def record(work: Path) -> dict:
    out = work / "job"
    cli(RUN_ARGS + ["--out", out])
    res = {"run": run_hashes(out)}
    for name, args in SIMULATE_CASES.items():
        p = work / f"{name}.npz"
        cli(["simulate", out / "frames", "--out", p, "--quiet", *args])
        res[f"simulate-{name}"] = spike_hash(p)
    res["in-memory"] = in_memory_cases()
    return res


if __name__ == "__main__":
    import contextlib
    import os
    os.environ.setdefault("RENDER2SPIKE_SPIKE_DEVICE", "cpu")  # the numba kernels, even where CUDA works
    with tempfile.TemporaryDirectory() as d, contextlib.redirect_stdout(sys.stderr):
        res = record(Path(d))
    print(json.dumps(res, indent=1, sort_keys=True))
