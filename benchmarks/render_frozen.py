"""render2spike frozen-launch benchmark: the film launch against the frozen launch, frame for frame.

``SceneRenderer(..., launch="film")`` renders each frame with the integrator's ``render`` into Mitsuba's
spectral film, traced anew on the host every frame; ``launch="frozen"`` (``render2spike/render/frozen.py``)
records the launch once with ``drjit.freeze`` and replays it. This times, per point (scene, size, spp),
what the render job pays per frame for its render: ``set_time`` to the frame's time, the launch, and the
wait for the channels (``SceneRenderer.render_exact``), on a moving scene over ``--frames`` frame times
after ``--warm`` frames (which record and compile; Dr.Jit may re-record a count once more in a later
frame, which the median hides; the ``recordings`` column gives each round's count). Each launch runs in its own child process (a camera
with the spectral film anywhere in a process breaks ``drjit.freeze``), the two alternating for
``--rounds`` rounds; the ratio film / frozen is taken per round, in one run, with the load average
before and after each child.

``--pipeline`` also times the render job per frame at each point (``render_scene`` with a fixed spp and
no adaptive refinement, as ``benchmarks/render.py`` times its pipeline blocks) with each launch, so the job
with the frozen launch can be set against the film launch's bare frame. Beside it, per frozen round: the cost of
creating one file in the job's folder (``file_create_probe``), and the frozen job again with its frame files left
out (a diagnostic, not a job: what the rest of the job costs).

``--job`` also times the whole ``render2spike render`` command on one scene with each launch (the
pilot, the noise budget, the verification renders and the frame files included; the frozen launch records
once per sample count it meets).

    python benchmarks/render_frozen.py --rounds 3 --job --pipeline

Writes ``frozen_launch.json`` and ``frozen_launch.md`` in ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent

#: (scene, size, spp): the bundled scenes at their window and at the full 250 x 400 sensor
POINTS = [("lambertian_plane", "window", 16), ("rotating_disk", "window", 16), ("room_pan", "window", 16),
          ("translating_object", "window", 16), ("rotating_disk", "window", 256), ("rotating_disk", "full", 4),
          ("rotating_disk", "full", 64)]
FULL = ["camera.profile=vidar-default"]


def _load():
    return tuple(round(x, 2) for x in os.getloadavg())


def child(scene: str, size: str, spp: int, launch: str, frames: int, warm: int) -> dict:
    """Time ``frames`` frames of ``render_exact`` after ``warm`` ones (ms, median and each), in this process."""
    from render2spike.render.renderer import SceneRenderer
    from render2spike.render.scene import load_scene
    sc = load_scene(scene, FULL if size == "full" else [])
    r = SceneRenderer(sc, launch=launch)
    dur = float(sc.duration_s)
    times = np.linspace(0.0, dur, warm + frames, endpoint=False)
    ms = []
    for i, t_s in enumerate(times):
        t0 = time.perf_counter()
        p, e = r.render_exact(float(t_s), [1000 + i], spp)
        dt = time.perf_counter() - t0
        if i >= warm:
            ms.append(1e3 * dt)
    return {"scene": scene, "size": size, "spp": spp, "launch": launch, "height": r.height, "width": r.width,
            "variant": r.variant, "frame_ms": ms, "median_ms": float(np.median(ms)),
            "recordings": r._frozen.n_recordings if r._frozen is not None else None, "mean_phi": float(p.mean())}


def pipeline_child(scene: str, size: str, spp: int, launch: str, frames: int, write: bool = True) -> dict:
    """The render job's time per frame (ms) with ``launch``: ``render_scene`` of ``frames`` frames at ``spp``
    (adaptive refinement off), from its first frame's render to its return, as ``benchmarks/render.py``
    times its pipeline blocks (frame writes, journal, manifest and verification launches in; loading, the
    light level and the pilot out). Kernel compilation in that span (Dr.Jit's kernel history) is taken out
    and reported; a recording of the frozen launch is not (it is part of what the launch costs)."""
    import tempfile

    import drjit as dr

    from render2spike.render import renderer as rmod
    from render2spike.render.job import render_scene
    from render2spike.render.scene import load_scene
    sets = [f"render.spp={spp}", "render.adaptive.enabled=false"] + (FULL if size == "full" else [])
    rate = float(load_scene(scene, sets).render["keyframe_rate_hz"])
    sc = load_scene(scene, sets, duration_s=(frames - 1) / rate)
    orig = rmod.SceneRenderer.render_frame
    st = {}

    def wrapped(self, t_s, *a, **k):
        if "t_first" not in st:
            dr.kernel_history()  # read = cleared
            st["t_first"] = time.perf_counter()
        return orig(self, t_s, *a, **k)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    rmod.SceneRenderer.render_frame = wrapped
    if not write:  # the diagnostic: the job with its frame files left out (the journal still names them)
        import sensor.io.frames
        sensor.io.frames.write_frame = lambda *a, **k: None
    with tempfile.TemporaryDirectory(dir=HERE / ".scratch" if (HERE / ".scratch").is_dir() else None) as d:
        res = render_scene(sc, Path(d) / "f", progress=False, log=lambda *a: None, launch=launch)
        t_end = time.perf_counter()
        probe = file_create_probe(Path(d) / "f")
    hist = dr.kernel_history()
    compile_s = sum(float(h.get("backend_time", 0.0)) for h in hist
                    if h.get("type") == dr.KernelType.JIT and not h.get("cache_hit")) / 1e3
    return {"scene": scene, "size": size, "spp": spp, "launch": launch, "frames": res.n_frames,
            "median_ms": 1e3 * (t_end - st["t_first"] - compile_s) / res.n_frames, "compile_s": compile_s,
            "file_create": probe}


def file_create_probe(folder: Path, n: int = 200) -> dict:
    """What making one file costs in ``folder`` now: ``n`` small files each created under a temp name
    (``O_CREAT | O_EXCL``), written (7 kB, a 32 x 48 frame's size) and renamed, as ``sensor.io.fileio.
    write_bytes_atomic`` writes a frame; then removed. -> ``{"wall_ms", "sys_ms"}`` per file (the system CPU
    time of this process: the kernel's part, which a frame's writer thread takes from the render's threads).

    Why: on the 2-CPU development VM (ext4 without a journal), ``perf`` put most of a file creation's time in
    the inode allocator's scan for recently deleted inodes (``recently_deleted``, ``find_inode_bit``): 0.07-0.85
    ms of kernel CPU per new file, at other times ~0.03 ms, as the benchmarks and tests had deleted more or
    fewer files. So the render job's overhead per frame is reported beside it."""
    import resource
    data = b"\0" * 7000
    names = [(str(folder / f".probe-{os.getpid()}-{i}.part"), str(folder / f".probe-{os.getpid()}-{i}.exr"))
             for i in range(n)]
    r0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
    for tmp, final in names:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        os.write(fd, data)
        os.close(fd)
        os.replace(tmp, final)
    t1, r1 = time.perf_counter(), resource.getrusage(resource.RUSAGE_SELF)
    for _, final in names:
        os.unlink(final)
    return {"wall_ms": 1e3 * (t1 - t0) / n, "sys_ms": 1e3 * (r1.ru_stime - r0.ru_stime) / n}


def _run_child(args: list[str]) -> dict:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", *args]
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    before = _load()
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
    if out.returncode != 0:
        raise SystemExit(f"render_frozen: the child {' '.join(args)} failed:\n{out.stderr[-2000:]}")
    row = json.loads(out.stdout.strip().splitlines()[-1])
    row["load_before"], row["load_after"] = before, _load()
    return row


def job(scene: str, launch: str, out: Path) -> dict:
    """Wall time of ``render2spike render SCENE --launch LAUNCH`` into a fresh folder."""
    folder = out / f"job_{scene}_{launch}"
    cmd = [sys.executable, "-m", "render2spike", "render", scene, "--out", str(folder), "--launch", launch,
           "--quiet", "--overwrite"]
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    before = _load()
    t0 = time.perf_counter()
    res = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
    wall = time.perf_counter() - t0
    if res.returncode != 0:
        raise SystemExit(f"render_frozen: {' '.join(cmd)} failed:\n{res.stderr[-2000:]}")
    m = json.loads((folder / "frames.json").read_text())
    import shutil
    shutil.rmtree(folder, ignore_errors=True)
    return {"scene": scene, "launch": launch, "wall_s": wall, "frames": len(m["frames"]), "spp": m["spp"],
            "render_noise_ratio": m.get("render_noise_ratio", {}).get("mean"), "load_before": before,
            "load_after": _load()}


def report(res: dict) -> str:
    L = ["# Frozen launch against film launch (`benchmarks/render_frozen.py`)", "",
         f"{res['when']}, {res['machine']}, {res['rounds']} rounds of {res['frames']} frames after {res['warm']} "
         f"warm-up frames; per round, the two launches in alternating child processes. ms per frame: the median "
         f"of `set_time` + launch + wait (`SceneRenderer.render_exact`) over the frames; ratio = film / frozen "
         "in the same round (above 1: the frozen launch is faster).", "",
         "| scene | size | spp | film ms (rounds) | frozen ms (rounds) | film / frozen (rounds) | recordings | load |",
         "|---|---|---|---|---|---|---|---|"]
    for p in res["points"]:
        f = [r["median_ms"] for r in p["film"]]
        z = [r["median_ms"] for r in p["frozen"]]
        ratio = [a / b for a, b in zip(f, z)]
        loads = [x for r in p["film"] + p["frozen"] for x in (r["load_before"][0], r["load_after"][0])]
        L.append(f"| {p['scene']} | {p['film'][0]['height']} x {p['film'][0]['width']} | {p['spp']} | "
                 f"{', '.join(f'{x:.2f}' for x in f)} | {', '.join(f'{x:.2f}' for x in z)} | "
                 f"{', '.join(f'{x:.2f}' for x in ratio)} | {', '.join(str(r['recordings']) for r in p['frozen'])} | "
                 f"{min(loads):.2f}-{max(loads):.2f} |")
    if any(p.get("pipeline_film") for p in res["points"]):
        L += ["", "The render job per frame (`render_scene`, fixed spp, adaptive off: frame writes, journal and "
              "verification launches in; kernel compilation out), against the film launch's bare frame above "
              "(the goal's bare `mi.render`) and against each launch's own bare frame; last, what creating one "
              "file (a frame's size, under a temp name, then renamed) cost in the frozen job's folder right after "
              "it (`file_create_probe`), in wall ms and the kernel's CPU ms: the job makes one file per frame; "
              "and, a diagnostic, the frozen job with `write_frame` made a no-op (its frame files left out, the "
              "rest as it is), in the same round:", "",
              "| scene | size | spp | job ms, film | job ms, frozen | frozen job / bare film launch | "
              "film job / its launch | frozen job / its launch | frozen job - its launch, ms | "
              "a file's creation, ms (sys CPU) | frozen job without its frame files / its launch |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
        for p in res["points"]:
            if not p.get("pipeline_film"):
                continue
            jf = [r["median_ms"] for r in p["pipeline_film"]]
            jz = [r["median_ms"] for r in p["pipeline_frozen"]]
            f = [r["median_ms"] for r in p["film"]]
            z = [r["median_ms"] for r in p["frozen"]]
            def fmt(xs):
                return ", ".join(f"{x:.2f}" for x in xs)
            L.append(f"| {p['scene']} | {p['film'][0]['height']} x {p['film'][0]['width']} | {p['spp']} | {fmt(jf)} | "
                     f"{fmt(jz)} | {fmt([a / b for a, b in zip(jz, f)])} | {fmt([a / b for a, b in zip(jf, f)])} | "
                     f"{fmt([a / b for a, b in zip(jz, z)])} | {fmt([a - b for a, b in zip(jz, z)])} | "
                     + (", ".join(f"{r['file_create']['wall_ms']:.2f} ({r['file_create']['sys_ms']:.2f})"
                                  if r.get("file_create") else "-" for r in p["pipeline_frozen"])) + " | "
                     + (fmt([r["median_ms"] / b for r, b in zip(p["pipeline_nowrite_frozen"], z)])
                        if p.get("pipeline_nowrite_frozen") else "-") + " |")
    if res.get("jobs"):
        L += ["", "`render2spike render SCENE --launch ...` (whole command, fresh folder, bundled scene):", "",
              "| scene | launch | wall s | frames | spp | render/shot noise | load |", "|---|---|---|---|---|---|---|"]
        for j in res["jobs"]:
            L.append(f"| {j['scene']} | {j['launch']} | {j['wall_s']:.2f} | {j['frames']} | {j['spp']} | "
                     f"{j['render_noise_ratio']:.3f} | {j['load_before'][0]:.2f}-{j['load_after'][0]:.2f} |")
    return "\n".join(L) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=HERE / "results", help="folder for the report")
    ap.add_argument("--rounds", type=int, default=3, help="alternating rounds per point (default 3)")
    ap.add_argument("--frames", type=int, default=24, help="timed frames per child (default 24)")
    ap.add_argument("--warm", type=int, default=4, help="untimed frames first (default 4)")
    ap.add_argument("--points", nargs="+", default=None, metavar="SCENE:SIZE:SPP",
                    help="points to time (default: " + " ".join(f"{a}:{b}:{c}" for a, b, c in POINTS) + ")")
    ap.add_argument("--job", nargs="*", default=None, metavar="SCENE",
                    help="also time the whole render command with each launch (default scene: rotating_disk)")
    ap.add_argument("--pipeline", action="store_true",
                    help="also time the render job per frame (render_scene, fixed spp, adaptive off) with each "
                         "launch at every point, beside the bare launches")
    ap.add_argument("--child", nargs=7, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        kind, scene, size, spp, launch, frames, warm = a.child
        if kind in ("pipeline", "pipeline_nowrite"):
            print(json.dumps(pipeline_child(scene, size, int(spp), launch, int(frames), kind == "pipeline")))
        else:
            print(json.dumps(child(scene, size, int(spp), launch, int(frames), int(warm))))
        return 0
    points = POINTS
    if a.points:
        try:
            points = [(s, z, int(n)) for s, z, n in (p.split(":") for p in a.points)]
        except ValueError:
            ap.error("--points takes SCENE:SIZE:SPP, e.g. rotating_disk:window:16")
        for s, z, n in points:
            if z not in ("window", "full") or n < 1:
                ap.error(f"--points {s}:{z}:{n}: SIZE is window or full, SPP a positive count")
    if a.rounds < 1 or a.frames < 1 or a.warm < 0:
        ap.error("--rounds and --frames take positive counts, --warm a count of 0 or more")
    a.out.mkdir(parents=True, exist_ok=True)
    import platform
    res = {"when": time.strftime("%Y-%m-%d %H:%M"), "machine": f"{platform.machine()}, {os.cpu_count()} CPUs",
           "rounds": a.rounds, "frames": a.frames, "warm": a.warm, "points": [], "jobs": []}
    for scene, size, spp in points:
        p = {"scene": scene, "size": size, "spp": spp, "film": [], "frozen": [], "pipeline_film": [],
             "pipeline_frozen": [], "pipeline_nowrite_frozen": []}
        kinds = ("launch", "pipeline") if a.pipeline else ("launch",)
        for rnd in range(a.rounds):
            for launch in (("film", "frozen") if rnd % 2 == 0 else ("frozen", "film")):
                for kind in kinds + (("pipeline_nowrite",) if a.pipeline and launch == "frozen" else ()):
                    row = _run_child([kind, scene, size, str(spp), launch, str(a.frames), str(a.warm)])
                    p[launch if kind == "launch" else f"{kind}_{launch}"].append(row)
                    print(f"{scene} {size} {spp} spp {launch} {kind}: {row['median_ms']:.2f} ms/frame "
                          f"(load {row['load_before'][0]}-{row['load_after'][0]})", flush=True)
        res["points"].append(p)
        (a.out / "frozen_launch.json").write_text(json.dumps(res, indent=1))
    if a.job is not None:
        for scene in (a.job or ["rotating_disk"]):
            for launch in ("film", "frozen", "film", "frozen"):
                j = job(scene, launch, a.out)
                res["jobs"].append(j)
                print(f"render {scene} --launch {launch}: {j['wall_s']:.2f} s, {j['frames']} frames", flush=True)
    (a.out / "frozen_launch.json").write_text(json.dumps(res, indent=1))
    (a.out / "frozen_launch.md").write_text(report(res))
    print(report(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
