"""Dataset throughput: camera-seconds of spikes plus ground truth per hour, and where each clip's time goes.

One command::

    python benchmarks/dataset.py                       # the default spec below, on this machine
    python benchmarks/dataset.py --device "1x H200"    # a note on the machine, printed beside the figures
    python benchmarks/dataset.py --spec FILE           # a given dataset spec instead
    python benchmarks/dataset.py --out DIR             # the report elsewhere (default benchmarks/results)

writes ``dataset.md`` and ``dataset.json`` in ``--out`` (overwritten: one current table, not a history).

What it does
------------
1. Builds the dataset of the spec in this process (``render2spike.dataset.build_dataset`` with
   ``workers=0``, a fresh folder under a temporary directory, removed afterwards unless ``--keep``), timing
   the whole call: planning and checks, every render, every sample, the manifest and summary.
   The default spec: the bundled scenes ``translating_object`` and ``rotating_disk``, lux 5 and 50, model
   ``elssim``, seed 0, a clip of ``--duration-s`` (0.02 s: 400 intervals of 50 us) on a centred
   ``--window`` (16 x 24 pixels) of the 250 x 400 sensor, the scenes' own noise budget (spp chosen by the
   pilot, at most their ``max_spp``). 2 scenes x 2 lux = 4 clips from 2 renders (every lux reuses a render).
2. Reads the timings the dataset records: each render folder's ``frames.json`` (``render_seconds``, and
   ``render_stage_seconds``: start, load, meter, pilot, keyframes) and each sample's ``timing`` in the
   manifest (read, simulate, truth, write; the rest of the sample's ``seconds`` is "other").
3. Times a bare launch of each render's scene at the render's spp and size: the project's own renderer
   (``SceneRenderer(scene).render_raw(t, seed, spp)``, the launch the render job takes, ``auto``),
   ``--bare-warm`` untimed calls (3), then ``--bare-calls`` timed calls (10) at times spread over the clip;
   samples/s = spp x H x W / the median call.

Figures
-------
* **camera-seconds per hour**: the clips' camera time (intervals x interval length, summed over the
  samples made) / the wall time of ``build_dataset`` x 3600, at the spec's window size (a larger window
  costs more per camera-second).
* **per clip**: its share of its render (``render_seconds`` / the clips that reuse the render), then its
  sample's simulate, truth, IO (read + write) and other, in seconds and % of the clip. The dataset makes no
  preview (``render2spike run`` does); the light meter and the noise pilot are in the render's share and
  split out per render.
* **per render**: frames rendered, spp, the stages, and samples/s of the whole render (spp x H x W x frames
  rendered / ``render_seconds``) and of its keyframes stage alone, against the bare launch's samples/s.
  Both job figures count one launch per keyframe; the verification launches (the first keyframe and every
  128th) are extra work inside them.

Before the timed run, each spike model of the spec runs once on a 2 x 2 clip, so that its numba kernels are
compiled (the first run on a checkout) or loaded from numba's cache (cached beside their source) outside
the figures; ``--cold`` skips it. The first render of the process imports Mitsuba (in its "start" stage) and
compiles its kernels (Dr.Jit caches them on disk between processes). The load average is recorded before and
after.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
from tables import fmt as _fmt, machine  # noqa: E402,F401

SENSOR_HW = (250, 400)  # the vidar-default sensor the bundled scenes' windows are cut from


def _load() -> tuple:
    return tuple(round(x, 2) for x in os.getloadavg())





def commit() -> str:
    """The checkout's commit (short hash; '+changes' when the tracked files differ from it)."""
    try:
        h = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT,
                           timeout=30).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True,
                               text=True, cwd=ROOT, timeout=30).stdout.strip()
        return (h or "unknown") + (" +changes" if dirty else "")
    except (OSError, subprocess.TimeoutExpired):
        return "unknown"


