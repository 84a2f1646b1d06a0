"""render2spike frozen-launch memory: peak memory of one frame with the film launch, the frozen launch as split
(``SceneRenderer.launch_counts``: at most ``frozen.MAX_SAMPLES_PER_LAUNCH`` samples a launch) and the frozen
launch in one launch (the cap lifted), each in its own child process::

    python benchmarks/frozen_memory.py --out DIR [--scene rotating_disk] [--spp 1024]

Per child: the peak resident set size (``ru_maxrss``) after one warm-up frame at 4 spp and after the timed
frame at ``--spp`` on the full 250 x 400 sensor, the frame's wall time (recording of each new sample count
included) and its launch counts. Writes ``frozen_memory.json`` and ``frozen_memory.md`` in ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
CASES = (("film", False), ("frozen", False), ("frozen", True))  # (launch, cap lifted)


def child(scene: str, spp: int, launch: str, lifted: bool) -> dict:
    import render2spike.render.renderer as rm
    from render2spike.render.scene import load_scene
    if lifted:
        rm.MAX_SAMPLES_PER_LAUNCH = 1 << 40
    sc = load_scene(scene, ["camera.profile=vidar-default"])
    r = rm.SceneRenderer(sc, launch=launch)
    r.render_exact(0.0, [1], 4)
    warm = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    counts = r.launch_counts(spp)
    t = time.perf_counter()
    r.render_exact(0.001, list(range(1, len(counts) + 1)), spp)
    return {"launch": launch, "cap_lifted": lifted, "spp": spp, "size": [r.height, r.width], "counts": counts,
            "frame_s": time.perf_counter() - t, "peak_mib_after_warmup": warm,
            "peak_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="rotating_disk")
    ap.add_argument("--spp", type=int, default=1024, help="samples per pixel of the measured frame (default 1024)")
    ap.add_argument("--out", type=Path, default=HERE / "results")
    ap.add_argument("--child", nargs=4, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        scene, spp, launch, lifted = a.child
        print(json.dumps(child(scene, int(spp), launch, lifted == "1")))
        return 0
    if a.spp < 1:
        ap.error("--spp takes a positive count")
    rows = []
    for launch, lifted in CASES:
        lb = os.getloadavg()[0]
        out = subprocess.run([sys.executable, __file__, "--child", a.scene, str(a.spp), launch, "1" if lifted else "0"],
                             capture_output=True, text=True)
        if out.returncode != 0:
            print(out.stderr[-2000:], file=sys.stderr)
            return 2
        row = json.loads(out.stdout.strip().splitlines()[-1])
        row["load"] = [round(lb, 2), round(os.getloadavg()[0], 2)]
        rows.append(row)
        print(row, flush=True)
    a.out.mkdir(parents=True, exist_ok=True)
    from sensor.io.fileio import write_json_atomic, write_text_atomic
    write_json_atomic(a.out / "frozen_memory.json", {"when": time.strftime("%Y-%m-%d %H:%M"), "rows": rows})
    lines = ["# Peak memory of one frame (`benchmarks/frozen_memory.py`)", "",
             f"{time.strftime('%Y-%m-%d %H:%M')}, {a.scene}, full sensor, {a.spp} spp; each row its own process.", "",
             "| launch | launches (spp each) | peak RSS MiB | after warm-up MiB | frame s | load |", "|---|---|---|---|---|---|"]
    for r in rows:
        name = r["launch"] + (" (one launch: cap lifted)" if r["cap_lifted"] else "")
        lines.append(f"| {name} | {' + '.join(map(str, r['counts']))} | {r['peak_mib']:.0f} | "
                     f"{r['peak_mib_after_warmup']:.0f} | {r['frame_s']:.1f} | {r['load'][0]:.2f}-{r['load'][1]:.2f} |")
    write_text_atomic(a.out / "frozen_memory.md", "\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
