"""render2spike render benchmark: samples/s, pipeline overhead, keyframes per camera-second, noise, wait.

One command::

    python benchmarks/render.py                       # this code only
    python benchmarks/render.py --old /tmp/perf-old   # and an older checkout, in the same run
    python benchmarks/render.py --quick               # smoke run (one scene, few frames)

writes ``benchmarks/results/render.md`` and ``render.json`` (atomically). Every
measurement runs in a fresh subprocess (its own JIT and memory); ``--old PATH``
runs the same measurement with ``PYTHONPATH=PATH`` (e.g. a ``git worktree add
/tmp/perf-old main`` checkout), so old and new are compared in one run. The
load average is recorded before and after.

Sections
--------
0. **Frame write**: ``sensor.io.frames.write_frame`` (its own EXR encoder) against
   the same frame written through the OpenEXR binding, at 64 x 96 and 250 x 400.
1. **Throughput and overhead** (per bundled scene, at its 64 x 96 window and at
   the full 250 x 400 sensor; fixed spp, adaptive refinement off): the pipeline
   (``render_scene``: frame render, Phi/E conversion, EXR write, state file,
   metric) per frame against a bare ``mi.render`` + ``np.asarray`` of the same
   loaded scene at the same times and spp, in blocks ordered pipeline, bare,
   bare, pipeline (a linearly drifting load cancels; JIT compilation is in
   neither). Samples/s = pixels x spp / bare seconds. Between the two bare
   blocks, two blocks of the renderer's own render call (the integrator without
   ``mi.render``'s differentiable wrapper): 'vs direct', the strongest baseline.
   The pipeline writes its frames under ``--frames-dir`` (default
   ``benchmarks/.scratch``); each point first probes the file system's cost of
   creating a frame-sized file there, reported beside the row.
2. **Keyframes per camera-second** (per scene at its window, 1 and 50 lux; also
   5 lux on the rotating disk;
   each version's budget spp with the scene's own ``max_spp``, the scene's own
   adaptive settings, a shortened clip).
3. **Render-noise ratio** achieved at 1, 5 and 50 lux (rotating disk, window,
   budget spp with the default ``max_spp`` 1024): the budget's spp and the ratio
   measured on independent pairs at three times other than the pilot's.
4. **Wait for one camera-second** (rotating disk at full resolution, 1, 5 and
   50 lux, budget spp): setup (load + light level + pilot) + keyframes per
   camera-second (section 2, same lux) x the measured seconds per frame
   (``--wait-frames`` frames rendered the way each version renders them:
   one launch plus 1/``VERIFY_EVERY`` of a verification launch now; two halves before).
   **Extrapolated** from those frames.

Every section renders with the film launch (``launch="film"``, :func:`_film`), so that its figures
stay comparable to a bare ``mi.render``; the default launch (``auto``: the frozen
launch on LLVM and CUDA) is timed against it by ``benchmarks/render_frozen.py``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
from tables import fmt as _fmt  # noqa: E402

SCENES = ("rotating_disk", "translating_object", "room_pan", "lambertian_plane")
LUX = (1.0, 5.0, 50.0)


# ------------------------------------------------------------------------------------------ measurements
def _quiet():
    import warnings
    warnings.filterwarnings("ignore")


def _film():
    """``{"launch": "film"}`` where the code measured has a choice of launch (the default is
    ``auto``, the frozen launch on LLVM and CUDA), else ``{}``: this benchmark times Mitsuba's own render,
    its bare blocks are ``mi.render`` of the pipeline's loaded scene, and ``--old`` runs older code that
    has no ``launch``. The frozen launch, and the job with it against the same bare launch:
    ``benchmarks/render_frozen.py --pipeline``."""
    import inspect
    from render2spike.render.renderer import SceneRenderer
    return {"launch": "film"} if "launch" in inspect.signature(SceneRenderer).parameters else {}


def _load(name, sets=(), lux=None, duration_s=None):
    from render2spike.render.scene import load_scene
    return load_scene(name, list(sets), lux=lux, duration_s=duration_s)


def m_overhead(cfg):
    """Section 1 in this process: pipeline vs bare mi.render on the same scene, blocks in the order P B B P.

    A pipeline block is one ``render_scene`` of ``frames`` frames (fixed spp, adaptive off), timed from its
    first frame's render to its return (so the pilot and loading are out, the frame writes, journal, manifest
    and the verification launches are in). A bare block renders the same times at the same spp with
    ``set_time`` + ``mi.render`` + ``np.asarray`` on the first pipeline's loaded scene, back to back. The
    order pipeline, bare, bare, pipeline (``rounds`` times, default 2) cancels a load that drifts linearly;
    overhead = sum of pipeline time / sum of bare time. (Frame-by-frame interleaving, used before, cannot be fair to a background
    writer: its writes would overlap the bare render, or lose their overlap with the pipeline's own.)
    Kernel compilation inside a pipeline block (its scene is loaded anew: a new kernel hash, once per job)
    is read from Dr.Jit's kernel history, taken out of the block's wall and CPU time, and returned as
    ``compile_s_per_block`` with ``kernels_compiled_per_block``; the bare blocks run warmed kernels.
    """
    import drjit as dr

    from render2spike.render import renderer as rmod
    from render2spike.render.job import render_scene
    _quiet()
    n, spp = int(cfg["frames"]), int(cfg["spp"])
    sets = [f"render.spp={spp}", "render.adaptive.enabled=false"] + list(cfg.get("sets", []))
    sc0 = _load(cfg["scene"], sets)
    rate = float(sc0.render["keyframe_rate_hz"])
    sc = _load(cfg["scene"], sets, duration_s=(n - 1) / rate)
    orig = rmod.SceneRenderer.render_frame

    def pipeline():
        st = {"times": []}

        def wrapped(self, t_s, *a, **k):
            if not st["times"]:
                dr.kernel_history()  # read = cleared: the block's own kernels from here on
                st["t_first"], st["rnd"], st["c_first"] = time.perf_counter(), self, time.process_time()
                st["launches0"] = getattr(self, "n_launches", None)  # counted by the renderer (newer code)
            st["times"].append(t_s)
            st["verify"] = st.get("verify", 0) + bool(k.get("variance", True))  # frames with a second launch
            return orig(self, t_s, *a, **k)
        rmod.SceneRenderer.render_frame = wrapped
        try:
            d = point_dir / f"block{next(block_no)}"
            t_all = time.perf_counter()
            res = render_scene(sc, d, progress=False, log=lambda *a: None, **_film())
            t_end, c_end = time.perf_counter(), time.process_time()
        finally:
            rmod.SceneRenderer.render_frame = orig
            hist = dr.kernel_history()
        # Each render_scene loads its own Mitsuba scene, whose render kernel has a new hash (the scene's
        # objects are part of it): the first frame at an spp the pilot did not use compiles it (LLVM
        # 0.2-0.6 s, CUDA 0.7-1.0 s), once per job, unless Dr.Jit's disk cache holds it from an earlier
        # process. The bare blocks reuse a warmed kernel, so that compile time, as Dr.Jit reports it, is
        # taken out of the block and reported on its own, with the number of kernels compiled (a pipeline
        # that compiled every frame would show it there).
        missed = [h for h in hist if h.get("type") == dr.KernelType.JIT and not h.get("cache_hit")]
        compile_s = sum(float(h.get("backend_time", 0.0)) for h in missed) / 1e3
        st["compile_s"], st["compiled"] = compile_s, len(missed)
        t_end -= compile_s
        CPU["P"].append(c_end - st["c_first"] - compile_s)
        if st["launches0"] is not None:  # verification launches really made (the first frame's can be the
            # pilot's t = 0 render at the frame spp, no launch): launches in the block beyond one per frame
            per_frame = len(st["rnd"].launch_counts(spp))
            st["verify"] = (st["rnd"].n_launches - st["launches0"]) // per_frame - len(st["times"])
        return t_end - st["t_first"], st["t_first"] - t_all, res, st

    CPU = {"P": [], "B": [], "I": []}  # process CPU time (all threads: render, writer) of each block

    def bare(rnd, times, call=None, key="B"):
        """``set_time`` + a render + ``np.asarray`` per frame; ``call(seed)``: the render (default ``mi.render``)."""
        if call is None:
            def call(seed):
                return rnd.mi.render(rnd.mi_scene, sensor=rnd.sensor, seed=seed, spp=spp)
        np.asarray(call(1))  # warm (kernels cached)
        t0, c0 = time.perf_counter(), time.process_time()
        for i, t_s in enumerate(times):
            rnd.set_time(t_s)
            np.asarray(call(1000 + i))
        CPU[key].append(time.process_time() - c0)
        took = time.perf_counter() - t0
        dr.kernel_history()  # recorded as in the pipeline blocks (same per-launch cost); read = cleared
        return took

    import itertools
    block_no = itertools.count()
    frames_root = Path(cfg["frames_dir"]) if cfg.get("frames_dir") else None
    if frames_root is not None:
        frames_root.mkdir(parents=True, exist_ok=True)
    # every pipeline block of this point renders into its own folder of one temp folder, removed when the
    # point is done: no folder is deleted between the blocks (file creation on this VM's ext4 varies with the
    # recent file churn, 0.02-0.6 ms a file; deleting between blocks would add the benchmark's own churn to the
    # pipeline blocks that follow)
    holder = tempfile.TemporaryDirectory(dir=frames_root, prefix="r2s-overhead-")
    point_dir = Path(holder.name)
    create_ms = _create_cost_ms(point_dir / "probe")
    P, B, I, pairs, compiles, compiled = [], [], [], [], [], []
    # Dr.Jit's kernel history (which the pipeline blocks read for their compile time) is recorded in
    # every block, bare ones too: recording costs each launch a little, and both sides pay it
    history_was = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    rnd = times = None
    try:
        for _ in range(int(cfg.get("rounds", 2))):
            p1, setup, res, st = pipeline()
            if rnd is None:
                rnd, times, setup_s = st["rnd"], st["times"], setup
            direct = getattr(rnd, "_render_call", None)  # the renderer's own render call (newer code)
            b1 = bare(rnd, times)
            if direct is not None:  # the strongest baseline: the render call the pipeline itself makes, bare
                I.append(bare(rnd, times, lambda seed: direct(seed, spp), "I"))
                I.append(bare(rnd, times, lambda seed: direct(seed, spp), "I"))
            b2 = bare(rnd, times)
            compiles.append(st["compile_s"])
            compiled.append(st["compiled"])
            p2, _, _, st2 = pipeline()
            compiles.append(st2["compile_s"])
            compiled.append(st2["compiled"])
            P += [p1, p2]
            B += [b1, b2]
            pairs += [p1 / b1, p2 / b2]
    finally:
        holder.cleanup()
        dr.set_flag(dr.JitFlag.KernelHistory, history_was)
    pipe, bare_s = float(np.sum(P)), float(np.sum(B))
    n_verify = st["verify"]  # verification launches per pipeline block (as counted in the last block)
    H, W = rnd.height, rnd.width
    bare_pf = bare_s / (len(B) * len(times))
    return {"scene": cfg["scene"], "resolution": f"{H}x{W}", "spp": spp, "frames": res.n_frames,
            "rounds": int(cfg.get("rounds", 2)), "setup_s": setup_s,
            "pipeline_s_per_frame": pipe / (len(P) * res.n_frames), "bare_s_per_frame": bare_pf,
            "overhead_ratio": pipe / bare_s, "overhead_ratio_blocks": pairs,
            # CPU time of the process (all threads) over the same blocks: what the pipeline costs in work,
            # much less sensitive than wall time to what other processes on the machine do meanwhile
            "cpu_overhead_ratio": float(np.sum(CPU["P"]) / np.sum(CPU["B"])),
            # the verification launches are extra renders by design: their estimated cost (one bare frame
            # each) taken out, what is left is the pipeline's own per-frame cost
            "overhead_ratio_without_verification": (pipe - len(P) * n_verify * bare_pf) / bare_s,
            "samples_per_s": H * W * spp * len(times) * len(B) / bare_s, "variant": rnd.variant,
            "verification_launches": n_verify,
            # against the bare loop of the render call the pipeline makes (the integrator without mi.render's
            # differentiable wrapper), in the same rounds: what the pipeline adds to its own renders
            "overhead_vs_direct": pipe / float(np.sum(I)) if I else None,
            "direct_s_per_frame": float(np.sum(I)) / (len(I) * len(times)) if I else None,
            "frames_dir": str(frames_root) if frames_root is not None else tempfile.gettempdir(),
            "create_ms": create_ms,
            # kernel compilation inside the pipeline blocks (taken out of their times above), per block
            "compile_s_per_block": compiles, "kernels_compiled_per_block": compiled}


def m_keyframes(cfg):
    """Section 2: keyframes per camera-second of render_scene at fixed spp (the scene's adaptive settings)."""
    from render2spike.render.job import render_scene
    _quiet()
    sc = _load(cfg["scene"], [f"render.spp={cfg['spp']}"] + list(cfg.get("sets", [])), lux=cfg["lux"],
               duration_s=cfg.get("duration_s"))
    with tempfile.TemporaryDirectory() as d:
        t = time.perf_counter()
        res = render_scene(sc, d, progress=False, log=lambda *a: None, **_film())
        wall = time.perf_counter() - t
    ts = res.manifest.get("temporal_sampling", {})
    return {"scene": cfg["scene"], "lux": cfg["lux"], "spp": int(res.spp), "duration_s": sc.duration_s,
            "keyframes": res.n_frames, "keyframes_per_camera_s": res.n_frames / sc.duration_s,
            "base_keyframes": ts.get("n_base"), "wall_s": wall}


def _budget(rnd, sc):
    """(spp, budget dict, how each frame is rendered) of this code version's noise budget."""
    from render2spike.render import noise
    ncfg, rcfg = sc.render["noise"], sc.render
    W = int(ncfg["window_intervals"])
    K = noise.keyframes_per_window(W, sc.profile.interval_s, float(rcfg["keyframe_rate_hz"]))
    rs = rnd.rate_scale()
    if hasattr(noise, "pilot_budget"):
        b, _ = noise.pilot_budget(rnd, sc, W, K, rs, dark_e=noise.dark_current_mean_e(sc.profile))
        return b["spp"], b, W, K, "new"
    # the budget of the version before (render2spike/render/job.py at main 3e4f9e4), verbatim in effect
    from render2spike.render.photometry import to_physical
    n1 = rnd.effective_spp(int(ncfg["pilot_spp"]))
    n2 = rnd.effective_spp(4 * n1)
    seeds = np.random.SeedSequence([int(rcfg["seed"]), 0x9110]).generate_state(4, dtype=np.uint32)
    pil = {}
    for j, n in enumerate((n1, n2)):
        pil[n] = [to_physical(*rnd.render_raw(0.0, int(s), n), rnd.k, rnd.f_number, rnd.transmission, rnd.cos4)[0]
                  for s in seeds[2 * j:2 * j + 2]]
    var1 = noise.pair_variance(*pil[n1]) * rs ** 2
    var2 = noise.pair_variance(*pil[n2]) * rs ** 2
    rate = 0.5 * (pil[n2][0] + pil[n2][1]) * rs
    b = noise.choose_spp(rate, float(var1.mean()), n1, float(var2.mean()), n2, W, K, float(ncfg["target_ratio"]),
                         int(ncfg["min_spp"]), int(ncfg["max_spp"]))
    half, halves = rnd.frame_spp(b["spp"])
    return half * halves, b, W, K, "old"


def m_noise(cfg):
    """Section 3 (and the per-frame part of 4): budget spp, achieved ratio, seconds per frame."""
    from render2spike.render.noise import dark_current_mean_e, render_noise_ratio
    from render2spike.render.renderer import SceneRenderer
    _quiet()
    sc = _load(cfg["scene"], ["render.noise.max_spp=1024"] + list(cfg.get("sets", [])), lux=cfg["lux"])
    t = time.perf_counter()
    rnd = SceneRenderer(sc, **_film())
    spp, b, W, K, version = _budget(rnd, sc)
    setup = time.perf_counter() - t
    rs = rnd.rate_scale()
    ratios = []
    for ts in cfg.get("ratio_times", []):
        f = rnd.render_frame(ts, 77, spp)  # both versions: phi_var of the returned frame
        ratios.append(render_noise_ratio(f["phi"] * rs, f["phi_var"] * rs ** 2, W, K,
                                         dark_current_mean_e(sc.profile)))
    per_frame = None
    if cfg.get("wait_frames"):
        from sensor.io.frames import write_frame
        n = int(cfg["wait_frames"])
        with tempfile.TemporaryDirectory() as d:
            # warm-up frame, untimed: a new spp compiles new kernels once per run (part of setup, not per frame)
            np.asarray(rnd.mi.render(rnd.mi_scene, sensor=rnd.sensor, seed=3, spp=spp if version == "new" else
                                     rnd.frame_spp(spp)[0]))
            t = time.perf_counter()
            for i in range(n):
                ts = 0.01 + i * 1e-3
                if version == "new":
                    f = rnd.render_frame(ts, 5, spp, variance=False)
                else:
                    f = rnd.render_frame(ts, 5, spp)
                write_frame(Path(d) / f"f{i}.exr", f["phi"].astype(np.float32), f["lux"].astype(np.float32), time_s=ts)
            per_frame = (time.perf_counter() - t) / n
        if version == "new":  # the first and every VERIFY_EVERY-th base keyframe get a verification launch (an upper bound)
            from render2spike.render.noise import VERIFY_EVERY
            per_frame *= 1.0 + 1.0 / VERIFY_EVERY
    return {"scene": cfg["scene"], "lux": cfg["lux"], "resolution": f"{rnd.height}x{rnd.width}", "spp": int(spp),
            "spp_needed": int(b.get("spp_needed", spp)), "predicted_ratio": b.get("predicted_ratio"),
            "measured_ratios": ratios, "setup_s": setup, "s_per_frame": per_frame, "version": version}


def m_write(cfg):
    """Section 0: one frame write (``sensor.io.frames.write_frame``: temp file, one write, rename) against the
    same frame written through the OpenEXR binding (the writer before, still the fallback), alternating,
    with a render job's header attributes; median milliseconds per frame."""
    from sensor.io import exr as F
    H, W, n = int(cfg["height"]), int(cfg["width"]), int(cfg.get("repeats", 40))
    rng = np.random.default_rng(0)
    phi = rng.uniform(0, 1e12, (H, W)).astype(np.float32)
    lux = rng.uniform(0, 50, (H, W)).astype(np.float32)
    attrs = {"spp": 16, "render_noise_ratio": 0.2, "render_noise_window_intervals": 1000,
             "variant": "llvm_ad_spectral", "scene_hash": "0" * 16, "target_lux": 5.0, "seeds": [1, 2],
             "made_by": json.dumps({"stage": "render", "tool": "render2spike", "scene": "x"}), "scene": "x"}
    header = {"time_s": ("double", 0.001), "units": ("string", F.UNITS_STRING)}
    header.update((k, F._attr_kind(v)) for k, v in attrs.items())

    def binding(path):
        from sensor.io.fileio import atomic_path
        with atomic_path(path) as tmp:
            F._write_frame_openexr(tmp, phi, lux, header)
    t = {"encoder": [], "binding": []}
    with tempfile.TemporaryDirectory(dir=cfg.get("dir")) as d:
        for i in range(n + 2):
            for kind in (("encoder", "binding") if i % 2 else ("binding", "encoder")):
                p = Path(d) / f"{kind}{i}.exr"
                t0 = time.perf_counter()
                if kind == "encoder":
                    F.write_frame(p, phi, lux, time_s=0.001, attrs=attrs)
                else:
                    binding(p)
                if i >= 2:  # two warm-up rounds
                    t[kind].append(time.perf_counter() - t0)
        same = (Path(d) / "encoder3.exr").read_bytes() == (Path(d) / "binding3.exr").read_bytes()
    med = {k: float(np.median(v)) for k, v in t.items()}
    return {"resolution": f"{H}x{W}", "repeats": n, "encoder_ms": 1e3 * med["encoder"],
            "binding_ms": 1e3 * med["binding"], "speedup": med["binding"] / med["encoder"], "same_bytes": same}


MEASURES = {"overhead": m_overhead, "keyframes": m_keyframes, "noise": m_noise, "write": m_write}


# ------------------------------------------------------------------------------------------ driver
def _create_cost_ms(folder: Path, n: int = 64) -> float:
    """CPU ms per file to create, write (a 13 kB frame's size) and rename ``n`` files in ``folder`` (made and
    removed here): what the file system charges for each frame file where the frames are written. On this
    VM's ext4 it was seen to vary tenfold between folders and over minutes (0.02-0.6 ms)."""
    folder.mkdir(parents=True, exist_ok=True)
    data = b"\0" * 13617
    c0 = time.process_time()
    for i in range(n):
        tmp = folder / f".p{i}.part"
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        os.write(fd, data)
        os.close(fd)
        os.replace(tmp, folder / f"p{i}.exr")
    ms = (time.process_time() - c0) / n * 1e3
    for i in range(n):
        (folder / f"p{i}.exr").unlink()
    folder.rmdir()
    return ms


def _run(kind, cfg, tree: Path | None = None):
    env = dict(os.environ)
    env["PYTHONPATH"] = str(tree or ROOT)
    env.setdefault("PYTHONWARNINGS", "ignore")
    out = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--one", kind, json.dumps(cfg)],
                         capture_output=True, text=True, cwd=str(tree or ROOT), env=env)
    if out.returncode != 0:
        raise RuntimeError(f"{kind} {cfg} ({tree or 'this tree'}) failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def _where(folder) -> str:
    """A frames folder's location for the report: relative to the checkout when inside it."""
    if not folder:
        return ""
    try:
        return str(Path(folder).resolve().relative_to(ROOT))
    except ValueError:
        return str(folder)


def _dur(s):
    return f"{s / 60:.1f} min" if s < 7200 else f"{s / 3600:.1f} h"


def write_report(res, meta, out_dir: Path) -> Path:
    from sensor.io.fileio import write_json_atomic, write_text_atomic
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out_dir / "render.json", {"meta": meta, **res})
    L = ["# render2spike render benchmark", "",
         f"Command: `{meta['command']}`  ", f"Date: {meta['date']}  ",
         f"Machine: {meta['cpu']}, {meta['cores']} cores; Mitsuba variant {meta.get('variant', '?')}  ",
         f"Load average before / after: {meta['load_before']} / {meta['load_after']}  ",
         f"Old code: {meta['old'] or 'not measured'}", "",
         ("GPU (CUDA) figures: the variant chosen here." if str(meta.get("variant", "")).startswith("cuda") else
          "CPU figures (the variant chosen here). GPU against CPU samples/s: `benchmarks/render_gpu.py`."), ""]
    if meta.get("note"):
        L += [meta["note"], ""]
    secs = meta.get("sections") or {}

    def when(*keys):
        out = []
        for k in keys:
            m = secs.get(k)
            if m:
                out.append(f"`{k}` measured {m.get('date')} (`{m.get('command')}`), load average before / after "
                           f"{list(m.get('load_before') or [])} / {list(m.get('load_after') or [])}.")
        return [" ".join(out), ""] if out else []
    if res.get("write"):
        L += ["## Frame write (sensor.io.frames.write_frame against the OpenEXR binding)", ""] + when("write") + [
              "One frame (Phi and E float32, uncompressed scanline, a render job's header) to a temp file in /tmp, "
              "renamed; the two writers alternate, median of the repeats after two warm-up rounds. 'same bytes': "
              "the two files are identical.", "",
              "| resolution | repeats | encoder ms | OpenEXR binding ms | binding / encoder | same bytes | load before-after |",
              "|---|---|---|---|---|---|---|"]
        for r in res["write"]:
            L.append(f"| {r['resolution']} | {r['repeats']} | {r['encoder_ms']:.3f} | {r['binding_ms']:.3f} | "
                     f"{r['speedup']:.1f} | {r['same_bytes']} | {r['load_before'][0]:.1f}-{r['load_after'][0]:.1f} |")
        L.append("")
    if res.get("overhead"):
        dates = sorted(r["date"] for r in res["overhead"] if r.get("date"))
        intro = when("overhead") if not dates else [
            f"Rows measured {dates[0]} to {dates[-1]} (each row's 1-minute load average before-after in the last "
            "column; rows are re-measured one by one with `--merge --scenes ... --sizes ...`).", ""]
        L += ["## Throughput and pipeline overhead (adaptive off, fixed spp)", ""] + intro + [
              "Blocks of frames in the order pipeline, bare, bare, pipeline (`--rounds` times, 2 by default; the row's blocks are in 'per block'); the pipeline "
              "block runs from its first frame's render to `render_scene`'s return (frame writes in the "
              "background writer, journal, manifest). It includes the noise verification launches actually made "
              "(the first and every `VERIFY_EVERY`-th base keyframe; the first frame's second render is the pilot's "
              "t = 0 render at the frame spp where the pilot made one, no launch); 'without verification' takes "
              "one bare frame per verification launch made out. 'per block': each pipeline block over its neighbouring bare block. "
              "'median block': the median of those, which one block disturbed by another process moves less. "
              "Kernel compilation in a pipeline block (a job's freshly loaded scene gets a new kernel hash; "
              "Dr.Jit's kernel history gives its time) is taken out of the block (in the JSON: "
              "`compile_s_per_block`). "
              "'CPU': the same ratio as 'overhead' in process CPU time (all threads); Dr.Jit's worker thread "
              "busy-waits between kernels, so both cores read as busy in either block and this ratio follows the "
              "wall-time one. 'vs direct': the pipeline over a bare loop of the render call it makes itself (the "
              "scene integrator without `mi.render`'s differentiable wrapper, blocks between the two bare ones), the "
              "strongest baseline: what the pipeline adds to its own renders (verification launches included, as "
              "in 'overhead'). 'file create ms': CPU per file to "
              "create, write 13 kB and rename in the frames folder's file system, probed at the start of the point "
              "(the pipeline pays it once per frame; the bare loops write nothing). Frames folders: 'frames in' "
              "(one folder per pipeline block, all removed after the point).", "",
              "| scene | resolution | spp | frames | samples/s | bare s/frame | pipeline s/frame | overhead "
              "| vs direct | without verification | median block | CPU | file create ms | frames in | per block "
              "| load before-after |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        head = L[-2:]

        def row(r):
            return (f"| {r['scene']} | {r['resolution']} | {r['spp']} | {r['frames']} | {_fmt(r['samples_per_s'])} | "
                    f"{_fmt(r['bare_s_per_frame'], 3)} | {_fmt(r['pipeline_s_per_frame'], 3)} | "
                    f"{_fmt(r['overhead_ratio'], 3)} | {_fmt(r.get('overhead_vs_direct'), 3)} | "
                    f"{_fmt(r.get('overhead_ratio_without_verification'), 3)} | "
                    f"{_fmt(float(np.median(r['overhead_ratio_blocks'])) if r.get('overhead_ratio_blocks') else None, 3)} | "
                    f"{_fmt(r.get('cpu_overhead_ratio'), 3)} | {_fmt(r.get('create_ms'), 3)} | "
                    f"{_where(r.get('frames_dir'))} | "
                    + ", ".join(_fmt(x, 3) for x in r.get("overhead_ratio_blocks", [])) + " | "
                    + (f"{r['load_before'][0]:.1f}-{r['load_after'][0]:.1f}" if r.get("load_before") else "") + " |")
        L += [row(r) for r in res["overhead"]] + [""]
        if res.get("overhead_old"):
            L += ["The older code (`--old`, `--old-for overhead`), each point measured right after the row above "
                  "of the same scene and resolution:", ""] + head + [row(r) for r in res["overhead_old"]] + [""]
    if res.get("keyframes"):
        L += ["## Keyframes per camera-second (window, budget spp, shortened clip)", ""] + when("keyframes", "keyframes_old") + [
              "| scene | lux | spp now | clip s | base keyframes | keyframes/s now | keyframes/s old | spp old |",
              "|---|---|---|---|---|---|---|---|"]
        old = {(r["scene"], r["lux"]): r for r in res.get("keyframes_old", [])}
        for r in res["keyframes"]:
            o = old.get((r["scene"], r["lux"]))
            o_kf = "" if o is None else f"{o['keyframes_per_camera_s']:.0f}"
            o_spp = "" if o is None else str(o["spp"])
            L.append(f"| {r['scene']} | {r['lux']:g} | {r['spp']} | {r['duration_s']:g} | {r['base_keyframes']} | "
                     f"{r['keyframes_per_camera_s']:.0f} | {o_kf} | {o_spp} |")
        L.append("")
    if res.get("noise"):
        L += ["## Render-noise ratio (target 0.2, band 0.15-0.25; rotating disk, max_spp 1024)", ""] + when("noise", "noise_old") + [
              "| version | lux | resolution | budget spp | predicted | measured (3 times) |", "|---|---|---|---|---|---|"]
        for r in res.get("noise", []) + res.get("noise_old", []):
            L.append(f"| {r['version']} | {r['lux']:g} | {r['resolution']} | {r['spp']} | {_fmt(r['predicted_ratio'], 3)} | "
                     + ", ".join(f"{x:.3f}" for x in r["measured_ratios"]) + " |")
        L.append("")
    if res.get("wait"):
        L += ["## Wait for one camera-second (rotating disk, full 250 x 400, budget spp) - EXTRAPOLATED", ""] + when("wait") + [
              f"From {meta['wait_frames']} measured frames per point x keyframes per camera-second at the same lux "
              "(window measurement above) + setup.", "",
              "| version | lux | spp | s/frame | keyframes/s | setup s | wait per camera-second |",
              "|---|---|---|---|---|---|---|"]
        for r in res["wait"]:
            L.append(f"| {r['version']} | {r['lux']:g} | {r['spp']} | {_fmt(r['s_per_frame'])} | "
                     f"{r['keyframes_per_camera_s']:.0f} | {_fmt(r['setup_s'], 1)} | {_dur(r['wait_s'])} |")
        for lux, ratio in res.get("wait_speedup", {}).items():
            L.append(f"\nWait old / new at {lux} lux: **{ratio:.2f}x**")
        L.append("")
    L += goal_lines(res)
    write_text_atomic(out_dir / "render.md", "\n".join(L))
    return out_dir / "render.md"


def goal_lines(res) -> list[str]:
    """Issue 12's render goals, each marked met / not met with the figures of this report that decide it."""
    say = lambda ok: "**met**" if ok else "**not met**"  # noqa: E731
    out = []
    new = [r for r in res.get("noise", []) if r.get("version") in (None, "new", "now")] or res.get("noise", [])
    if new:
        ok = all(0.15 <= x <= 0.25 for r in new for x in r["measured_ratios"])
        out.append(f"- render/shot-noise ratio within 0.15-0.25 for a 0.2 target at 1, 5 and 50 lux: {say(ok)} ("
                   + "; ".join(f"{r['lux']:g} lux: " + ", ".join(f"{x:.3f}" for x in r["measured_ratios"])
                               for r in new) + ")")
    if res.get("overhead"):
        rows = res["overhead"]
        worst = {}
        for r in rows:
            worst[r["resolution"]] = max(worst.get(r["resolution"], 0.0), r["overhead_ratio"])
        where = sorted({_where(r.get("frames_dir")) or "the system temp folder" for r in rows})
        creates = [r["create_ms"] for r in rows if r.get("create_ms") is not None]
        direct = [r["overhead_vs_direct"] for r in rows if r.get("overhead_vs_direct")]
        out.append(f"- pipeline overhead <= 1.1x a bare `mi.render` at every size: {say(max(worst.values()) <= 1.1)} "
                   "(largest per resolution: " + ", ".join(f"{k} {v:.2f}x" for k, v in worst.items())
                   + f"; frames written in {', '.join(where)}"
                   + (f", file creation {min(creates):.3f}-{max(creates):.3f} ms" if creates else "")
                   + (f"; against the bare loop of the pipeline's own render call: {min(direct):.2f}-"
                      f"{max(direct):.2f}x" if direct else "") + ")")
    if res.get("wait_speedup"):
        r50 = {str(k): v for k, v in res["wait_speedup"].items()}.get("50") or \
            {str(k): v for k, v in res["wait_speedup"].items()}.get("50.0")
        if r50 is not None:
            out.append(f"- wait per camera-second at 50 lux, full resolution, cut by at least 2x: {say(r50 >= 2)} "
                       f"({r50:.2f}x, extrapolated)")
    out.append("- on a GPU, at least 20x the CPU's samples per second: not measured here; `benchmarks/render_gpu.py` "
               "measures it where a GPU is lent")
    return ["## Goals (issue 12)", ""] + out + [""] if out else []


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--old", help="an older checkout to measure in the same run (PYTHONPATH=OLD)")
    ap.add_argument("--scenes", nargs="+", default=list(SCENES))
    ap.add_argument("--lux", type=float, nargs="+", default=list(LUX))
    ap.add_argument("--spp", type=int, default=16, help="fixed spp of sections 1-2 (default 16)")
    ap.add_argument("--frames", type=int, default=32, help="frames per overhead run at the window (default 32)")
    ap.add_argument("--full-frames", type=int, default=32, help="frames per overhead run at full res (default 32)")
    ap.add_argument("--sizes", nargs="+", default=["window", "full"], choices=["window", "full"],
                    help="overhead at the scene's window and/or the full sensor (default both)")
    ap.add_argument("--rounds", type=int, default=2, help="P B B P rounds per overhead point (default 2)")
    ap.add_argument("--frames-dir", default=str(HERE / ".scratch"), metavar="DIR",
                    help="where the overhead section's pipeline writes its frames folders (default: "
                         "benchmarks/.scratch, under the working tree, as `render2spike render --out out/...` does; "
                         "pass /tmp to measure there: the report gives each point's file-creation cost)")
    ap.add_argument("--full-spp", type=int, default=4, help="spp of the full-resolution overhead runs (default 4)")
    ap.add_argument("--clip", type=float, default=0.02, help="camera seconds of the keyframe runs (default 0.02)")
    ap.add_argument("--kf-spp", default="auto", help="spp of the keyframe runs (default: auto, each version's budget)")
    ap.add_argument("--wait-frames", type=int, default=2, help="frames timed per wait point (default 2)")
    ap.add_argument("--skip", nargs="*", default=[], choices=["write", "overhead", "keyframes", "noise", "wait"])
    ap.add_argument("--old-for", nargs="*", default=["keyframes", "noise", "wait"],
                    choices=["overhead", "keyframes", "noise", "wait"],
                    help="sections that also measure --old (default keyframes, noise, wait; 'overhead' measures "
                         "each overhead point with the old code right after the new one)")
    ap.add_argument("--merge", action="store_true",
                    help="keep the sections (and old-code rows) not measured now from the existing render.json in "
                         "--out; each section records when and under which load it was measured")
    ap.add_argument("--quick", action="store_true", help="smoke run: rotating disk, few frames, 50 lux")
    ap.add_argument("--out", default=str(HERE / "results"))
    ap.add_argument("--report-only", action="store_true", help="rewrite render.md from render.json in --out")
    ap.add_argument("--one", nargs=2, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.one:
        print(json.dumps(MEASURES[a.one[0]](json.loads(a.one[1]))))
        return 0
    if a.report_only:  # rewrite render.md from render.json (e.g. after a change of the report's layout)
        d = json.loads((Path(a.out) / "render.json").read_text())
        meta = d.pop("meta")
        print(f"wrote {write_report(d, meta, Path(a.out))}")
        return 0
    if a.quick:
        a.scenes, a.lux, a.frames, a.full_frames, a.clip, a.wait_frames = ["rotating_disk"], [50.0], 6, 2, 0.01, 1
    old = Path(a.old).resolve() if a.old else None
    full = ["camera.profile=vidar-default"]
    load_before = tuple(round(x, 2) for x in os.getloadavg())
    res = {}
    prev = {}
    if a.merge and (Path(a.out) / "render.json").is_file():
        prev = json.loads((Path(a.out) / "render.json").read_text())
    sections = dict(prev.get("meta", {}).get("sections", {}))
    if prev and not sections:  # a file from before per-section records: all its sections share its meta
        m = prev.get("meta", {})
        sections = {k: {"date": m.get("date"), "load_before": m.get("load_before"), "load_after": m.get("load_after"),
                        "command": m.get("command")} for k in prev if k != "meta"}
    cmd = "python benchmarks/render.py " + " ".join(argv if argv is not None else sys.argv[1:])

    def mark(key, t_load):
        sections[key] = {"date": time.strftime("%Y-%m-%d %H:%M:%S"), "load_before": t_load,
                         "load_after": tuple(round(x, 2) for x in os.getloadavg()), "command": cmd}

    def now_load():
        return tuple(round(x, 2) for x in os.getloadavg())
    if old is None or not a.old_for:
        old_for = set()
    else:
        old_for = set(a.old_for)

    def say(msg):
        print(f"[{time.strftime('%H:%M:%S')} load {os.getloadavg()[0]:.1f}] {msg}", flush=True)
    if "write" not in a.skip:
        l0 = now_load()
        res["write"] = []
        for H, W in ((64, 96), (250, 400)):
            lb = now_load()
            r = _run("write", {"height": H, "width": W})
            r.update(load_before=lb, load_after=now_load())
            res["write"].append(r)
            say(f"write {r['resolution']}: {r['encoder_ms']:.3f} ms (binding {r['binding_ms']:.3f} ms), same bytes "
                f"{r['same_bytes']}")
        mark("write", l0)
    if "overhead" not in a.skip:
        l0 = now_load()
        res["overhead"] = []
        if "overhead" in old_for:
            res["overhead_old"] = []
        for sc in a.scenes:
            for size, sets, n, spp in (("window", [], a.frames, a.spp), ("full", full, a.full_frames, a.full_spp)):
                if size not in a.sizes:
                    continue
                for key, tree in (("overhead", None), ("overhead_old", old)):
                    if key == "overhead_old" and "overhead" not in old_for:
                        continue
                    lb = now_load()
                    r = _run("overhead", {"scene": sc, "spp": spp, "frames": n, "sets": sets, "rounds": a.rounds,
                                          "frames_dir": str(Path(a.frames_dir).resolve())}, tree)
                    r.update(date=time.strftime("%Y-%m-%d %H:%M:%S"), load_before=lb, load_after=now_load())
                    res[key].append(r)
                    say(f"{key} {sc} {r['resolution']}: {r['samples_per_s']:.3g} samples/s, pipeline/bare "
                        f"{r['overhead_ratio']:.3f}" + (f", pipeline/direct {r['overhead_vs_direct']:.3f}"
                                                        if r.get("overhead_vs_direct") else "")
                        + f", file create {r['create_ms']:.3f} ms")
        mark("overhead", l0)
        if "overhead" not in old_for:  # old-code rows of an earlier run were measured beside that run's rows,
            prev.pop("overhead_old", None)  # not beside these: dropped rather than shown as a comparison
        for key in ("overhead", "overhead_old"):
            if prev.get(key) and key in res:  # --merge: rows (scene, resolution) not measured now are kept
                have = {(r["scene"], r["resolution"]) for r in res[key]}
                rows = res[key] + [r for r in prev[key] if (r["scene"], r["resolution"]) not in have]
                order = {sc: i for i, sc in enumerate(SCENES)}
                res[key] = sorted(rows, key=lambda r: (order.get(r["scene"], 99), r["resolution"] == "250x400"))
    if "keyframes" not in a.skip:
        for key, tree in (("keyframes", None), ("keyframes_old", old)):
            if key == "keyframes_old" and "keyframes" not in old_for:
                continue
            l0 = now_load()
            res[key] = []
            for sc in a.scenes:
                # every lux on the rotating disk (the wait needs them); the dimmest and brightest elsewhere
                for lux in (a.lux if sc == "rotating_disk" else sorted({min(a.lux), max(a.lux)})):
                    clip = a.clip if sc != "lambertian_plane" else None
                    r = _run("keyframes", {"scene": sc, "spp": a.kf_spp, "lux": lux, "duration_s": clip}, tree)
                    res[key].append(r)
                    say(f"{key} {sc} {lux:g} lux: {r['keyframes_per_camera_s']:.0f} keyframes/s")
            mark(key, l0)
    for key in ("keyframes", "keyframes_old"):  # the wait section needs them: from the earlier run if skipped
        if key not in res and key in prev:
            res[key] = prev[key]
    if "noise" not in a.skip:
        for key, tree in (("noise", None), ("noise_old", old)):
            if key == "noise_old" and "noise" not in old_for:
                continue
            l0 = now_load()
            res[key] = []
            for lux in a.lux:
                r = _run("noise", {"scene": "rotating_disk", "lux": lux, "ratio_times": [0.013, 0.051, 0.087]}, tree)
                res[key].append(r)
                say(f"{key} {lux:g} lux: spp {r['spp']}, ratio {r['measured_ratios']}")
            mark(key, l0)
    if "wait" not in a.skip:
        l0 = now_load()
        res["wait"] = []
        kf = {(r["lux"], v): r["keyframes_per_camera_s"] for k, v in (("keyframes", "new"), ("keyframes_old", "old"))
              for r in res.get(k, []) if r["scene"] == "rotating_disk"}
        for version, tree in (("new", None), ("old", old)):
            if version == "old" and "wait" not in old_for:
                continue
            for lux in a.lux:
                r = _run("noise", {"scene": "rotating_disk", "lux": lux, "sets": full, "wait_frames": a.wait_frames},
                         tree)
                k = kf.get((lux, version))
                if k is None:
                    continue
                r.update(keyframes_per_camera_s=k, wait_s=r["setup_s"] + k * r["s_per_frame"], version=version)
                res["wait"].append(r)
                say(f"wait {version} {lux:g} lux full res: spp {r['spp']}, {r['s_per_frame']:.2f} s/frame, "
                    f"{_dur(r['wait_s'])} per camera-second (extrapolated)")
        by = {(r["version"], r["lux"]): r["wait_s"] for r in res["wait"]}
        res["wait_speedup"] = {f"{lux:g}": by[("old", lux)] / by[("new", lux)] for lux in a.lux
                               if ("old", lux) in by and ("new", lux) in by}
        mark("wait", l0)
    for key, val in prev.items():  # --merge: what was not measured now
        if key != "meta" and key not in res:
            res[key] = val
    cpu = ""
    try:
        cpu = next(ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name"))
    except (OSError, StopIteration):
        pass
    meta = {"command": cmd, "sections": sections,
            "date": time.strftime("%Y-%m-%d %H:%M:%S"), "cpu": cpu, "cores": len(os.sched_getaffinity(0)),
            "load_before": load_before, "load_after": tuple(round(x, 2) for x in os.getloadavg()),
            "old": str(old) if old else None, "wait_frames": a.wait_frames,
            "variant": (res.get("overhead") or [{}])[0].get("variant") or prev.get("meta", {}).get("variant")}
    path = write_report(res, meta, Path(a.out))
    print(f"wrote {path} and {path.with_suffix('.json')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