def default_spec(duration_s: float, window: tuple[int, int], lux: list[float], scenes: list[str]) -> dict:
    """The benchmark's spec: ``scenes`` on a centred ``window`` (H, W) of the sensor, a ``duration_s`` clip."""
    h, w = window
    r0, c0 = (SENSOR_HW[0] - h) // 2, (SENSOR_HW[1] - w) // 2
    return {"format": "render2spike-dataset", "seed": 0, "scenes": list(scenes),
            "set": [f"camera.profile.window=[{r0},{c0},{h},{w}]"], "duration_s": duration_s, "lux": list(lux),
            "models": ["elssim"]}


def warm_numba(models: list[str]) -> float:
    """Run each spike model once on a 2 x 2 clip (the dataset's own ``simulate_clip``, the ``vidar-default``
    sensor): its numba kernels compiled or loaded from numba's cache before the timed run; -> seconds."""
    import numpy as np

    from render2spike.studies.common import profile_for, simulate_clip
    t0 = time.perf_counter()
    for m in models:
        prof = profile_for("vidar-default", (2, 2), m)
        t = np.array([0.0, 20 * prof.interval_s])
        simulate_clip(np.full((2, 2, 2), 0.5, np.float32), t, prof, m, 0, 10)
    return time.perf_counter() - t0


def bare_launch(s, spp: int, times_s: list[float], seed: int, warm: int) -> dict:
    """samples/s of the renderer's own launch (``render_raw``) of ``s``'s scene at ``spp``: ``warm`` untimed
    calls at those times (cycling), then one timed call at each time. Also the renderer's set-up (load + light meter)
    [s]."""
    from render2spike.dataset import _load_source_scene
    from render2spike.render.renderer import SceneRenderer
    scene = _load_source_scene(s)
    t0 = time.perf_counter()
    rnd = SceneRenderer(scene)
    setup_s = time.perf_counter() - t0
    for i in range(warm):  # at the timed calls' times (a launch may record anew at a new time)
        rnd.render_raw(times_s[i % len(times_s)], seed, spp)
    calls = []
    for t in times_s:
        t1 = time.perf_counter()
        rnd.render_raw(t, seed, spp)
        calls.append(time.perf_counter() - t1)
    med = statistics.median(calls)
    return {"variant": rnd.variant, "launch": rnd.launch_kind, "setup_s": setup_s, "load_s": rnd.load_s,
            "calls_s": calls, "median_s": med, "samples_per_s": spp * rnd.height * rnd.width / med}


