"""Keyframes in blocks: samples/s of one launch of K keyframes against one launch a keyframe and a bare ``mi.render``.

Where only the camera moves, the render job takes its base keyframes in blocks of up to 16, one frozen launch each
(``FrozenLaunch.launch_block``; ``docs/render.md``, "Keyframes in blocks"). This measures, for one scene, in one
process, the time a keyframe takes three ways, at the same camera times (1 ms apart) and sample counts:

* ``bare``: Mitsuba's own ``mi.render`` of the whole frame (the film launch, ``SceneRenderer.render_raw``), first,
  then let go of (a live film scene breaks ``drjit.freeze``);
* ``own``: the frozen launch, one launch a keyframe (``render_raw``);
* ``block``: the frozen launch, ``--block`` keyframes a launch (``render_block``).

``own`` and ``block`` alternate over ``--rounds`` rounds (the shared machine's load moves); each is warmed (recorded)
first. The figure that matters is block / bare and block / own: on 2 CPU cores a keyframe is mostly its samples, so
they are near 1; on a GPU, where a small keyframe's launch costs more than its samples, the block is the lever.

    python benchmarks/keyframe_blocks.py [--scene room_pan] [--full] [--spp 16 121] [--frames 32] [--block 16]
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import statistics
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from benchmarks.tables import machine, write_report  # noqa: E402


def _load() -> float:
    return float(os.getloadavg()[0])


def _scene(name: str, full: bool):
    from render2spike.render.scene import load_scene
    sets = ["camera.profile=vidar-default"] if full else []
    return load_scene(name, sets)


def _timed(fn, times, seed: int) -> float:
    """Seconds ``fn(times, seed)`` takes."""
    t0 = time.perf_counter()
    fn(times, seed)
    return time.perf_counter() - t0


def measure(scene_name: str, full: bool, spp: int, frames: int, block: int, rounds: int, variant) -> dict:
    from render2spike.render.renderer import SceneRenderer
    times = [0.001 * i for i in range(frames)]
    scene = _scene(scene_name, full)

    def own(r):
        return lambda ts, seed: [r.render_raw(t, seed + i, spp) for i, t in enumerate(ts)]

    load0 = _load()
    film = SceneRenderer(scene, variant, launch="film")
    cal = film.calibration
    own(film)(times[:2], 1)  # warm: the kernel compiled or loaded
    bare_s = _timed(own(film), times, 100)
    h, w = film.height, film.width
    del film
    gc.collect()
    r = SceneRenderer(scene, variant, launch="frozen", calibration=cal)
    k = min(block, r.frame_launch.block_size(spp, block))

    def blocks(ts, seed):
        return [r.render_block(ts[i:i + k], seed + i, spp) for i in range(0, len(ts), k)]

    own(r)(times[:2], 1)
    blocks(times, 1)  # every block length recorded
    own_s, block_s = [], []
    for j in range(rounds):
        own_s.append(_timed(own(r), times, 1000 * (j + 1)))
        block_s.append(_timed(blocks, times, 1000 * (j + 1) + 500))
    samples = frames * h * w * spp
    own_m, block_m = statistics.median(own_s), statistics.median(block_s)
    return {"scene": scene_name, "size": [h, w], "spp": spp, "frames": frames, "block": k, "variant": r.variant,
            "bare_s": bare_s, "own_s": own_s, "block_s": block_s,
            "bare_ms_per_frame": 1e3 * bare_s / frames, "own_ms_per_frame": 1e3 * own_m / frames,
            "block_ms_per_frame": 1e3 * block_m / frames, "bare_msamples_per_s": samples / bare_s / 1e6,
            "block_msamples_per_s": samples / block_m / 1e6, "block_over_bare": block_m / bare_s,
            "block_over_own": block_m / own_m, "load_before": load0, "load_after": _load()}


def report(rows: list[dict], out: Path, cmd: str) -> None:
    m = machine()
    lines = ["# Keyframes in blocks: one launch of K keyframes against one a keyframe and a bare mi.render", "",
             f"Machine: {m['cpu']}, {m['cores']} cores" + (f", {m['gpu']}" if m["gpu"] else "")
             + f". `{cmd}`. Times per keyframe; own and block: median over the rounds, which alternate.", "",
             "| scene | size | spp | variant | block | bare mi.render [ms] | own launch [ms] | block [ms] | "
             "block / bare | block / own | block Msamples/s | load before / after |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['size'][0]} x {r['size'][1]} | {r['spp']} | {r['variant']} | {r['block']} | "
                     f"{r['bare_ms_per_frame']:.2f} | {r['own_ms_per_frame']:.2f} | {r['block_ms_per_frame']:.2f} | "
                     f"{r['block_over_bare']:.2f} | {r['block_over_own']:.2f} | {r['block_msamples_per_s']:.2f} | "
                     f"{r['load_before']:.1f} / {r['load_after']:.1f} |")
    lines += ["", "Bare: Mitsuba's film launch (`mi.render`), measured once before the frozen launch exists in the "
              "process. 1.00 would be a block that costs what its samples cost in the reference launch."]
    write_report(out, "keyframe_blocks", lines, {"rows": rows})


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("--scene", default="room_pan", help="a bundled scene in which only the camera moves")
    ap.add_argument("--full", action="store_true", help="the full 250 x 400 sensor (default: the scene's window)")
    ap.add_argument("--spp", type=int, nargs="+", default=[16, 121], help="samples per pixel (default 16 121)")
    ap.add_argument("--frames", type=int, default=32, help="keyframes timed each way (default 32)")
    ap.add_argument("--block", type=int, default=16, help="keyframes a block launch (default 16)")
    ap.add_argument("--rounds", type=int, default=2, help="own/block rounds, alternating (default 2)")
    ap.add_argument("--variant", default=None, help="Mitsuba variant (default: the one auto picks)")
    ap.add_argument("--out", type=Path, default=HERE / "results")
    a = ap.parse_args(argv)
    rows = []
    for spp in a.spp:
        rows.append(measure(a.scene, a.full, spp, a.frames, a.block, a.rounds, a.variant))
        print(json.dumps({k: v for k, v in rows[-1].items() if not isinstance(v, list)}), flush=True)
    report(rows, a.out, " ".join(["python benchmarks/keyframe_blocks.py", *(argv if argv is not None else sys.argv[1:])]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
