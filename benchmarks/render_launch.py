"""render2spike launch benchmark: where the time of one small render launch goes, and whether freezing it helps.

On a GPU a 64 x 96 frame at 16 spp takes about as long as one at 256 spp: a fixed cost per launch
dominates (``docs/performance.md``, "Render"). This measures that cost, per frame, on the renderer's own
steps (``SceneRenderer.set_time``, then its render call, as ``SceneRenderer.launch`` makes them) for one
variant::

    python benchmarks/render_launch.py --variant cuda_ad_spectral --scene rotating_disk --spp 16 --out DIR

Per frame (medians over ``--frames`` frames, after ``--warm`` frames), in ms:

* ``update_ms``: ``set_time`` (the scene's parameters at this time, and for a moving scene the rebuild
  of its ray-tracing acceleration structure: on CUDA an OptiX build, whose device work is not in the
  kernel history below), split into ``pose_ms`` (this project's part: the motion matrices at this time
  and the writes of the moving objects' parameters) and ``params_update_ms`` (Mitsuba's
  ``SceneParameters.update``: the changed objects' ``parameters_changed``, which for a moving shape
  rebuilds the scene's acceleration structure);
* ``call_ms``: the render call until it returns. With ``--launch film`` (the default): Mitsuba tracing
  the integrator into Dr.Jit's IR, and the film's evaluation, which assembles and launches the kernel
  (Mitsuba evaluates the film inside ``render``, as the kernel history shows, even with
  ``evaluate=False``). With ``--launch frozen``: the recorded function's call (Dr.Jit walking its inputs,
  the scene among them, and replaying its kernels; the frames of its first sample count record it and
  are among the ``--warm`` ones);
* ``sync_ms``: waiting for the kernels and copying the result to the host (``np.asarray`` on the film;
  the frozen launch's ``channels``);
* from Dr.Jit's kernel history for the same frame: ``codegen_ms`` (assembling the kernel source and
  hashing it, host), ``backend_ms`` (compiling, ~0 on a cache hit) and ``exec_ms`` (the run time of
  the JIT kernels as the backend measured it: on CUDA the device time; on LLVM the worker threads',
  which run while the host goes on); ``other_kernels_ms``: the other entries' (memsets, reductions);
* ``trace_ms`` = call - codegen - backend: the host's own work of recording the render, the part
  ``drjit.freeze`` would skip on a replay (``set_time`` is outside it). Where ``sync_ms`` is about
  ``exec_ms`` (CUDA), a frame is update + trace + codegen + exec plus a copy.

Recording the kernel history costs each launch a little (1-10 % a launch, measured on the CPU), so ``wall_ms`` is a bit
above a bare loop's frame (``benchmarks/render_gpu.py``).

``--freeze`` also tries ``drjit.freeze`` on the render call, in a child process that is killed after
``--freeze-timeout-s`` (a recording that does not return loses nothing measured): whether it runs, its
frame time, and how far its films are from the unfrozen ones at the same seeds (on a GPU two unfrozen
renders already differ in their last bits: ``benchmarks/repro_check.py``).
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


#: the per-frame columns, in the table's order
KEYS = ("wall_ms", "update_ms", "pose_ms", "params_update_ms", "call_ms", "sync_ms", "trace_ms", "codegen_ms", "backend_ms", "exec_ms",
        "other_kernels_ms")


def frame_row(t0: float, t1: float, t2: float, t3: float, hist: list[dict], jit, params_update_s: float = 0.0) -> dict:
    """One frame's split (ms) from its four clock readings [s] (before ``set_time``, after it, after the render
    call, after the result is on the host), the kernel history entries it made (``jit``: the history's JIT
    kernel type; the other entries count as other kernels) and the seconds ``set_time`` spent in Mitsuba's
    ``SceneParameters.update`` (``params_update_s``; the rest of ``set_time`` is ``pose_ms``)."""
    k = [h for h in hist if h.get("type") == jit]
    o = [h for h in hist if h.get("type") != jit]
    row = {"wall_ms": 1e3 * (t3 - t0), "update_ms": 1e3 * (t1 - t0),
           "pose_ms": 1e3 * (t1 - t0 - params_update_s), "params_update_ms": 1e3 * params_update_s,
           "call_ms": 1e3 * (t2 - t1),
           "sync_ms": 1e3 * (t3 - t2),
           "codegen_ms": sum(float(h.get("codegen_time", 0.0)) for h in k),
           "backend_ms": sum(float(h.get("backend_time", 0.0)) for h in k),
           "exec_ms": sum(float(h.get("execution_time", 0.0)) for h in k),
           "other_kernels_ms": sum(float(h.get("execution_time", 0.0)) for h in o),
           "kernels": len(k), "cache_misses": sum(not h.get("cache_hit") for h in k)}
    row["trace_ms"] = row["call_ms"] - row["codegen_ms"] - row["backend_ms"]
    return row


def summarize(rows: list[dict], warm: int) -> dict:
    """Medians of each column over the frames after the first ``warm`` (which compile and fill caches)."""
    timed = rows[warm:]
    if not timed:
        raise ValueError(f"no timed frames: {len(rows)} frame(s), {warm} of them warm-up")
    return {k: float(np.median([r[k] for r in timed])) for k in timed[0]}


def _renderer(scene: str, sets: list[str], n: int, launch: str = "film"):
    from render2spike.render.renderer import SceneRenderer
    from render2spike.render.scene import load_scene
    rate = float(load_scene(scene, list(sets)).render["keyframe_rate_hz"])
    import inspect  # the launch asked for, where the code has a choice (older code had the film launch only)
    kw = {"launch": launch} if "launch" in inspect.signature(SceneRenderer).parameters else {}
    if launch != "film" and not kw:
        raise SystemExit(f"--launch {launch}: this version of render2spike has the film launch only")
    rnd = SceneRenderer(load_scene(scene, list(sets), duration_s=(n - 1) / rate), **kw)
    return rnd, [i / rate for i in range(n)]


class _TimedUpdate:
    """``SceneParameters.update`` of one renderer, timed: ``seconds`` is the time of the last call."""

    def __init__(self, params):
        self._update = params.update
        self.seconds = 0.0

    def __call__(self, *a, **k):
        t = time.perf_counter()
        try:
            return self._update(*a, **k)
        finally:
            self.seconds = time.perf_counter() - t


def measure(scene: str, spp: int, frames: int, warm: int, sets: list[str], launch: str = "film") -> dict:
    """One row: per-frame medians of the launch split (ms) for the variant this process renders with."""
    import drjit as dr
    rnd, times = _renderer(scene, sets, warm + frames, launch)
    frozen = getattr(rnd, "_frozen", None)
    if frozen is not None and len(rnd.launch_counts(spp)) > 1:  # this times one render call, the renderer's one launch
        raise SystemExit(f"--spp {spp}: the frozen launch takes it in {len(rnd.launch_counts(spp))} launches at "
                         f"{rnd.height} x {rnd.width} (render2spike.render.frozen.MAX_SAMPLES_PER_LAUNCH); this "
                         "script times one launch: ask for fewer samples per pixel")
    timed = _TimedUpdate(rnd.params)
    rnd.params.update = timed  # this renderer's only: set_time calls it once per moving frame
    was = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    rows = []
    try:
        dr.kernel_history()  # read = cleared
        for i, t_s in enumerate(times):
            timed.seconds = 0.0  # a static scene's set_time calls nothing
            t0 = time.perf_counter()
            rnd.set_time(t_s)
            t1 = time.perf_counter()
            img = rnd._render_call(1000 + i, spp)
            t2 = time.perf_counter()
            frozen.channels(img) if frozen is not None else np.asarray(img)
            t3 = time.perf_counter()
            rows.append(frame_row(t0, t1, t2, t3, dr.kernel_history(), dr.KernelType.JIT, timed.seconds))
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, was)
        del rnd.params.update
    med = summarize(rows, warm)
    return {"scene": scene, "resolution": f"{rnd.height}x{rnd.width}", "spp": spp, "variant": rnd.variant,
            "launch": "frozen" if frozen is not None else "film", "moving": len(getattr(rnd, "_moving", {})),
            "frames": frames, "warm": warm, "median": med,
            "samples_per_s": rnd.height * rnd.width * spp / (med["wall_ms"] / 1e3)}


def freeze_trial(scene: str, spp: int, frames: int, warm: int, sets: list[str]) -> dict:
    """``drjit.freeze`` on the render call (in this process: the parent runs it in a child): does it run, how
    fast, and how far its films are from the unfrozen ones at the same times and seeds."""
    import drjit as dr
    rnd, times = _renderer(scene, sets, warm + frames)
    mi = rnd.mi
    films = []
    for i, t_s in enumerate(times):
        rnd.set_time(t_s)
        films.append(np.array(rnd._render_call(1000 + i, spp)))

    @dr.freeze
    def frozen(scene_, sensor, seed):
        return scene_.integrator().render(scene_, sensor, seed=seed, spp=spp, develop=True, evaluate=False)

    walls, worst, equal = [], 0.0, 0
    try:
        for i, t_s in enumerate(times):
            rnd.set_time(t_s)
            t0 = time.perf_counter()
            with dr.suspend_grad():
                arr = np.asarray(frozen(rnd.mi_scene, rnd.sensor, mi.UInt32(1000 + i)))
            walls.append(time.perf_counter() - t0)
            ref = films[i].astype(np.float64)
            d = np.abs(arr - ref)
            worst = max(worst, float((d / np.maximum(np.abs(ref), np.finfo(np.float32).tiny)).max()))
            equal += bool(np.array_equal(arr, films[i]))
    except Exception as exc:  # noqa: BLE001 - the finding is the failure itself
        root = exc
        while root.__cause__ is not None:  # Dr.Jit chains its reasons: the innermost one says what failed
            root = root.__cause__
        msg = " ".join(str(root).split())
        return {"works": False, "frames_done": len(walls), "error": f"{type(root).__name__}: {msg[:400]}"}
    return {"works": True, "wall_ms_median": 1e3 * float(np.median(walls[warm:])), "frames": len(walls) - warm,
            "films_equal_unfrozen": equal, "max_rel_diff_vs_unfrozen": worst}


def _freeze_child(cfg: dict, timeout_s: float) -> dict:
    """:func:`freeze_trial` in a child process, killed after ``timeout_s``."""
    import subprocess
    try:
        out = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--freeze-child", json.dumps(cfg)],
                             capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return {"works": False, "error": f"no result within {timeout_s:g} s (process killed): the recording or a "
                                         "replay did not return"}
    lines = out.stdout.strip().splitlines()
    if out.returncode != 0 or not lines:
        tail = " ".join(out.stderr.strip().splitlines()[-3:])
        return {"works": False, "error": f"the child exited with {out.returncode}: {tail[-400:]}"}
    return json.loads(lines[-1])


def _fmt(v, spec=".3f"):
    return "-" if v is None else format(v, spec)


def write_md(out: Path, rows: list[dict]) -> Path:
    """The report: one table line per row (columns absent from older rows as '-')."""
    from sensor.io.fileio import write_text_atomic
    lines = ["# Where one render launch's time goes", "",
             "Medians per frame in ms (`benchmarks/render_launch.py`; columns in its docstring; '-': not "
             "measured by the version of the script that made the row).", "",
             "| date | machine | load before/after | variant | launch | scene | size | spp | " + " | ".join(KEYS) +
             " | kernels | samples/s | freeze |", "|" + "---|" * (len(KEYS) + 11)]
    for r in rows:
        m = r["median"]
        fz = r.get("freeze")
        if fz is None:
            fzs = "-"
        elif fz["works"]:
            fzs = f"works: {fz['wall_ms_median']:.2f} ms, {fz['films_equal_unfrozen']}/{fz['frames']} films equal"
            if "max_rel_diff_vs_unfrozen" in fz:
                fzs += f", max rel. diff. {fz['max_rel_diff_vs_unfrozen']:.2g}"
        else:
            fzs = f"fails: {fz['error'][:160]}"
        load = " / ".join(", ".join(f"{x:.2f}" for x in r[k]) for k in ("load_before", "load_after"))
        lines.append(f"| {r['date']} | {r['machine']} | {load} | {r['variant']} | {r.get('launch', 'film')} | "
                     f"{r['scene']} | {r['resolution']} | "
                     f"{r['spp']} | " + " | ".join(_fmt(m.get(k)) for k in KEYS) +
                     f" | {m['kernels']:.0f} | {r['samples_per_s']:.3g} | {fzs} |")
    return write_text_atomic(out / "render_launch.md", "\n".join(lines) + "\n")


def _read_rows(js: Path, ap) -> list[dict]:
    try:
        rows = json.loads(js.read_text())
        if not isinstance(rows, list) or not all(isinstance(r, dict) and "median" in r for r in rows):
            raise ValueError("expected a list of rows, each with a 'median' entry")
        return rows
    except (OSError, ValueError) as exc:
        ap.error(f"{js}: not a render_launch.json written by this script ({exc}); move it away or choose "
                 "another --out")


def main(argv=None):
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["--freeze-child"]:  # internal: the parent's freeze trial
        cfg = json.loads(argv[1])
        import warnings
        warnings.filterwarnings("ignore")
        print(json.dumps(freeze_trial(cfg["scene"], cfg["spp"], cfg["frames"], cfg["warm"], cfg["sets"])))
        return 0
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                 epilog="Appends a row to render_launch.json in --out and rewrites render_launch.md.")
    ap.add_argument("--variant", default=None,
                    help="Mitsuba variant (sets RENDER2SPIKE_VARIANT for this process; default: the automatic choice)")
    ap.add_argument("--scene", default="rotating_disk", help="bundled scene name or scene YAML (default rotating_disk)")
    ap.add_argument("--full", action="store_true", help="the full 250 x 400 sensor (default: the scene's window)")
    ap.add_argument("--spp", type=int, nargs="+", default=[16], help="samples per pixel (default 16)")
    ap.add_argument("--frames", type=int, default=40, help="timed frames (default 40)")
    ap.add_argument("--warm", type=int, default=5, help="untimed frames first (default 5)")
    ap.add_argument("--launch", choices=("film", "frozen"), default="film",
                    help="the launch split up: the integrator's render into the film (default), or the frozen "
                         "launch (render2spike.render.frozen) that the renderer takes by default on LLVM and CUDA")
    ap.add_argument("--freeze", action="store_true", help="also try drjit.freeze on the film launch's render call "
                    "(in a child; with --launch film only)")
    ap.add_argument("--freeze-timeout-s", type=float, default=60.0, help="kill the freeze trial after this long")
    ap.add_argument("--out", default=str(HERE / "results"))
    ap.add_argument("--report-only", action="store_true", help="rewrite render_launch.md from the json in --out")
    a = ap.parse_args(argv)
    js = Path(a.out) / "render_launch.json"
    if a.report_only:
        if not js.is_file():
            ap.error(f"--report-only reads {js}, which does not exist (a render_launch.json written by an earlier run)")
        print(f"wrote {write_md(Path(a.out), _read_rows(js, ap))}")
        return 0
    if a.freeze and a.launch != "film":
        ap.error("--freeze tries drjit.freeze on the film launch's render call; the frozen launch is one already "
                 "(drop --freeze, or use --launch film)")
    if a.frames < 1 or a.warm < 1 or min(a.spp) < 1:
        ap.error(f"--frames, --warm and every --spp must be >= 1 (got {a.frames}, {a.warm}, {a.spp})")
    if Path(a.scene).is_file():
        a.scene = str(Path(a.scene).resolve())
    if a.variant:
        os.environ["RENDER2SPIKE_VARIANT"] = a.variant
    import warnings
    warnings.filterwarnings("ignore")
    from render_gpu import machine
    mach = machine()
    mline = f"{mach['cpu']}, {mach['cores']} cores" + (f"; GPU {mach['gpu']}" if mach["gpu"] else "")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    from sensor.io.fileio import write_json_atomic
    rows = _read_rows(js, ap) if js.is_file() else []
    sets = ["camera.profile=vidar-default"] if a.full else []
    command = "python benchmarks/render_launch.py " + " ".join(argv)
    for spp in a.spp:
        lb = _load_avg()
        r = measure(a.scene, spp, a.frames, a.warm, sets, a.launch)
        r.update(date=time.strftime("%Y-%m-%d %H:%M:%S"), machine=mline, load_before=lb,
                 load_after=_load_avg(), command=command)
        rows.append(r)
        write_json_atomic(js, rows)  # before the freeze trial: what was measured is kept whatever it does
        write_md(out, rows)
        m = r["median"]
        print(f"{r['variant']} {r['launch']} {r['scene']} {r['resolution']} spp {spp}: wall {m['wall_ms']:.2f} ms "
              f"= update {m['update_ms']:.2f} (pose {m['pose_ms']:.3f} + Mitsuba's update {m['params_update_ms']:.2f})"
              f" + call {m['call_ms']:.2f} (trace {m['trace_ms']:.2f} + codegen "
              f"{m['codegen_ms']:.2f} + backend {m['backend_ms']:.2f}) + sync {m['sync_ms']:.2f}; JIT kernels ran "
              f"{m['exec_ms']:.2f}, others {m['other_kernels_ms']:.2f}; load {r['load_before']}", flush=True)
        if a.freeze:
            r["freeze"] = _freeze_child({"scene": a.scene, "spp": spp, "frames": a.frames, "warm": a.warm,
                                         "sets": sets}, a.freeze_timeout_s)
            write_json_atomic(js, rows)
            write_md(out, rows)
            print(f"  freeze: {r['freeze']}", flush=True)
    print(f"wrote {out / 'render_launch.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