def measure(spec, work: Path, bare_calls: int, bare_warm: int, warm: bool = True, log=print) -> dict:
    """Build the dataset of ``spec`` (a mapping, or a spec file's path) in ``work/dataset`` (in this process), then the bare launches; -> the
    figures (see the module docstring)."""
    from render2spike.dataset import build_dataset, load_spec, prepare
    out = work / "dataset"
    spec_d, spec_path = load_spec(spec)
    pl = prepare(spec_d, spec_path, log=lambda *a: None)
    numba_s = None
    if warm:
        log("numba: the spike models' kernels, before the timed run")
        numba_s = warm_numba(list(dict.fromkeys(s.model for s in pl.samples)))
    load_before = _load()
    t0 = time.perf_counter()
    res = build_dataset(spec, out, workers=0, progress=False, log=log)
    wall_s = time.perf_counter() - t0
    load_after = _load()
    man = json.loads((out / "manifest.json").read_text())
    renders = {}
    for s, rk in zip(pl.samples, pl.render_keys):
        if rk in renders:
            renders[rk]["n_clips"] += 1
            continue
        fm = json.loads((out / "renders" / rk / "frames.json").read_text())
        src = s.source.get("scene") or s.source.get("frames")
        renders[rk] = {"key": rk, "scene": Path(src).stem if "scene" in s.source else src, "sample": s,
                       "n_clips": 1, "spp": int(fm["spp"]), "height": int(fm["height"]), "width": int(fm["width"]),
                       "frames": len(fm["frames"]), "rendered": int(fm["n_rendered_this_run"]),
                       "render_s": float(fm["render_seconds"]), "stages_s": fm.get("render_stage_seconds") or {},
                       "variant": fm.get("variant"), "launch": fm.get("launch"),
                       "times_s": [f["time_s"] for f in fm["frames"]]}
    clips = []
    for s, sid, rk in zip(pl.samples, pl.ids, pl.render_keys):
        rec = man["samples"][sid]
        if rec.get("status") != "done":
            clips.append({"id": sid, "scene": renders[rk]["scene"], "lux": s.lux, "model": s.model,
                          "error": rec.get("error")})
            continue
        info = json.loads((out / "samples" / sid / "sample.json").read_text())
        tm = rec.get("timing") or {}
        sample_s = float(rec.get("seconds") or 0.0)
        r = renders[rk]
        row = {"id": sid, "scene": r["scene"], "lux": s.lux, "model": s.model,
               "camera_s": info["n_intervals"] * info["interval_s"], "n_intervals": info["n_intervals"],
               "render_s": r["render_s"] / r["n_clips"], "simulate_s": tm.get("simulate", 0.0),
               "truth_s": tm.get("truth", 0.0), "io_s": tm.get("read", 0.0) + tm.get("write", 0.0),
               "read_s": tm.get("read", 0.0), "write_s": tm.get("write", 0.0), "sample_s": sample_s}
        row["other_s"] = sample_s - row["simulate_s"] - row["truth_s"] - row["io_s"]
        row["clip_s"] = row["render_s"] + sample_s
        clips.append(row)
    for r in renders.values():
        ts = r["times_s"]
        pick = [ts[round(i * (len(ts) - 1) / max(bare_calls - 1, 1))] for i in range(bare_calls)]
        log(f"bare launch: {r['scene']} at {r['spp']} spp, {r['height']} x {r['width']}, {bare_calls} calls")
        b = bare_launch(r.pop("sample"), r["spp"], pick, seed=12345, warm=bare_warm)
        r["bare"] = b
        px = r["spp"] * r["height"] * r["width"]
        r["job_samples_per_s"] = px * r["rendered"] / r["render_s"] if r["render_s"] > 0 else None
        kf = float(r["stages_s"].get("keyframes", 0.0))
        r["keyframes_samples_per_s"] = px * r["rendered"] / kf if kf > 0 else None
        del r["times_s"]
    made = [c for c in clips if "error" not in c]
    camera_s = sum(c["camera_s"] for c in made)
    return {"wall_s": wall_s, "camera_s": camera_s, "numba_warm_s": numba_s,
            "camera_s_per_hour": camera_s / wall_s * 3600 if wall_s > 0 else None,
            "n_samples": res.n_samples, "n_done": res.n_done, "n_made": res.n_made, "failed": res.failed,
            "renders": list(renders.values()), "clips": clips,
            "renders_s": sum(r["render_s"] for r in renders.values()),
            "samples_s": sum(c["sample_s"] for c in made),
            "load_before": load_before, "load_after": load_after, "load_end": _load()}


def _pct(x: float, whole: float) -> str:
    return f"{100 * x / whole:.0f} %" if whole > 0 else ""


