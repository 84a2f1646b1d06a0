"""Hashes of what the README's main job writes, for the golden test (tests/test_golden.py).

``python3 -m tests.golden.hashes OUT`` prints the hashes of a finished ``render2spike run ... --out OUT``
as JSON. Only content is hashed (pixel arrays, per-frame times and seeds, the spike bits), never the files'
provenance (dates, commands, timings), so the same scene, options and seeds give the same hashes.
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import numpy as np


def _sha(*parts: bytes) -> str:
    h = hashlib.sha256()
    for p in parts:
        h.update(p)
    return h.hexdigest()[:16]


def frame_hashes(frames_dir: Path) -> dict[str, str]:
    """{frame file name: hash of its Phi and E pixels, time_s and seeds}."""
    import OpenEXR
    out = {}
    for p in sorted(frames_dir.glob("frame_*.exr")):
        f = OpenEXR.File(str(p))
        ch = f.channels()
        hdr = f.header()
        out[p.name] = _sha(np.ascontiguousarray(ch["Phi"].pixels, np.float32).tobytes(),
                           np.ascontiguousarray(ch["E"].pixels, np.float32).tobytes(),
                           np.asarray(hdr["time_s"], np.float64).tobytes(),
                           str(hdr["seeds"]).encode())
    return out


def spike_hash(npz: Path) -> dict:
    """Hash and count of the bit-packed spikes in a run's spikes.npz."""
    z = np.load(npz)
    packed = z["packed"]
    meta = json.loads(bytes(z["meta_json"]).decode())
    bits = np.unpackbits(packed, axis=-1)
    return {"spikes_sha": _sha(packed.tobytes()), "spikes": int(bits.sum()),
            "shape": list(meta.get("shape", packed.shape))}


def run_hashes(out: Path) -> dict:
    out = Path(out)
    res = {"frames": frame_hashes(out / "frames")}
    res.update(spike_hash(out / "spikes.npz"))
    dat = out / "spikes.dat"
    if dat.exists():
        res["dat_sha"] = _sha(dat.read_bytes())
    return res


if __name__ == "__main__":
    print(json.dumps(run_hashes(Path(sys.argv[1])), indent=1, sort_keys=True))
