"""render2spike launch benchmark: where the time of one small render launch goes, and whether freezing it helps.

On a GPU a 64 x 96 frame at 16 spp takes about as long as one at 256 spp: a fixed cost per launch
dominates (``docs/performance.md``, "GPU"). This measures that cost, per frame, on the renderer's own
render call (``SceneRenderer.launch``: ``set_time`` + the integrator's ``render``) for one variant::

    python benchmarks/render_launch.py --variant cuda_ad_spectral --scene rotating_disk --spp 16 --out DIR

Per frame (medians over ``--frames`` frames, after ``--warm`` frames), in ms:

* ``call_ms``: host time until the render call returns (scene update, Mitsuba tracing the integrator into
  Dr.Jit's IR, and the film's evaluation, which assembles and launches the kernel: Mitsuba evaluates the
  film inside ``render``, as the kernel history shows, even with ``evaluate=False``);
* ``sync_ms``: host time of ``np.asarray`` on the film (waiting for the kernel, copying the film to the host);
* from Dr.Jit's kernel history for the same frame: ``codegen_ms`` (assembling the kernel source and
  hashing it, host), ``backend_ms`` (compiling, ~0 on a cache hit), ``exec_ms`` (the kernels' run time as
  the backend measured it: on CUDA the device time; on LLVM the worker threads', which run while the host
  goes on) and the number of kernels;
* ``trace_ms`` = call - codegen - backend: the host's own per-launch work of recording the render (the part
  ``drjit.freeze`` would skip). Where ``sync_ms`` is about ``exec_ms`` (CUDA), the frame is
  ``trace + codegen + exec`` plus a copy.

``--freeze`` also tries ``drjit.freeze`` on the same call (record once, replay without tracing): whether
it runs, its frame time, and whether its films equal the unfrozen ones at the same seeds bit for bit.
Writes ``render_launch.json`` (appending one row per run) and ``render_launch.md`` in ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(1, str(HERE.parent))


def _load_avg():
    return tuple(round(x, 2) for x in os.getloadavg())


def measure(scene: str, spp: int, frames: int, warm: int, sets: list[str], freeze: bool) -> dict:
    """One row: per-frame medians of the launch split (ms) for the variant this process renders with."""
    import drjit as dr

    from render2spike.render.renderer import SceneRenderer
    from render2spike.render.scene import load_scene
    sc0 = load_scene(scene, list(sets))
    rate = float(sc0.render["keyframe_rate_hz"])
    n = warm + frames
    sc = load_scene(scene, list(sets), duration_s=(n - 1) / rate)
    rnd = SceneRenderer(sc)
    times = [i / rate for i in range(n)]
    was = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    rows = []
    films = []
    try:
        dr.kernel_history()
        for i, t_s in enumerate(times):
            t0 = time.perf_counter()
            img = rnd.launch(t_s, 1000 + i, spp)
            t1 = time.perf_counter()
            arr = np.asarray(img)
            t2 = time.perf_counter()
            hist = [h for h in dr.kernel_history() if h.get("type") == dr.KernelType.JIT]
            films.append(arr.copy())
            if i < warm:
                continue
            row = {"wall_ms": 1e3 * (t2 - t0), "call_ms": 1e3 * (t1 - t0), "sync_ms": 1e3 * (t2 - t1),
                   "codegen_ms": sum(float(h.get("codegen_time", 0.0)) for h in hist),
                   "backend_ms": sum(float(h.get("backend_time", 0.0)) for h in hist),
                   "exec_ms": sum(float(h.get("execution_time", 0.0)) for h in hist),
                   "kernels": len(hist), "cache_misses": sum(not h.get("cache_hit") for h in hist)}
            row["trace_ms"] = row["call_ms"] - row["codegen_ms"] - row["backend_ms"]
            rows.append(row)
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, was)
    med = {k: float(np.median([r[k] for r in rows])) for k in rows[0]}
    out = {"scene": scene, "resolution": f"{rnd.height}x{rnd.width}", "spp": spp, "variant": rnd.variant,
           "frames": frames, "warm": warm, "median": med,
           "samples_per_s": rnd.height * rnd.width * spp / (med["wall_ms"] / 1e3)}
    if freeze:
        out["freeze"] = _try_freeze(rnd, times, spp, films, warm)
    return out


def _try_freeze(rnd, times, spp, films, warm) -> dict:
    """``drjit.freeze`` on the render call: does it run, how fast, and are its films the unfrozen ones."""
    import drjit as dr
    mi = rnd.mi

    @dr.freeze
    def frozen(scene, sensor, seed):
        return scene.integrator().render(scene, sensor, seed=seed, spp=spp, develop=True, evaluate=False)

    walls, same = [], []
    try:
        for i, t_s in enumerate(times):
            rnd.set_time(t_s)
            t0 = time.perf_counter()
            with dr.suspend_grad():
                arr = np.asarray(frozen(rnd.mi_scene, rnd.sensor, mi.UInt32(1000 + i)))
            walls.append(time.perf_counter() - t0)
            same.append(bool(np.array_equal(arr, films[i])))
    except Exception as exc:  # noqa: BLE001 - the finding is the failure itself
        root = exc
        while root.__cause__ is not None:  # Dr.Jit chains its reasons: the innermost one says what failed
            root = root.__cause__
        msg = " ".join(str(root).split())
        return {"works": False, "frames_done": len(walls), "error": f"{type(root).__name__}: {msg[:400]}"}
    return {"works": True, "wall_ms_median": 1e3 * float(np.median(walls[warm:] or walls)),
            "films_equal_unfrozen": int(sum(same)), "frames": len(same)}


def write_md(out: Path, rows: list[dict]) -> Path:
    from sensor.fileio import write_text_atomic
    keys = ("wall_ms", "call_ms", "sync_ms", "trace_ms", "codegen_ms", "backend_ms", "exec_ms")
    lines = ["# Where one render launch's time goes", "",
             "Medians per frame in ms (`benchmarks/render_launch.py`; columns in its docstring).", "",
             "| date | machine | load before/after | variant | scene | size | spp | " + " | ".join(keys) +
             " | kernels | samples/s | freeze |", "|" + "---|" * (len(keys) + 10)]
    for r in rows:
        m = r["median"]
        fz = r.get("freeze")
        fzs = "-" if fz is None else (f"works: {fz['wall_ms_median']:.2f} ms, {fz['films_equal_unfrozen']}/"
                                      f"{fz['frames']} films equal" if fz["works"] else
                                      f"fails: {fz['error'][:160]}")
        load = " / ".join(", ".join(f"{x:.2f}" for x in r[k]) for k in ("load_before", "load_after"))
        lines.append(f"| {r['date']} | {r['machine']} | {load} | {r['variant']} | "
                     f"{r['scene']} | {r['resolution']} | {r['spp']} | " +
                     " | ".join(f"{m[k]:.3f}" for k in keys) + f" | {m['kernels']:.0f} | {r['samples_per_s']:.3g} | "
                     f"{fzs} |")
    return write_text_atomic(out / "render_launch.md", "\n".join(lines) + "\n")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                 epilog="Appends a row to render_launch.json in --out and rewrites render_launch.md.")
    ap.add_argument("--variant", default=None,
                    help="Mitsuba variant (sets RENDER2SPIKE_VARIANT for this process; default: the automatic choice)")
    ap.add_argument("--scene", default="rotating_disk")
    ap.add_argument("--full", action="store_true", help="the full 250 x 400 sensor (default: the scene's window)")
    ap.add_argument("--spp", type=int, nargs="+", default=[16])
    ap.add_argument("--frames", type=int, default=40, help="timed frames (default 40)")
    ap.add_argument("--warm", type=int, default=5, help="untimed frames first (default 5)")
    ap.add_argument("--freeze", action="store_true", help="also try drjit.freeze on the render call")
    ap.add_argument("--out", default=str(HERE / "results" / "render_launch"))
    ap.add_argument("--report-only", action="store_true", help="rewrite render_launch.md from the json in --out")
    a = ap.parse_args(argv)
    js = Path(a.out) / "render_launch.json"
    if a.report_only:
        if not js.is_file():
            ap.error(f"--report-only reads {js}, which does not exist (a render_launch.json written by an earlier run)")
        print(f"wrote {write_md(Path(a.out), json.loads(js.read_text()))}")
        return 0
    if a.frames < 1 or a.warm < 1:
        ap.error(f"--frames and --warm must be >= 1 (got {a.frames}, {a.warm})")
    if a.variant:
        os.environ["RENDER2SPIKE_VARIANT"] = a.variant
    import warnings
    warnings.filterwarnings("ignore")
    from render_gpu import machine
    mach = machine()
    mline = f"{mach['cpu']}, {mach['cores']} cores" + (f"; GPU {mach['gpu']}" if mach["gpu"] else "")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    from sensor.fileio import write_json_atomic
    rows = json.loads(js.read_text()) if js.is_file() else []
    sets = ["camera.profile=vidar-default"] if a.full else []
    for spp in a.spp:
        lb = _load_avg()
        r = measure(a.scene, spp, a.frames, a.warm, sets, a.freeze)
        r.update(date=time.strftime("%Y-%m-%d %H:%M:%S"), machine=mline, load_before=lb,
                 load_after=_load_avg(), command="python benchmarks/render_launch.py " +
                 " ".join(argv if argv is not None else sys.argv[1:]))
        rows.append(r)
        write_json_atomic(js, rows)
        write_md(out, rows)
        m = r["median"]
        print(f"{r['variant']} {r['scene']} {r['resolution']} spp {spp}: wall {m['wall_ms']:.2f} ms = call "
              f"{m['call_ms']:.2f} (trace {m['trace_ms']:.2f} + codegen {m['codegen_ms']:.2f} + backend "
              f"{m['backend_ms']:.2f}) + sync {m['sync_ms']:.2f}; kernels ran {m['exec_ms']:.2f}; load "
              f"{r['load_before']}; freeze: {r.get('freeze')}", flush=True)
    print(f"wrote {out / 'render_launch.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
