"""render2spike sensor benchmark: model x implementation x illuminance -> throughput, real-time factor, memory.

One command::

    python benchmarks/run.py                 # full table (a few minutes on 2 cores)
    python benchmarks/run.py --quick         # smoke run (0.2 s of camera time, small reference)
    python benchmarks/run.py --reset interval crossing --models elssim   # elssim under both pixel resets

writes ``benchmarks/results/benchmark.md`` and ``benchmark.csv``.

What is measured (each configuration in a fresh subprocess, so peak memory and JIT
time are its own):

* input: photoelectron-rate keyframes of a moving textured scene at 1 kHz (one
  every 20 intervals), interpolated piecewise-linearly by the simulator
  (:mod:`benchmarks.scene` gives the lux -> e-/interval chain);
* output: the full spike stream, bit-packed (``SpikeSimulator.iter_feed_packed``),
  written to a file on disk by a writer thread (``--sink disk``, default; at most two
  blocks queued, the final flush is timed) or dropped (``--sink none``);
* timed: ``feed`` + simulation + the write; **not** timed: generating the keyframes
  (the renderer's job) and the first-call JIT compilation / cache load, which is
  reported separately (``jit_s``);
* the reference (step) simulator is timed on ``--ref-intervals`` intervals (default
  400) of the same scene and extrapolated (its cost per interval is constant);
  "speed-up" = fast pixel-steps/s / reference pixel-steps/s, same model and lux,
  measured in the same run;
* peak memory: ``tracemalloc`` peak of the streaming loop (numpy buffers included;
  the 0.1 s input chunk of keyframes, 40 MB at 400 x 250, is part of it) and the
  process's peak RSS (``resource.ru_maxrss``, includes the interpreter, numpy, numba).
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(HERE))

from scene import KEYFRAME_HZ, MovingScene, lux_to_rate_e  # noqa: E402
from sensor.fileio import write_text_atomic  # noqa: E402
from sensor.units import intervals_to_seconds, seconds_to_intervals  # noqa: E402

LUX = (0.1, 1.0, 5.0, 50.0, 500.0)
MODELS = ("elssim", "ideal", "isi")
CHUNK_KEYFRAMES = 100  # keyframes fed per call (0.1 s)


def _profile(name):
    from sensor import SensorProfile
    try:
        return SensorProfile.load(name)
    except Exception:  # no bundled profile yet: a synthetic one like it
        from sensor.vidar import VIDAR_SYNTHETIC
        return SensorProfile.synthetic(250, 400, **VIDAR_SYNTHETIC, seed=0, name="synthetic-vidar-like")


def _warmup(profile, model, implementation) -> float:
    """First-call cost: JIT compilation (or loading numba's cache) on an 8 x 8 window."""
    from sensor import SpikeSimulator
    t = time.perf_counter()
    small = profile.window(0, 0, 8, 8)
    sim = SpikeSimulator(small, model, 0, implementation=implementation)
    r = np.full((3, 8, 8), 5.0, np.float32)
    list(sim.iter_feed_packed(r, np.array([0.0, 1e-3, 2e-3])))
    sim.finish_packed()
    return time.perf_counter() - t


class _Writer:
    """Writes blocks to a file from a background thread (the write releases the GIL), at most 2 queued."""

    def __init__(self, f):
        import queue
        import threading
        self.f = f
        self.q = queue.Queue(maxsize=2)
        self.t = threading.Thread(target=self._run, daemon=True)
        self.t.start()

    def _run(self):
        while True:
            b = self.q.get()
            if b is None:
                return
            self.f.write(b)

    def write(self, data):
        self.q.put(data)

    def close(self):
        self.q.put(None)
        self.t.join()
        self.f.close()


def run_one(cfg: dict) -> dict:
    """Run one configuration in this process; returns the measurements."""
    from sensor import SpikeSimulator
    if cfg.get("threads"):
        os.environ["RENDER2SPIKE_THREADS"] = str(cfg["threads"])
    profile = _profile(cfg["profile"])
    if cfg.get("reset"):
        profile = profile.replace(reset=cfg["reset"])
    model, impl, lux = cfg["model"], cfg["implementation"], float(cfg["lux"])
    duration = float(cfg["duration_s"])
    jit_s = _warmup(profile, model, impl)
    scene = MovingScene(profile, lux, seed=0, duration_s=duration)
    H, W = profile.shape
    n_int_target = int(round(duration / profile.interval_s))
    sim = SpikeSimulator(profile, model, seed=1, implementation=impl)
    sink = None
    if cfg["sink"] == "disk":
        fd, sink_path = tempfile.mkstemp(suffix=".spk", dir=cfg.get("tmpdir"))
        sink = _Writer(os.fdopen(fd, "wb", buffering=0))
    tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0]
    wall = 0.0
    n_int = 0
    n_spk = 0
    nbytes = 0
    i0 = 0
    kf_per_int = profile.interval_s * KEYFRAME_HZ
    while i0 < scene.n_keyframes:
        frames, ts = scene.chunk(i0, CHUNK_KEYFRAMES + (1 if i0 == 0 else 0))
        i0 += frames.shape[0]
        t = time.perf_counter()
        for blk in sim.iter_feed_packed(frames, ts):
            if sink is not None:
                sink.write(blk)
            wall += time.perf_counter() - t
            n_int += blk.shape[0]
            n_spk += int(np.bitwise_count(blk).sum())
            nbytes += blk.nbytes
            t = time.perf_counter()
        wall += time.perf_counter() - t
        del frames
        if n_int >= n_int_target:
            break
    t = time.perf_counter()
    blk = sim.finish_packed()
    if sink is not None:
        sink.write(blk)
        sink.close()  # waits for the last write: part of the timed run
    wall += time.perf_counter() - t
    n_int += blk.shape[0]
    n_spk += int(np.bitwise_count(blk).sum())
    nbytes += blk.nbytes
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    if sink is not None:
        os.unlink(sink_path)
    del kf_per_int
    steps = n_int * H * W
    return {
        "model": model, "reset": profile.reset if model == "elssim" else "", "implementation": sim.implementation,
        "lux": lux,
        "rate_e_mean": float(lux_to_rate_e(lux, profile)), "threshold_e": profile.threshold_e,
        "intervals": n_int, "camera_s": n_int * profile.interval_s, "wall_s": wall,
        "pixel_steps_per_s": steps / wall, "realtime_factor": n_int * profile.interval_s / wall,
        "spikes_per_pixel_interval": n_spk / steps, "output_mib": nbytes / 2 ** 20,
        "peak_traced_mib": (peak - base) / 2 ** 20,
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "jit_s": jit_s, "threads": int(os.environ.get("RENDER2SPIKE_THREADS", "0")) or _nthreads(),
        "block_intervals": sim.block, "profile": profile.name,
    }


