"""Static-region reuse: render time and render noise with and without it, in one run.

One command::

    python benchmarks/static_reuse.py                    # rotating_disk (the README's main job) and translating_object
    python benchmarks/static_reuse.py --duration-s 0.1   # the main job's full clip
    python benchmarks/static_reuse.py --out DIR          # the report elsewhere (default benchmarks/results)

writes ``static_reuse.md`` and ``static_reuse.json`` in ``--out`` (overwritten: one current table).

For each scene it renders the same clip four times in this process, in the order whole, reuse, reuse, whole
(``render.static_reuse: false``: every keyframe rendered whole; reuse: the default,
:mod:`render2spike.render.reuse`), each into a fresh folder, and keeps the one of each mode that took the
least CPU time (``--rounds 1``: once each); and reads each render's ``frames.json``: the keyframes stage's seconds (every keyframe
rendered, checked and written; the static frame and the pilot are in the pilot stage), the spp, the
dynamic fraction of the frame, the static frame's spp, and the render-noise ratio the budget measures on
its verified keyframes (:mod:`render2spike.render.noise`: ``sqrt(W mean(v_eff) / mean(r + d))``, with
``v_eff = v / K`` for a pixel rendered in every keyframe and ``v`` for a static one), and, with reuse, the
static check (the static pixels of a whole-frame render against the static frame: about 1 when nothing
changed there). Samples per keyframe: the frames' mean spp (each frame's header) x pixels rendered (the
dynamic fraction with reuse). Render CPU: the process's CPU time over the render (all threads), less moved
by other work on a shared machine than the wall time. Keyframes stage / bare launch: the stage's seconds over
the time its samples take at the rate of a bare whole-frame launch of the same scene and spp, timed in the same
process after the renders (1.00: the stage is all launch). The load average is recorded before and after; the
ratio of the two modes is the figure, not either time.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

SCENES = ("rotating_disk", "translating_object")


def one(scene_name: str, reuse: bool, duration_s: float, root: Path) -> dict:
    from render2spike.render.job import render_scene
    from render2spike.render.scene import load_scene
    sets = [] if reuse else ["render.static_reuse=false"]
    scene = load_scene(scene_name, sets, duration_s=duration_s)
    out = root / f"{scene_name}-{'reuse' if reuse else 'whole'}-{time.monotonic_ns()}"
    t0, c0 = time.perf_counter(), time.process_time()
    res = render_scene(scene, out, progress=False, log=lambda *a: None)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    m = res.manifest
    st = m["render_stage_seconds"]
    sr = m.get("static_reuse", {})
    n_px = scene.profile.height * scene.profile.width
    frac = (sr.get("dynamic_fraction") or {}).get("mean") if sr.get("applied") else 1.0
    from sensor.io.frames import read_frames
    seq = read_frames(out)
    spp_mean = sum(int(seq.read(i).header["spp"]) for i in range(len(seq))) / len(seq)
    return {"scene": scene_name, "reuse": bool(sr.get("applied")), "wall_s": wall, "cpu_s": cpu, "stages_s": st,
            "frames": m["n_rendered_this_run"], "spp": m["spp"], "spp_by_level": m.get("spp_by_level"),
            "size": [scene.profile.height, scene.profile.width],
            "dynamic_fraction": frac, "samples_per_keyframe": frac * n_px * spp_mean,
            "static_spp": sr.get("static_spp"), "static_check": sr.get("static_check"),
            "ratio": m["render_noise_ratio"].get("verified_mean"), "budget": {
                k: m["noise_budget"].get(k) for k in ("spp_needed", "predicted_ratio", "clipped", "static")}}


def bare_rate(scene_name: str, spp: int, duration_s: float) -> dict:
    """samples/s of a bare whole-frame launch of the scene at ``spp`` (``SceneRenderer.render_raw``, the launch
    the render job takes): 2 untimed calls, then the median of 5 timed ones at times spread over the clip."""
    import statistics

    from render2spike.render.renderer import SceneRenderer
    from render2spike.render.scene import load_scene
    rnd = SceneRenderer(load_scene(scene_name, duration_s=duration_s))
    times = [duration_s * i / 4 for i in range(5)]
    for t in times[:2]:
        rnd.render_raw(t, 7, spp)
    calls = []
    for t in times:
        t0 = time.perf_counter()
        rnd.render_raw(t, 7, spp)
        calls.append(time.perf_counter() - t0)
    med = statistics.median(calls)
    return {"spp": int(spp), "median_s": med, "samples_per_s": spp * rnd.height * rnd.width / med}


def over_bare(row: dict, bare: dict) -> float:
    """The keyframes stage's seconds over the seconds its samples take at the bare launch's rate."""
    rate = bare[f"{row['scene']} {row['spp']}"]["samples_per_s"]
    return row["stages_s"]["keyframes"] / (row["samples_per_keyframe"] * row["frames"] / rate)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration-s", type=float, default=0.05, help="camera time of each clip [s] (default 0.05)")
    ap.add_argument("--scenes", default=",".join(SCENES), help="bundled scenes, comma-separated")
    ap.add_argument("--rounds", type=int, choices=(1, 2), default=2,
                    help="1: whole then reuse; 2 (default): whole, reuse, reuse, whole, the best of each kept")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    a = ap.parse_args(argv)
    from benchmarks.tables import machine, write_report
    load0 = os.getloadavg()
    rows = []
    with tempfile.TemporaryDirectory(prefix="r2s-reuse-") as tmp:
        for name in a.scenes.split(","):
            for reuse in (False, True, True, False)[:4 if a.rounds == 2 else 2]:  # ABBA: drift in the load cancels
                rows.append(one(name, reuse, a.duration_s, Path(tmp)))
                print(json.dumps({k: rows[-1][k] for k in ("scene", "reuse", "wall_s", "cpu_s", "ratio")}),
                      flush=True)
        bare = {f"{r['scene']} {r['spp']}": bare_rate(r["scene"], r["spp"], a.duration_s)
                for r in {(r["scene"], r["spp"]): r for r in rows}.values()}
    load1 = os.getloadavg()
    rec = {"machine": machine(), "load_before": load0, "load_after": load1, "duration_s": a.duration_s,
           "rows": rows, "bare_launch": bare}
    lines = ["# Static-region reuse: keyframe time and render noise, whole frames against reuse", "",
             f"Machine: {rec['machine']['cpu']}, {rec['machine']['cores']} cores; load average "
             f"{load0[0]:.1f} before, {load1[0]:.1f} after. Clips of {a.duration_s:g} s, the scenes' own noise "
             "budget. `python benchmarks/static_reuse.py`.", "",
             "| scene | reuse | keyframes | spp by level (dynamic) | dynamic fraction | samples / keyframe | static spp | "
             "keyframes stage [s] | keyframes stage / bare launch | pilot + static frame [s] | render CPU [s] | "
             "ratio (verified) | static check z2 / limit |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    best = {}
    for r in rows:  # the best (least CPU) render of each scene and mode
        k = (r["scene"], r["reuse"])
        if k not in best or r["cpu_s"] < best[k]["cpu_s"]:
            best[k] = r
    rows = list(best.values())
    for r in rows:
        chk = "; ".join(f"{c['z2_mean']:.2f} / {c['limit']:.2f}" for c in (r["static_check"] or [])
                        if c.get("z2_mean") is not None) or "-"
        lines.append(f"| {r['scene']} | {'yes' if r['reuse'] else 'no'} | {r['frames']} | "
                     f"{' / '.join(map(str, r['spp_by_level'] or [r['spp']]))} | "
                     f"{r['dynamic_fraction']:.3f} | {r['samples_per_keyframe']:,.0f} | {r['static_spp'] or '-'} | "
                     f"{r['stages_s']['keyframes']:.1f} | "
                     f"{over_bare(r, bare):.2f} | "
                     f"{r['stages_s']['pilot']:.1f} | {r['cpu_s']:.1f} | "
                     f"{r['ratio'] if r['ratio'] is None else round(r['ratio'], 3)} | {chk} |")
    lines.append("")
    lines.append("Keyframes stage / bare launch: the stage's seconds over the time its samples (samples / keyframe x "
                 "keyframes) take at the bare launch's rate, `SceneRenderer.render_raw` of the whole frame at the "
                 "row's base spp, median of 5 calls after 2 untimed ones, in the same process after the renders: "
                 + ", ".join(f"{n.split()[0]} at {b['spp']} spp {b['samples_per_s'] / 1e6:.2f} million samples/s"
                             for n, b in bare.items())
                 + ". 1.00 would be a stage that is all launch; the rest is the coverage test, the checks, the "
                 "verified frames' second renders and Python.")
    lines.append("")
    for name in a.scenes.split(","):
        w = next((r for r in rows if r["scene"] == name and not r["reuse"]), None)
        u = next((r for r in rows if r["scene"] == name and r["reuse"]), None)
        if w and u:
            lines.append(f"- {name}: with reuse the render takes {u['cpu_s'] / w['cpu_s']:.2f}x the CPU time of "
                         f"whole frames ({u['wall_s'] / w['wall_s']:.2f}x the wall time; keyframes stage "
                         f"{u['stages_s']['keyframes'] / w['stages_s']['keyframes']:.2f}x), for "
                         f"{u['samples_per_keyframe'] / w['samples_per_keyframe']:.2f}x the samples per keyframe.")
    write_report(a.out, "static_reuse", lines, rec)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
