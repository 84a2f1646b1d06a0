"""render2spike frozen-replay check: is every replay of the frozen launch the function it recorded, frame after frame?

``drjit.freeze`` replays a recording as long as its inputs keep their layout; a change it does not see
(a structure rebuilt outside the recording) makes a replay silently wrong. This renders each bundled
scene's moving clip with the frozen launch (``render2spike/render/frozen.py``) and, at every frame
time, the same function unfrozen with the same seed and pose, and compares the two ``Phi`` channels
value by value::

    python benchmarks/frozen_replay_check.py --out DIR [--scenes ...] [--frames 12] [--spp 16]
    python benchmarks/frozen_replay_check.py --as-vertices ...   # meshes moved by their vertices

``--as-vertices`` moves meshes the way the film launch does (rewriting their vertices) instead of as
instances. Moved that way, the frozen launch's replays were wrong
in 4 of 12 frames of ``translating_object`` (8 in some runs) on the LLVM variant. Run it on a GPU to see whether the
CUDA variant shares that. The frozen launch now refuses vertex motion; this flag switches the refusal off
for the check alone. Writes ``frozen_replay.json`` and ``frozen_replay.md`` in ``--out``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
SCENES = ["translating_object", "rotating_disk", "room_pan", "lambertian_plane"]


def check(scene: str, frames: int, spp: int) -> dict:
    """Frozen replay against the unfrozen function at ``frames`` times of the scene's clip."""
    import render2spike.render.renderer as rm
    from render2spike.render.scene import load_scene
    sc = load_scene(scene)
    r = rm.SceneRenderer(sc, launch="frozen")
    fl = r._frozen
    rows = []
    for k, t_s in enumerate(np.linspace(0.0, sc.duration_s, frames, endpoint=False)):
        r.set_time(float(t_s))
        a = fl.channels(fl.launch(1000 + k, spp, r._cam_m))["Phi"]
        fn, fl._fn = fl._fn, fl._launch  # the same function, not frozen, on the same scene state
        try:
            b = fl.channels(fl.launch(1000 + k, spp, r._cam_m))["Phi"]
        finally:
            fl._fn = fn
        rows.append({"t_s": float(t_s), "equal": bool(np.array_equal(a, b)),
                     "values_differing": int(np.count_nonzero(a != b)), "recordings": fl.n_recordings,
                     "mean_rel_diff": float(abs(a.mean() - b.mean()) / max(abs(b.mean()), 1e-300))})
    return {"scene": scene, "variant": r.variant, "spp": spp, "size": [r.height, r.width],
            "moving": {k: v[0] for k, v in r._moving.items()}, "frames": rows,
            "frames_equal": sum(x["equal"] for x in rows)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=SCENES, help="bundled scenes (default: all four)")
    ap.add_argument("--frames", type=int, default=12, help="frame times per scene over its clip (default 12)")
    ap.add_argument("--spp", type=int, default=16, help="samples per pixel (default 16)")
    ap.add_argument("--as-vertices", action="store_true",
                    help="move meshes by rewriting their vertices (the film launch's way), not as instances")
    ap.add_argument("--out", type=Path, default=HERE / "results")
    a = ap.parse_args(argv)
    if a.frames < 1 or a.spp < 1:
        ap.error("--frames and --spp take positive counts")
    if a.as_vertices:
        import render2spike.render.frozen as fz
        import render2spike.render.renderer as rm
        fz.instance_moving_meshes = lambda mi, d, m: {}
        rm._check_frozen_motion = lambda moving: None
    res = {"when": time.strftime("%Y-%m-%d %H:%M"), "command": "python benchmarks/frozen_replay_check.py "
           + " ".join(sys.argv[1:] if argv is None else argv), "as_vertices": a.as_vertices,
           "load_before": os.getloadavg(), "scenes": []}
    bad = 0
    for scene in a.scenes:
        row = check(scene, a.frames, a.spp)
        res["scenes"].append(row)
        bad += len(row["frames"]) - row["frames_equal"]
        print(f"{scene} ({row['variant']}, moving {row['moving']}): {row['frames_equal']}/{len(row['frames'])} "
              f"replays equal the unfrozen function; recordings {row['frames'][-1]['recordings']}", flush=True)
    res["load_after"] = os.getloadavg()
    lines = ["# Frozen replays against the unfrozen function (`benchmarks/frozen_replay_check.py`)", "",
             f"`{res['command']}`, {res['when']}, load {res['load_before'][0]:.2f}-{res['load_after'][0]:.2f}"
             + (" (meshes moved by their vertices)" if a.as_vertices else ""), "",
             "| scene | variant | moving (how) | frames equal | values differing per frame | recordings |",
             "|---|---|---|---|---|---|"]
    for row in res["scenes"]:
        mv = ", ".join(f"{k} ({v})" for k, v in row["moving"].items()) or "-"
        lines.append(f"| {row['scene']} | {row['variant']} | {mv} | {row['frames_equal']} / {len(row['frames'])} | "
                     f"{' '.join(str(x['values_differing']) for x in row['frames'])} | "
                     f"{row['frames'][-1]['recordings']} |")
    a.out.mkdir(parents=True, exist_ok=True)
    from sensor.io.fileio import write_json_atomic, write_text_atomic
    write_json_atomic(a.out / "frozen_replay.json", res)
    write_text_atomic(a.out / "frozen_replay.md", "\n".join(lines) + "\n")
    print("\n".join(lines))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