def write_md(path: Path, res: dict) -> Path:
    """The report: header (command, date, machine, commit, load), the throughput, per clip, per render."""
    m = res["machine"]
    mach = f"{m['cpu'] or 'CPU'}, {m['cores']} cores" + (f"; GPU {m['gpu']}" if m.get("gpu") else "")
    if res.get("device"):
        mach += f" ({res['device']})"
    rs = res["renders"]
    variants = sorted({f"{r['variant']}, {r['launch']} launch" for r in rs})
    h, w = (rs[0]["height"], rs[0]["width"]) if rs else ("?", "?")
    lines = [
        "# Dataset throughput (`benchmarks/dataset.py`)", "",
        f"- command: `{res['command']}`",
        f"- date: {res['date']}; commit {res['commit']}",
        f"- machine: {mach}",
        f"- render: {'; '.join(variants)}",
        f"- load average (1, 5, 15 min): before {res['load_before']}, after the dataset {res['load_after']}, "
        f"after the bare launches {res['load_end']}",
        f"- spec: `{json.dumps(res['spec'], sort_keys=True)}`", "",
        f"**{_fmt(res['camera_s_per_hour'])} camera-seconds of spikes plus ground truth per hour** at {h} x {w} "
        f"pixels: {res['n_made']} clip(s) made ({res['n_done']} of {res['n_samples']} done), "
        f"{_fmt(res['camera_s'], 3)} camera-seconds in {_fmt(res['wall_s'])} s of `build_dataset` "
        f"(renders {_fmt(res['renders_s'])} s, samples {_fmt(res['samples_s'])} s, the rest "
        f"{_fmt(res['wall_s'] - res['renders_s'] - res['samples_s'])} s: planning, checks, manifest, summary).",
        "", (f"The spike models' numba kernels were compiled or loaded from numba's cache before the timed run "
             f"({_fmt(res['numba_warm_s'])} s, not in the figure)." if res.get("numba_warm_s") is not None else
             "Cold (`--cold`): the first clip's simulate includes compiling or loading the numba kernels."),
        "", "## Per clip", "",
        "A clip's render is its share of the render it reuses (every lux of a scene shares one render); "
        "IO = reading the frames back + writing the sample's files; other = the rest of the sample task "
        "(imports, the profile). The dataset makes no preview. Seconds (% of the clip).", "",
        "| scene | lux | model | intervals | render | simulate | truth | IO (read + write) | other | clip s |",
        "|---|---|---|---|---|---|---|---|---|---|"]
    for c in res["clips"]:
        if "error" in c:
            lines.append(f"| {c['scene']} | {_fmt(c['lux'])} | {c['model']} | failed: {c['error']} | | | | | | |")
            continue
        cs = c["clip_s"]

        def cell(x, cs=cs):
            return f"{x:.3f} ({_pct(x, cs)})"
        lines.append(f"| {c['scene']} | {_fmt(c['lux'])} | {c['model']} | {c['n_intervals']} | {cell(c['render_s'])} "
                     f"| {cell(c['simulate_s'])} | {cell(c['truth_s'])} | {c['io_s']:.3f} ({_pct(c['io_s'], cs)}; "
                     f"{c['read_s']:.3f} + {c['write_s']:.3f}) | {cell(c['other_s'])} | {cs:.3f} |")
    lines += ["", "## Per render, against a bare launch", "",
              "Stages of the render job in seconds (its `frames.json`): start (folder and launch checks), load "
              "(the scene into Mitsuba), meter (the light meter), pilot (the noise budget's pilot renders), "
              "keyframes (rendered, checked, written). Samples/s = spp x H x W x keyframes rendered / seconds, "
              "of the whole render and of its keyframes stage; the bare launch: `SceneRenderer.render_raw` of "
              "the same scene at the same spp and size, median of the timed calls after untimed warm-up calls. "
              "The first render's start includes importing Mitsuba.", "",
              "| scene | H x W | spp | keyframes | start | load | meter | pilot | keyframes s | render s "
              "| job samples/s | keyframes samples/s | bare launch samples/s (median ms) | job / bare "
              "| keyframes / bare |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rs:
        st = r["stages_s"]
        b = r["bare"]

        def ratio(x, b=b):
            return _fmt(x / b["samples_per_s"]) if x else ""
        lines.append(
            f"| {r['scene']} | {r['height']} x {r['width']} | {r['spp']} | {r['rendered']} | "
            + " | ".join(_fmt(st.get(k), 3) for k in ("start", "load", "meter", "pilot", "keyframes"))
            + f" | {_fmt(r['render_s'], 3)} | {_fmt(r['job_samples_per_s'])} | {_fmt(r['keyframes_samples_per_s'])} "
            f"| {_fmt(b['samples_per_s'])} ({1e3 * b['median_s']:.2f}) | {ratio(r['job_samples_per_s'])} "
            f"| {ratio(r['keyframes_samples_per_s'])} |")
    lines += ["", "Figures of one run on one machine; on a shared machine compare the rows of one run. Module "
              "docstring: what each figure counts.", ""]
    path.write_text("\n".join(lines))
    return path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="Writes dataset.md and dataset.json in --out (overwritten).")
    ap.add_argument("--spec", default=None, help="a dataset spec (YAML/JSON) instead of the default one")
    ap.add_argument("--out", default=str(HERE / "results"), help="folder of the report (default benchmarks/results)")
    ap.add_argument("--device", default="", help="a note on the machine, printed beside the figures "
                    "(the render takes the variant it picks itself; the report names it)")
    ap.add_argument("--scenes", nargs="+", default=["translating_object", "rotating_disk"],
                    help="default spec: bundled scenes (default translating_object rotating_disk)")
    ap.add_argument("--lux", type=float, nargs="+", default=[5.0, 50.0], help="default spec: lux (default 5 50)")
    ap.add_argument("--duration-s", type=float, default=0.02, help="default spec: clip length [s] (default 0.02)")
    ap.add_argument("--window", type=int, nargs=2, default=[16, 24], metavar=("H", "W"),
                    help="default spec: a centred window of the 250 x 400 sensor [pixels] (default 16 24)")
    ap.add_argument("--bare-calls", type=int, default=10, help="timed bare launches per render (default 10)")
    ap.add_argument("--bare-warm", type=int, default=3, help="untimed bare launches first (default 3)")
    ap.add_argument("--cold", action="store_true", help="no numba warm-up before the timed run: the first "
                    "clip's simulate includes compiling (or loading from numba's cache) the spike kernels")
    ap.add_argument("--work", default=None, help="where the dataset is built (default: a temporary folder)")
    ap.add_argument("--keep", action="store_true", help="keep the dataset folder")
    a = ap.parse_args(argv)
    if a.bare_calls < 1 or a.bare_warm < 1:
        ap.error("--bare-calls and --bare-warm: at least 1")
    h, w = a.window
    if not (0 < h <= SENSOR_HW[0] and 0 < w <= SENSOR_HW[1]):
        ap.error(f"--window: H in 1..{SENSOR_HW[0]} and W in 1..{SENSOR_HW[1]}")
    if a.spec is not None:
        if not Path(a.spec).is_file():
            ap.error(f"--spec: no file {a.spec}")
        spec = str(Path(a.spec).resolve())
    else:
        spec = default_spec(a.duration_s, (h, w), a.lux, a.scenes)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    work = Path(a.work) if a.work else Path(tempfile.mkdtemp(prefix="r2s-dsbench-"))
    work.mkdir(parents=True, exist_ok=True)
    if (work / "dataset").exists():
        shutil.rmtree(work / "dataset")  # a fresh dataset: a rerun must not resume a finished one
    cmd = "python benchmarks/dataset.py " + " ".join(argv if argv is not None else sys.argv[1:])
    from sensor.errors import InputError
    try:
        res = measure(spec, work, a.bare_calls, a.bare_warm, warm=not a.cold, log=lambda *x: print(*x, flush=True))
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    finally:
        if not a.keep:
            shutil.rmtree(work / "dataset", ignore_errors=True)
            if not a.work:
                shutil.rmtree(work, ignore_errors=True)
    res.update({"command": cmd.strip(), "date": time.strftime("%Y-%m-%d %H:%M %Z"), "machine": machine(),
                "device": a.device, "commit": commit(),
                "spec": spec if isinstance(spec, dict) else {"file": spec}})
    (out / "dataset.json").write_text(json.dumps(res, indent=1, default=str))
    md = write_md(out / "dataset.md", res)
    print(md.read_text())
    return 1 if res["failed"] else 0


if __name__ == "__main__":
    sys.exit(main())
