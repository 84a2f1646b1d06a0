"""render2spike GPU render benchmark: samples/s and frames/s of each Mitsuba variant on the same scenes.

One command per machine::

    python benchmarks/render_gpu.py                                          # every variant that works here
    python benchmarks/render_gpu.py --variants llvm_ad_spectral --out DIR     # the CPU rows only
    python benchmarks/render_gpu.py --cpu-ref OTHER/render_gpu.json --out DIR # and compare with another machine

Each point (variant x scene x resolution x spp) is ``benchmarks/render.py``'s
overhead measurement (section 1 there: blocks pipeline, bare, bare, pipeline;
fixed spp, adaptive refinement off) run in a fresh child process with
``RENDER2SPIKE_VARIANT`` set, so the JIT compilation and CUDA start-up stay out
of the timed blocks. Per point the report gives:

* **samples/s**: pixels x spp x frames / seconds of the bare blocks
  (``set_time`` + ``mi.render`` + ``np.asarray``: the copy to the host
  synchronises the GPU, so the time is the render's, not its launch's);
* **frames/s** of the pipeline (``render_scene``: render, Phi/E conversion,
  EXR write, journal) and its overhead over the bare render.

The ratio table divides the GPU variant's samples/s by a CPU variant's at the
same scene, resolution and spp: measured in the same run on the same machine
where that machine has a working CPU variant, and against ``--cpu-ref`` (an
earlier ``render_gpu.json`` of another machine, e.g. the 2-core CI-class one)
otherwise. Each row keeps the machine, the load average before and after, and
the date. The report is rewritten (atomically) after every point, so a run cut
short by ``--time-limit-s`` or a lost machine still leaves what it measured.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
sys.path.insert(1, str(ROOT))  # the checkout's packages, as the children get them (PYTHONPATH)
from tables import fmt as _fmt, machine  # noqa: E402,F401

SCENES = ("rotating_disk", "translating_object", "room_pan", "lambertian_plane")
GPU = "cuda_ad_spectral"
CPU = ("llvm_ad_spectral", "scalar_spectral")
FULL = ["camera.profile=vidar-default"]  # the full 250 x 400 sensor (the scenes' own profiles are windows)


def _load():
    return tuple(round(x, 2) for x in os.getloadavg())





def works(variant: str) -> tuple[bool, str]:
    """Whether ``variant`` renders here (the render stage's own child-process probe)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    code = ("import sys; from render2spike.render import backend as b; lib = b.find_libllvm(); "
            f"ok, msg = b.probe_variant({variant!r}, lib); print(ok); print(msg, file=sys.stderr)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=str(ROOT))
    ok = out.returncode == 0 and out.stdout.strip().endswith("True")
    return ok, (out.stderr.strip().splitlines() or [""])[-1][:300]


def auto_variant() -> str:
    """The variant the render stage picks on its own here (no ``RENDER2SPIKE_VARIANT``)."""
    env = {k: v for k, v in os.environ.items() if k != "RENDER2SPIKE_VARIANT"}
    env["PYTHONPATH"] = str(ROOT)
    out = subprocess.run([sys.executable, "-c", "from render2spike.render.backend import mitsuba; "
                          "print(mitsuba().variant())"], capture_output=True, text=True, env=env, cwd=str(ROOT))
    return out.stdout.strip().splitlines()[-1] if out.returncode == 0 and out.stdout.strip() else \
        f"failed: {(out.stderr.strip().splitlines() or ['?'])[-1][:200]}"


def point(variant: str, cfg: dict, timeout_s: float) -> dict:
    """One overhead point of ``benchmarks/render.py`` in a child with ``RENDER2SPIKE_VARIANT=variant``."""
    env = dict(os.environ, PYTHONPATH=str(ROOT), RENDER2SPIKE_VARIANT=variant)
    env.setdefault("PYTHONWARNINGS", "ignore")
    out = subprocess.run([sys.executable, str(HERE / "render.py"), "--one", "overhead", json.dumps(cfg)],
                         capture_output=True, text=True, cwd=str(ROOT), env=env, timeout=timeout_s)
    if out.returncode != 0:
        raise RuntimeError(out.stderr.strip()[-1500:])
    return json.loads(out.stdout.strip().splitlines()[-1])


def ratio_rows(rows: list[dict], ref_rows: list[dict], ref_name: str) -> list[dict]:
    """GPU samples/s over CPU samples/s for every (scene, resolution, spp) measured on both."""
    cpu = {}
    rank = {v: k for k, v in enumerate(CPU)}  # the fastest CPU variant measured: LLVM before scalar
    for r in sorted((r for r in ref_rows if r.get("ok") and r["variant"] != GPU),
                    key=lambda r: rank.get(r["variant"], len(CPU))):
        cpu.setdefault((r["scene"], r["resolution"], r["spp"]), r)
    out = []
    for r in rows:
        if r.get("ok") and r["variant"] == GPU:
            c = cpu.get((r["scene"], r["resolution"], r["spp"]))
            if c is not None:
                out.append({"scene": r["scene"], "resolution": r["resolution"], "spp": r["spp"], "against": ref_name,
                            "cpu_variant": c["variant"], "gpu_samples_per_s": r["samples_per_s"],
                            "cpu_samples_per_s": c["samples_per_s"],
                            "ratio": r["samples_per_s"] / c["samples_per_s"]})
    return out


def write_report(out_dir: Path, meta: dict, rows: list[dict], ref: dict | None) -> Path:
    from sensor.io.fileio import write_json_atomic, write_text_atomic
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out_dir / "render_gpu.json", {"meta": meta, "rows": rows})
    m = meta["machine"]
    L = ["# render2spike GPU render benchmark", "", f"Command: `{meta['command']}`  ", f"Date: {meta['date']}  ",
         f"Machine: {m['cpu']}, {m['cores']} cores; GPU: {m['gpu'] or 'none'}  ",
         f"Variant chosen automatically here: `{meta.get('auto_variant')}`  ",
         f"Variants that work here: {', '.join(meta['working']) or 'none'}"
         + ("; not working: " + "; ".join(f"{k} ({v})" for k, v in meta["not_working"].items())
            if meta["not_working"] else "") + "  ",
         f"Load average before / after: {meta['load_before']} / {meta.get('load_after')}", "",
         "Per point: blocks pipeline, bare, bare, pipeline (`benchmarks/render.py` section 1) in a fresh child "
         "process; samples/s from the bare blocks (`mi.render` + the copy to the host, which waits for the GPU); "
         "frames/s and overhead of the pipeline (`render_scene`: render, Phi/E, EXR write, journal) over those.", "",
         "Kernel compilation in the pipeline blocks (each job loads its own scene, whose render kernel is "
         "new: once per job) is taken out of their times and given as 'compile s' (per block).", "",
         "| variant | scene | resolution | spp | frames | samples/s | bare ms/frame | pipeline frames/s | overhead "
         "| compile s | load before-after |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if not r.get("ok"):
            L.append(f"| {r['variant']} | {r['scene']} | {r.get('size')} | {r['spp']} | failed: "
                     f"{r.get('error', '')[-160:].replace('|', '/').replace(chr(10), ' ')} ||||||")
            continue
        L.append(f"| {r['variant']} | {r['scene']} | {r['resolution']} | {r['spp']} | {r['frames']} | "
                 f"{_fmt(r['samples_per_s'])} | {_fmt(1e3 * r['bare_s_per_frame'], 3)} | "
                 f"{_fmt(1.0 / r['pipeline_s_per_frame'], 3)} | {_fmt(r['overhead_ratio'], 3)} | "
                 + (", ".join(f"{c:.2f}" for c in r["compile_s_per_block"]) if r.get("compile_s_per_block")
                    else "in the blocks") + f" | {r['load_before'][0]:.1f}-{r['load_after'][0]:.1f} |")
    ratios = ratio_rows(rows, rows, f"the same machine's CPU ({m['cpu']}, {m['cores']} cores, same run)")
    if ref is not None:
        rm = ref["meta"]["machine"]
        ratios += ratio_rows(rows, ref["rows"], f"{rm['cpu']}, {rm['cores']} cores ({ref['meta']['date']}, "
                                                f"load {ref['meta']['load_before'][0]:.1f}-"
                                                f"{(ref['meta'].get('load_after') or ref['meta']['load_before'])[0]:.1f})")
    if ratios:
        L += ["", "## GPU samples/s over CPU samples/s (same scene, resolution and spp)", "",
              "| scene | resolution | spp | GPU samples/s | CPU variant | CPU samples/s | GPU / CPU | CPU measured on |",
              "|---|---|---|---|---|---|---|---|"]
        for q in ratios:
            L.append(f"| {q['scene']} | {q['resolution']} | {q['spp']} | {_fmt(q['gpu_samples_per_s'])} | "
                     f"{q['cpu_variant']} | {_fmt(q['cpu_samples_per_s'])} | **{q['ratio']:.0f}x** | {q['against']} |")
        L += ["", "Goal (issue 12), on a GPU at least 20x the CPU's samples per second, per CPU measured against:", ""]
        for against in dict.fromkeys(q["against"] for q in ratios):
            qs = [q for q in ratios if q["against"] == against]
            parts = []
            for res in dict.fromkeys(q["resolution"] for q in qs):
                rs = [q["ratio"] for q in qs if q["resolution"] == res]
                parts.append(f"{res}: {min(rs):.1f}-{max(rs):.1f}x")
            lo = min(q["ratio"] for q in qs)
            L.append(f"- {against}: **met**, 20x or more at every point measured ({'; '.join(parts)})"
                     if lo >= 20 else
                     f"- {against}: **not met**, 20x or more at {sum(q['ratio'] >= 20 for q in qs)} of "
                     f"{len(qs)} points ({'; '.join(parts)})")
    write_text_atomic(out_dir / "render_gpu.md", "\n".join(L) + "\n")
    return out_dir / "render_gpu.md"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                 epilog="Writes render_gpu.md and render_gpu.json in --out after every point.")
    ap.add_argument("--variants", nargs="+", default=None,
                    help=f"variants to measure (default: those of {GPU}, {CPU[0]} that work here; "
                         f"{CPU[1]} only when named)")
    ap.add_argument("--scenes", nargs="+", default=list(SCENES))
    ap.add_argument("--sizes", nargs="+", default=["window", "full"], choices=["window", "full"])
    ap.add_argument("--spp", type=int, nargs="+", default=[16, 256], help="spp values (default 16 256)")
    ap.add_argument("--frames", type=int, default=16, help="frames per block (default 16)")
    ap.add_argument("--cpu-frames", type=int, default=None,
                    help="frames per block for CPU variants (default --frames; fewer keeps 2-core runs short)")
    ap.add_argument("--rounds", type=int, default=1, help="P B B P rounds per point (default 1)")
    ap.add_argument("--cpu-ref", help="render_gpu.json of another machine whose CPU rows to compare with")
    ap.add_argument("--time-limit-s", type=float, default=None,
                    help="start no new point after this many seconds (the report keeps what was measured)")
    ap.add_argument("--point-timeout-s", type=float, default=600.0, help="give up one point after this long")
    ap.add_argument("--out", default=str(HERE / "results"))
    ap.add_argument("--report-only", action="store_true",
                    help="rewrite render_gpu.md from the render_gpu.json in --out (e.g. with a newer --cpu-ref)")
    a = ap.parse_args(argv)
    for need, what in (((Path(a.out) / "render_gpu.json") if a.report_only else None, "--report-only reads"),
                       (Path(a.cpu_ref) if a.cpu_ref else None, "--cpu-ref names")):
        if need is not None and not need.is_file():
            ap.error(f"{what} {need}, which does not exist (a render_gpu.json written by an earlier run)")
    if a.report_only:
        d = json.loads((Path(a.out) / "render_gpu.json").read_text())
        ref = json.loads(Path(a.cpu_ref).read_text()) if a.cpu_ref else None
        print(f"wrote {write_report(Path(a.out), d['meta'], d['rows'], ref)}")
        return 0
    t_start = time.perf_counter()
    variants = a.variants or [GPU, CPU[0]]
    working, not_working = [], {}
    for v in variants:
        ok, msg = works(v)
        (working.append(v) if ok else not_working.__setitem__(v, msg))
        print(f"variant {v}: {'works' if ok else 'does not work: ' + msg}", flush=True)
    ref = json.loads(Path(a.cpu_ref).read_text()) if a.cpu_ref else None
    meta = {"command": "python benchmarks/render_gpu.py " + " ".join(argv if argv is not None else sys.argv[1:]),
            "date": time.strftime("%Y-%m-%d %H:%M:%S"), "machine": machine(), "load_before": _load(),
            "working": working, "not_working": not_working, "auto_variant": auto_variant()}
    print(f"auto-selected variant: {meta['auto_variant']}; machine {meta['machine']}", flush=True)
    rows: list[dict] = []
    out = Path(a.out)
    write_report(out, meta, rows, ref)
    for sc in a.scenes:
        for size in a.sizes:
            for spp in a.spp:
                for v in working:
                    if a.time_limit_s is not None and time.perf_counter() - t_start > a.time_limit_s:
                        print("time limit reached: no further points", flush=True)
                        meta["stopped_early"] = True
                        meta["load_after"] = _load()
                        write_report(out, meta, rows, ref)
                        return 0
                    n = a.frames if v == GPU or a.cpu_frames is None else a.cpu_frames
                    cfg = {"scene": sc, "spp": spp, "frames": n, "sets": FULL if size == "full" else [],
                           "rounds": a.rounds, "frames_dir": str(Path(os.environ.get("TMPDIR", "/tmp")))}
                    lb, t0 = _load(), time.perf_counter()
                    try:
                        r = point(v, cfg, a.point_timeout_s)
                        r.update(ok=True)
                    except (RuntimeError, subprocess.TimeoutExpired) as exc:
                        r = {"ok": False, "scene": sc, "spp": spp, "error": str(exc)}
                    r.update(variant=r.get("variant", v), size=size, load_before=lb, load_after=_load(),
                             date=time.strftime("%Y-%m-%d %H:%M:%S"), wall_s=time.perf_counter() - t0)
                    if r["ok"] and r["variant"] != v:
                        r.update(ok=False, error=f"asked for {v}, the child rendered with {r['variant']}")
                    rows.append(r)
                    meta["load_after"] = _load()
                    write_report(out, meta, rows, ref)
                    print(f"[{r['wall_s']:.0f} s] {v} {sc} {size} spp {spp}: " +
                          (f"{r['samples_per_s']:.3g} samples/s, pipeline {1 / r['pipeline_s_per_frame']:.1f} "
                           f"frames/s, overhead {r['overhead_ratio']:.2f}" if r["ok"] else "FAILED " +
                           r["error"][-300:]), flush=True)
    print(f"wrote {out / 'render_gpu.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