def _nthreads():
    try:
        from sensor.fast import n_threads
        return n_threads()
    except ImportError:
        return 1


def _subprocess(cfg: dict) -> dict:
    out = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--one", json.dumps(cfg)],
                         capture_output=True, text=True, cwd=str(ROOT))
    if out.returncode != 0:
        raise RuntimeError(f"configuration {cfg} failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def _machine() -> dict:
    cpu = platform.processor() or ""
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import numpy
    try:
        import numba
        nb = numba.__version__
    except ImportError:
        nb = "not installed"
    return {"cpu": cpu, "cores": len(os.sched_getaffinity(0)), "python": platform.python_version(),
            "numpy": numpy.__version__, "numba": nb, "loadavg": os.getloadavg()}


def _fmt(x, nd=2):
    if x is None or x == "":
        return ""
    if isinstance(x, str):
        return x
    if abs(x) >= 1e5 or (0 < abs(x) < 1e-2):
        return f"{x:.2e}"
    return f"{x:.{nd}f}"


def write_tables(rows, mem_rows, meta, out_dir: Path):
    out_dir.mkdir(parents=True, exist_ok=True)
    cols = ["model", "reset", "implementation", "lux", "rate_e_mean", "intervals", "wall_s", "pixel_steps_per_s",
            "realtime_factor", "speedup_vs_reference", "spikes_per_pixel_interval", "peak_traced_mib", "peak_rss_mib",
            "jit_s", "threads"]
    buf = io.StringIO()
    wr = csv.DictWriter(buf, fieldnames=cols + ["extrapolated"], extrasaction="ignore")
    wr.writeheader()
    for r in rows:
        wr.writerow(r)
    write_text_atomic(out_dir / "benchmark.csv", buf.getvalue())
    lines = ["# render2spike sensor benchmark", "",
             f"Command: `{meta['command']}`  ", f"Date: {meta['date']}  ",
             f"Machine: {meta['machine']['cpu']}, {meta['machine']['cores']} cores; Python {meta['machine']['python']}, "
             f"numpy {meta['machine']['numpy']}, numba {meta['machine']['numba']}  ",
             f"Load average before / after: {meta['load_before']} / {meta['load_after']}  ",
             f"Profile: {meta['profile']} ({meta['height']} x {meta['width']}, threshold {meta['threshold_e']:g} e-); "
             f"input: keyframes at 1 kHz of a moving texture (reflectance mean 0.5, f/2, T = 0.9, 5000 K); output: "
             f"bit-packed spike stream written to {meta['sink']}.  ",
             f"Fast paths: {meta['duration_s']:g} s of camera time ({int(round(seconds_to_intervals(meta['duration_s'])))} intervals). "
             f"Reference: {meta['ref_intervals']} intervals, throughput extrapolated (cost per interval is constant). "
             "Real time = 2.0e9 pixel-steps/s (400 x 250 at 20 kHz). JIT/cache-load time is excluded from the "
             "throughput and shown in `jit_s`.", "",
             "| model | reset | impl | lux | e-/interval | intervals | wall s | pixel-steps/s | x real time "
             "| speed-up vs ref | spikes/px/interval | peak traced MiB | peak RSS MiB | jit s |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append("| " + " | ".join([
            r["model"], r.get("reset", ""), r["implementation"] + (" (extrap.)" if r.get("extrapolated") else ""),
            _fmt(r["lux"], 1),
            _fmt(r["rate_e_mean"]), str(r["intervals"]), _fmt(r["wall_s"]), _fmt(r["pixel_steps_per_s"]),
            _fmt(r["realtime_factor"], 3), _fmt(r.get("speedup_vs_reference", "")), _fmt(r["spikes_per_pixel_interval"], 4),
            _fmt(r["peak_traced_mib"], 1), _fmt(r["peak_rss_mib"], 0), _fmt(r["jit_s"])]) + " |")
    if mem_rows:
        lines += ["", "Peak memory vs duration (elssim, fast, 5 lux):", "",
                  "| camera s | intervals | wall s | peak traced MiB | peak RSS MiB |", "|---|---|---|---|---|"]
        for r in mem_rows:
            lines.append(f"| {r['camera_s']:.2f} | {r['intervals']} | {r['wall_s']:.2f} | {r['peak_traced_mib']:.1f} | "
                         f"{r['peak_rss_mib']:.0f} |")
    lines.append("")
    write_text_atomic(out_dir / "benchmark.md", "\n".join(lines))
    return out_dir / "benchmark.md"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=2.0, help="camera seconds for the fast paths (default 2)")
    ap.add_argument("--ref-intervals", type=int, default=400, help="intervals for the reference (extrapolated)")
    ap.add_argument("--lux", type=float, nargs="+", default=list(LUX))
    ap.add_argument("--models", nargs="+", default=list(MODELS), choices=MODELS)
    ap.add_argument("--profile", default="vidar-default")
    ap.add_argument("--reset", nargs="+", choices=("interval", "crossing"), default=None,
                    help="pixel reset(s) for elssim (default: the profile's own; vidar-default: crossing); "
                         "ideal and isi have one pixel and run once")
    ap.add_argument("--sink", choices=("disk", "none"), default="disk")
    ap.add_argument("--threads", type=int, default=0, help="worker threads of the fast path (default: all CPUs)")
    ap.add_argument("--no-memory-scan", action="store_true", help="skip the peak-memory-vs-duration rows")
    ap.add_argument("--quick", action="store_true", help="smoke run: 0.2 s of camera time, 100 reference intervals")
    ap.add_argument("--out", default=str(HERE / "results"))
    ap.add_argument("--one", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.one:
        print(json.dumps(run_one(json.loads(a.one))))
        return 0
    if a.quick:
        a.duration, a.ref_intervals = 0.2, 100
    load_before = tuple(round(x, 2) for x in os.getloadavg())
    common = {"profile": a.profile, "sink": a.sink, "threads": a.threads}
    rows = []
    # resets alternate at each lux, so that their rows are measured close together (ratios under a drifting load)
    runs = [(m, lux, r) for m in a.models for lux in a.lux
            for r in ((a.reset or [None]) if m == "elssim" else [None])]
    for model, lux, reset in runs:
        ref = _subprocess(dict(common, model=model, reset=reset, implementation="reference", lux=lux,
                               duration_s=float(intervals_to_seconds(a.ref_intervals))))
        ref["extrapolated"] = True
        fast = _subprocess(dict(common, model=model, reset=reset, implementation="fast", lux=lux,
                                duration_s=a.duration))
        fast["speedup_vs_reference"] = fast["pixel_steps_per_s"] / ref["pixel_steps_per_s"]
        ref["speedup_vs_reference"] = 1.0
        for r in (fast, ref):
            rows.append(r)
            print(f"{r['model']:7s} {r['reset']:8s} {r['implementation']:9s} {lux:6g} lux: "
                  f"{r['pixel_steps_per_s']:.3e} "
                  f"pixel-steps/s, x{r['realtime_factor']:.3f} real time, speed-up "
                  f"{r['speedup_vs_reference']:.1f}, peak {r['peak_traced_mib']:.0f} MiB traced / "
                  f"{r['peak_rss_mib']:.0f} MiB RSS, jit {r['jit_s']:.2f} s", flush=True)
    mem_rows = []
    if not a.no_memory_scan and "elssim" in a.models:
        for d in (a.duration / 2, a.duration, a.duration * 2):
            r = _subprocess(dict(common, model="elssim", implementation="fast", lux=5.0, duration_s=d))
            mem_rows.append(r)
            print(f"memory scan: {d:g} s camera -> peak {r['peak_traced_mib']:.1f} MiB traced, "
                  f"{r['peak_rss_mib']:.0f} MiB RSS", flush=True)
    prof = _profile(a.profile)
    meta = {"command": "python benchmarks/run.py " + " ".join(argv if argv is not None else sys.argv[1:]),
            "date": time.strftime("%Y-%m-%d %H:%M:%S"), "machine": _machine(), "load_before": load_before,
            "load_after": tuple(round(x, 2) for x in os.getloadavg()), "profile": prof.name,
            "height": prof.height, "width": prof.width, "threshold_e": prof.threshold_e,
            "sink": "a file on disk" if a.sink == "disk" else "nowhere (dropped)", "duration_s": a.duration,
            "ref_intervals": a.ref_intervals}
    path = write_tables(rows, mem_rows, meta, Path(a.out))
    print(f"wrote {path} and {path.with_suffix('.csv')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
