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
  blocks queued, the final flush is timed; through :class:`sensor.io.fileio.DirectStream`, as
  ``render2spike simulate`` writes) or dropped (``--sink none``);
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
from tables import fmt as _fmt  # noqa: E402
from sensor.io.fileio import write_text_atomic  # noqa: E402
from sensor.units import intervals_to_seconds, seconds_to_intervals  # noqa: E402

LUX = (0.1, 1.0, 5.0, 50.0, 500.0)
MODELS = ("elssim", "ideal", "isi")


def _profile(name):
    from sensor import SensorProfile
    try:
        return SensorProfile.load(name)
    except Exception:  # no bundled profile yet: a synthetic one like it
        from sensor.calibration.vidar import VIDAR_SYNTHETIC
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
    """Writes blocks to a file from a background thread (the write releases the GIL), at most 2 queued.

    The file is a :class:`sensor.io.fileio.DirectStream`, as ``render2spike simulate``'s ``.dat`` writer's:
    the same way around the page cache (on this VM a buffered write of 1 GB costs about 2 CPU s), so the
    kernel baseline writes its spikes as cheaply as the command can."""

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
            try:
                if b is None:
                    return
                self.f.write(b)
            finally:
                self.q.task_done()

    def write(self, data):
        self.q.put(data)

    def drain(self):
        """Wait until every queued block is written (so no write of a timed block runs in untimed time)."""
        self.q.join()

    def close(self):
        self.q.put(None)
        self.t.join()
        self.f.close()


def run_one(cfg: dict) -> dict:
    """Run one configuration in this process; returns the measurements."""
    from sensor import SpikeSimulator
    from sensor.rates import block_keyframe_rows
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
        from sensor.io.fileio import DirectStream
        fd, sink_path = tempfile.mkstemp(suffix=".spk", dir=cfg.get("tmpdir"))
        os.close(fd)
        sink = _Writer(DirectStream(sink_path))
    trace = cfg.get("trace", True)  # off for the end-to-end comparison: tracing slows only this side
    if trace:
        tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0] if trace else 0
    wall = 0.0
    cpu = 0.0  # CPU seconds of the whole process (every thread) inside the timed sections
    n_int = 0
    n_spk = 0
    nbytes = 0
    kf_per_int = profile.interval_s * KEYFRAME_HZ
    per_interval = cfg.get("input") == "per_interval"
    if per_interval:  # one rate per interval (no timestamps), generated a block at a time (not timed)
        sim = SpikeSimulator(profile, model, seed=1, implementation=impl, per_interval=True)
    # keyframes: one feed per simulator block, exactly its keyframes (block_keyframe_rows; the one or two at a
    # block boundary repeated with overlap=), so no block's keyframes are ever joined: the kernel at its fastest
    plan = block_keyframe_rows(np.arange(scene.n_keyframes) * scene.dt, sim.block, profile.interval_s)

    def feeds():
        """(rates, t_s, overlap) per feed, made when asked for (their making is never timed)."""
        if per_interval:
            for m0 in range(0, n_int_target, sim.block):
                n = min(sim.block, n_int_target - m0)
                yield np.stack([scene.frame_at((m0 + m + 0.5) * profile.interval_s) for m in range(n)]), None, 0
            return
        end = 0
        for i, j in plan:
            frames, ts = scene.chunk(i, j - i)
            yield frames, ts, (end - i if end else 0)
            end = j
            if end >= scene.n_keyframes:
                return

    # Each feed is timed alone, its input made just before it (hot in the L3 cache): the kernel at its
    # fastest, the baseline of the end-to-end rows. preload (keyframes): the whole input made first and the
    # loop timed in one piece, as over a large array in memory: the input is then cold in the caches and
    # the kernel slower (8 s of keyframes, 3.3 GB: 8.07 s against 4.95-5.09 s), slower than the command
    # itself, whose reader warms each block's keyframes just ahead; so it is not the baseline.
    preload = bool(cfg.get("preload")) and not per_interval
    source = list(feeds()) if preload else feeds()
    t0, c0 = time.perf_counter(), time.process_time()
    for frames, ts, ov in source:
        t, c = time.perf_counter(), time.process_time()
        for blk in sim.iter_feed_packed(frames, ts, owned=True, overlap=ov):
            if sink is not None:
                sink.write(blk)
            wall += time.perf_counter() - t
            cpu += time.process_time() - c
            n_int += blk.shape[0]
            # untimed; the writer thread writes this block meanwhile, so most of the write is outside the timed
            # run: the kernel's time is then close to that with no output at all (4 s of frames,
            # load 0.5-1.1: 2.23-2.33 s, against 2.12-2.19 s with sink "none" and 2.69-2.82 s counting after
            # the drain). The strongest baseline for the command, which overlaps its writes with the next
            # block: kept so.
            n_spk += int(np.bitwise_count(blk).sum())
            nbytes += blk.nbytes
            t, c = time.perf_counter(), time.process_time()
        if sink is not None:
            sink.drain()  # the writes of these blocks are part of the timed run, not of the next input's making
        wall += time.perf_counter() - t
        cpu += time.process_time() - c
        del frames
    if preload:  # one piece: the counting and the loop's own work between feeds count as well
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    t, c = time.perf_counter(), time.process_time()
    blk = sim.finish_packed()
    if sink is not None:
        sink.write(blk)
        sink.close()  # waits for the last write: part of the timed run
    wall += time.perf_counter() - t
    cpu += time.process_time() - c
    n_int += blk.shape[0]
    n_spk += int(np.bitwise_count(blk).sum())
    nbytes += blk.nbytes
    peak = tracemalloc.get_traced_memory()[1] if trace else float("nan")
    if trace:
        tracemalloc.stop()
    if sink is not None:
        os.unlink(sink_path)
    del kf_per_int
    steps = n_int * H * W
    return {
        "model": model, "reset": profile.reset if model == "elssim" else "", "implementation": sim.implementation,
        "lux": lux,
        "rate_e_mean": float(lux_to_rate_e(lux, profile)), "threshold_e": profile.threshold_e,
        "intervals": n_int, "camera_s": n_int * profile.interval_s, "wall_s": wall, "cpu_s": cpu,
        "pixel_steps_per_s": steps / wall, "realtime_factor": n_int * profile.interval_s / wall,
        "spikes_per_pixel_interval": n_spk / steps, "output_mib": nbytes / 2 ** 20,
        "peak_traced_mib": (peak - base) / 2 ** 20,
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "jit_s": jit_s, "threads": int(os.environ.get("RENDER2SPIKE_THREADS", "0")) or _nthreads(),
        "block_intervals": sim.block, "profile": profile.name,
    }


# ------------------------------------------------------------- `render2spike simulate` end to end vs the kernel
_WRAP = ("import json, resource, subprocess, sys, time; t = time.perf_counter(); "
         "r = subprocess.run(sys.argv[1:], capture_output=True, text=True); w = time.perf_counter() - t; "
         "u = resource.getrusage(resource.RUSAGE_CHILDREN); "
         "print(json.dumps({'rc': r.returncode, 'wall_s': w, 'err': r.stderr[-2000:], "
         "'out': (r.stdout.strip().splitlines() or [''])[-1], "
         "'cpu_s': u.ru_utime + u.ru_stime, 'peak_rss_mib': u.ru_maxrss / 1024.0}))")


def _cli(inp: Path, out: Path, profile: str) -> dict:
    """Run ``python -m render2spike simulate`` in a child; wall time and the child's peak RSS."""
    cmd = [sys.executable, "-m", "render2spike", "simulate", str(inp), "--out", str(out), "--profile", profile,
           "--seed", "1", "--quiet"]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    r = subprocess.run([sys.executable, "-c", _WRAP, *cmd], capture_output=True, text=True, cwd=str(ROOT), env=env)
    res = json.loads(r.stdout.strip().splitlines()[-1])
    if res["rc"] != 0:
        raise RuntimeError(f"render2spike simulate {inp} failed:\n{res['err']}")
    out.unlink(missing_ok=True)
    return res


def _make_frames(folder: Path, profile, lux: float, duration_s: float) -> Path:
    """The benchmark scene's keyframes (1 kHz) as a frames folder (Phi [e-/(s m^2)] in float32 EXR)."""
    from sensor import photoelectron_rate
    from sensor.io.frames import frame_filename, write_frame, write_manifest
    scene = MovingScene(profile, lux, seed=0, duration_s=duration_s)
    per_phi = float(photoelectron_rate(np.ones(1), profile)[0])  # e-/interval per unit Phi
    entries = []
    for i in range(scene.n_keyframes):
        write_frame(folder / frame_filename(i), scene.frame(i) / per_phi, time_s=i * scene.dt)
        entries.append({"file": frame_filename(i), "time_s": i * scene.dt})
    write_manifest(folder, profile.height, profile.width, entries, profile={"name": profile.name})
    return folder


def _subset(src: Path, dst: Path, n: int) -> Path:
    """A frames folder with the first n frames of ``src`` (hard links, no copies)."""
    from sensor.io.frames import read_frames, write_manifest
    seq = read_frames(src)
    dst.mkdir(parents=True, exist_ok=True)
    entries = seq.manifest["frames"][:n]
    for e in entries:
        os.link(src / e["file"], dst / e["file"])
    write_manifest(dst, *seq.shape, entries, profile=seq.manifest.get("profile"))
    return dst


def _make_npy(path: Path, profile, lux: float, duration_s: float) -> Path:
    """One rate per interval [e-/interval] (T, H, W) float32 .npy, written block by block."""
    scene = MovingScene(profile, lux, seed=0, duration_s=duration_s)
    T = int(round(duration_s / profile.interval_s))
    arr = np.lib.format.open_memmap(path, mode="w+", dtype=np.float32, shape=(T,) + profile.shape)
    for m in range(T):
        arr[m] = scene.frame_at((m + 0.5) * profile.interval_s)
    arr.flush()
    del arr
    return path


def _make_npz(path: Path, profile, lux: float, duration_s: float) -> Path:
    """The benchmark's keyframes (1 kHz) as an .npz: rate_e (K, H, W) float32 [e-/interval] and t_s (K,) [s],
    stored (not deflated), written keyframe by keyframe (never whole in memory)."""
    import zipfile
    scene = MovingScene(profile, lux, seed=0, duration_s=duration_s)
    K = scene.n_keyframes
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as zf:
        with zf.open("rate_e.npy", "w", force_zip64=True) as fh:
            np.lib.format.write_array_header_2_0(fh, {"descr": "<f4", "fortran_order": False,
                                                      "shape": (K,) + profile.shape})
            for i in range(K):
                fh.write(np.ascontiguousarray(scene.frame(i), np.float32).tobytes())
        buf = io.BytesIO()
        np.save(buf, np.arange(K) * scene.dt)
        zf.writestr("t_s.npy", buf.getvalue())
    return path


def cli_rows(profile_name: str, frames_durations, npy_durations, lux: float = 5.0, tmpdir=None, say=print,
             repeats: int = 3, npz_durations=()):
    """End-to-end `render2spike simulate` vs the kernel on the same input, per input kind and duration."""
    prof = _profile(profile_name)
    rows = []
    with tempfile.TemporaryDirectory(dir=tmpdir) as d:
        d = Path(d)
        t = time.perf_counter()
        full = _make_frames(d / "frames_full", prof, lux, max(frames_durations))
        say(f"cli: wrote {max(frames_durations):g} s of frames in {time.perf_counter() - t:.0f} s (not timed)")
        tiny = _subset(full, d / "tiny", 2)
        # imports, profile, JIT cache load and 20 intervals: the fixed cost of one command
        _warm(tiny)
        startup = min(_cli(tiny, d / "o.dat", profile_name)["wall_s"] for _ in range(repeats))
        for dur in frames_durations:
            n = int(round(dur * KEYFRAME_HZ)) + 1
            src = full if n == len(json.loads((full / "frames.json").read_text())["frames"]) else \
                _subset(full, d / f"frames_{dur:g}", n)
            rows.append(_cli_row("frames folder", src, d, profile_name, prof, lux, dur, "keyframes", startup, repeats))
            say(_cli_say(rows[-1]))
        for kind, make, suffix, kernel_input, durations in (
                (".npz keyframes", _make_npz, ".npz", "keyframes", npz_durations),
                (".npy per interval", _make_npy, ".npy", "per_interval", npy_durations)):
            for dur in durations:
                src = make(d / f"rate_{dur:g}{suffix}", prof, lux, dur)
                rows.append(_cli_row(kind, src, d, profile_name, prof, lux, dur, kernel_input, startup, repeats))
                say(_cli_say(rows[-1]))
                src.unlink()
    return add_marginal(rows)


def add_marginal(rows):
    """Throughput between two durations of one input kind: (kernel s at the longer - at the shorter) /
    (end-to-end s at the longer - at the shorter), on each row after the first of its kind. The fixed
    costs (start-up, the last block, exit) cancel; what is left is the rate at which the command turns
    more input into spikes, against the kernel's."""
    last = {}
    for r in rows:
        a = last.get(r["input"])
        r["e2e_vs_kernel_marginal"] = "" if a is None or r["e2e_wall_s"] <= a["e2e_wall_s"] else \
            (r["kernel_wall_s"] - a["kernel_wall_s"]) / (r["e2e_wall_s"] - a["e2e_wall_s"])
        last[r["input"]] = r
    return rows


def _warm(src: Path) -> None:
    """Read the input once, untimed, so the timed run reads it from the page cache: the comparison is of
    the command's work against the kernel's (which reads nothing), not of this machine's disk. (On the
    project's VM a memory monitor pages out page-cache pages unused for about a minute, so inputs
    written early in the benchmark were otherwise read from disk in later rows, at random.)"""
    files = sorted(p for p in src.iterdir() if p.is_file()) if src.is_dir() else [src]
    buf = bytearray(8 << 20)
    for f in files:
        with open(f, "rb", buffering=0) as fh:
            while fh.readinto(buf):
                pass


def _kernel_child(cfg: dict) -> dict:
    """:func:`run_one` in a grandchild started by a small wrapper process, like the command end to end: its
    peak RSS is then its own (a child forked straight from this process inherits this process's
    high-water mark, which includes the input files it just wrote)."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--one", json.dumps(cfg)]
    r = subprocess.run([sys.executable, "-c", _WRAP, *cmd], capture_output=True, text=True, cwd=str(ROOT))
    res = json.loads(r.stdout.strip().splitlines()[-1])
    if res["rc"] != 0:
        raise RuntimeError(f"configuration {cfg} failed:\n{res['err']}")
    out = json.loads(res["out"])
    out["peak_rss_mib"] = res["peak_rss_mib"]
    return out


def _best(runs):
    """The fastest of repeated runs (the least disturbed by other jobs), with the largest peak RSS seen."""
    best = dict(min(runs, key=lambda r: r["wall_s"]))
    best["peak_rss_mib"] = max(r["peak_rss_mib"] for r in runs)
    return best


def _cli_row(kind, src, d, profile_name, prof, lux, dur, kernel_input, startup, repeats=3):
    # end to end and kernel alternate, so a drifting load hits both alike; the fastest of each is kept
    load = os.getloadavg()[0]
    e2e_runs, ker_runs = [], []
    for _ in range(repeats):
        # each run starts with no dirty pages waiting for write-back (writing the inputs leaves gigabytes of
        # them, and both sides write 250 MB of spikes per camera-second): os.sync() before each, untimed
        os.sync()
        _warm(src)
        e2e_runs.append(_cli(src, d / "o.dat", profile_name))
        os.sync()
        ker_runs.append(_kernel_child({"profile": profile_name, "sink": "disk", "threads": 0, "model": "elssim",
                                       "implementation": "fast", "lux": lux, "duration_s": dur,
                                       "input": kernel_input, "tmpdir": str(d), "trace": False}))
    e2e, ker = _best(e2e_runs), _best(ker_runs)
    steps = ker["intervals"] * prof.height * prof.width
    return {"input": kind, "camera_s": dur, "intervals": ker["intervals"], "e2e_wall_s": e2e["wall_s"],
            "e2e_cpu_s": e2e["cpu_s"],
            "e2e_pixel_steps_per_s": steps / e2e["wall_s"], "e2e_peak_rss_mib": e2e["peak_rss_mib"],
            "startup_s": startup, "kernel_wall_s": ker["wall_s"], "kernel_pixel_steps_per_s": ker["pixel_steps_per_s"],
            "kernel_peak_rss_mib": ker["peak_rss_mib"], "kernel_cpu_s": ker["cpu_s"],
            "e2e_vs_kernel": ker["wall_s"] / e2e["wall_s"],
            "e2e_vs_kernel_after_startup": (ker["wall_s"] / (e2e["wall_s"] - startup) if e2e["wall_s"] - startup > 0.05
                                            else float("nan")),  # undefined when start-up is nearly all of it
            "load_1min": load}


def _cli_say(r):
    return (f"cli {r['input']:18s} {r['camera_s']:g} s: end to end {r['e2e_wall_s']:.2f} s "
            f"({r['e2e_peak_rss_mib']:.0f} MiB RSS), kernel {r['kernel_wall_s']:.2f} s "
            f"({r['kernel_peak_rss_mib']:.0f} MiB) -> {r['e2e_vs_kernel']:.2f}x the kernel's throughput "
            f"({r['e2e_vs_kernel_after_startup']:.2f}x after {r['startup_s']:.1f} s start-up)")


def _nthreads():
    try:
        from sensor.models.fast import n_threads
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


def write_tables(rows, mem_rows, meta, out_dir: Path, cli_rows_=None):
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
    if cli_rows_:
        buf = io.StringIO()
        wr = csv.DictWriter(buf, fieldnames=list(cli_rows_[0]))
        wr.writeheader()
        for r in cli_rows_:
            wr.writerow(r)
        write_text_atomic(out_dir / "benchmark_cli.csv", buf.getvalue())
    lines = ["# render2spike sensor benchmark", "",
             f"Command: `{meta['command']}`  ", f"Date: {meta['date']}  ",
             f"Machine: {meta['machine']['cpu']}, {meta['machine']['cores']} cores; Python {meta['machine']['python']}, "
             f"numpy {meta['machine']['numpy']}, numba {meta['machine']['numba']}  ",
             f"Load average before / after: {meta['load_before']} / {meta['load_after']}  ",
             f"Profile: {meta['profile']} ({meta['height']} x {meta['width']}, threshold {meta['threshold_e']:g} e-); "
             f"input: keyframes at 1 kHz of a moving texture (reflectance mean 0.5, f/2, T = 0.9, 5000 K); output: "
             f"bit-packed spike stream written to {meta['sink']}.  "]
    if rows:  # the kernel table (absent with --only-cli)
        lines += [
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
    if cli_rows_:
        lines += ["", "`render2spike simulate` end to end (a child process: imports, JIT cache load, reading the input, "
                  "writing a .dat) vs the kernel on the same input in the same run (elssim, fast, 5 lux; kernel = "
                  "`SpikeSimulator.iter_feed_packed` on in-memory input, one feed per simulator block (its "
                  "keyframes exactly, so none is ever joined, made just before its feed: hot in the caches, "
                  "the kernel at its fastest), output written to disk by a thread, most of each block's write while "
                  "the block's spikes are counted (untimed), the rest waited for inside the timed sections (so "
                  "the kernel's time is close to its time with no output at all), through the command's own writer stream (sensor.io.fileio.DirectStream: "
                  "around the page cache where the file system allows), JIT and input making excluded). CPU s = user + system seconds of every thread: the whole command's, and the kernel "
                  "process's inside its timed sections. "
                  f"Start-up = the command on a 2-frame folder ({cli_rows_[0]['startup_s']:.2f} s, fastest of 3); "
                  "\"after start-up\" = kernel s / (end-to-end s - start-up); \"marginal\" = the kernel's extra "
                  "seconds over the command's from the previous duration of the same input to this one (fixed costs "
                  "cancel: the throughput on longer inputs). Each figure is the fastest of 3 runs, "
                  "end to end and kernel alternating, each after an os.sync() and the command's after one untimed read of "
                  "its input (page cache warm); peak RSS the largest of the 3; load = 1-minute load average "
                  "when the row started.", "",
                  "| input | camera s | intervals | end-to-end s | kernel s | throughput vs kernel | after start-up "
                  "| marginal | CPU s end-to-end / kernel | peak RSS end-to-end MiB | peak RSS kernel MiB | load |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in cli_rows_:
            marg = r.get("e2e_vs_kernel_marginal", "")
            lines.append(f"| {r['input']} | {r['camera_s']:g} | {r['intervals']} | {r['e2e_wall_s']:.2f} | "
                         f"{r['kernel_wall_s']:.2f} | {r['e2e_vs_kernel']:.2f} | {r['e2e_vs_kernel_after_startup']:.2f} | "
                         f"{'' if marg == '' else f'{marg:.2f}'} | {r.get('e2e_cpu_s', float('nan')):.2f} / "
                         f"{r.get('kernel_cpu_s', float('nan')):.2f} | "
                         f"{r['e2e_peak_rss_mib']:.0f} | {r['kernel_peak_rss_mib']:.0f} | {r.get('load_1min', float('nan')):.1f} |")
    goals = goal_lines(rows, mem_rows, cli_rows_ or [])
    if goals:
        lines += ["", "## Goals (issue 12)", ""] + goals
    lines.append("")
    write_text_atomic(out_dir / "benchmark.md", "\n".join(lines))
    return out_dir / "benchmark.md"


def _flat(values, tol: float = 1.15) -> bool:
    """Flat in duration: the largest value at most ``tol`` times the smallest."""
    return max(values) <= tol * min(values)


def goal_lines(rows, mem_rows, cli_rows_) -> list[str]:
    """The issue's goals, each with the figures of this run that decide it ("met" / "not met")."""
    out = []
    say = lambda ok: "**met**" if ok else "**not met**"  # noqa: E731
    fast = [r for r in rows if r["model"] == "elssim" and r["implementation"] == "fast"]
    for reset in sorted({r.get("reset", "") for r in fast}):
        dim = [r for r in fast if r.get("reset", "") == reset and r["lux"] <= 5]
        if dim:
            out.append(f"- kernel (elssim, {reset or 'profile'} reset) at least real time at <= 5 lux: "
                       f"{say(all(r['realtime_factor'] >= 1 for r in dim))} ("
                       + ", ".join(f"{r['realtime_factor']:.2f}x at {r['lux']:g} lux" for r in dim) + ")")
        bright = [r for r in fast if r.get("reset", "") == reset and r["lux"] >= 500]
        if bright:
            out.append(f"- kernel (elssim, {reset or 'profile'} reset) at least 10x the reference at 500 lux: "
                       f"{say(all(r['speedup_vs_reference'] >= 10 for r in bright))} ("
                       + ", ".join(f"{r['speedup_vs_reference']:.1f}x" for r in bright) + ")")
    if len(mem_rows) > 1:
        vals = [r["peak_traced_mib"] for r in mem_rows]
        out.append(f"- kernel peak memory flat in duration: {say(_flat(vals))} ("
                   + ", ".join(f"{v:.1f}" for v in vals) + " MiB traced)")
    for kind in dict.fromkeys(r["input"] for r in cli_rows_):
        rs = [r for r in cli_rows_ if r["input"] == kind]
        last = rs[-1]
        marg = [r["e2e_vs_kernel_marginal"] for r in rs if r.get("e2e_vs_kernel_marginal", "") != ""]
        text = (f"- `render2spike simulate` from a {kind}, at least 0.8x the kernel's throughput: end to end "
                f"{say(last['e2e_vs_kernel'] >= 0.8)} at {last['camera_s']:g} s ({last['e2e_vs_kernel']:.2f}x, "
                f"start-up included)")
        if marg:
            text += f"; marginal throughput {say(marg[-1] >= 0.8)} ({marg[-1]:.2f}x from {rs[-2]['camera_s']:g} to " \
                    f"{last['camera_s']:g} s)"
        out.append(text)
        if len(rs) > 1:
            vals = [r["e2e_peak_rss_mib"] for r in rs]
            out.append(f"- `render2spike simulate` from a {kind}, peak memory flat in duration: {say(_flat(vals))} ("
                       + ", ".join(f"{v:.0f}" for v in vals) + " MiB for "
                       + ", ".join(f"{r['camera_s']:g}" for r in rs) + " s)")
    return out


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
    ap.add_argument("--no-cli", action="store_true", help="skip `render2spike simulate` end to end vs the kernel")
    ap.add_argument("--cli-frames", type=float, nargs="+", default=[1.0, 2.0, 4.0],
                    help="camera seconds of the frames-folder inputs (800 kB per keyframe at 1 kHz: 3.2 GB of "
                         "temporary files for 4 s; default 1 2 4)")
    ap.add_argument("--cli-npz", type=float, nargs="*", default=[0.5, 2.0],
                    help="camera seconds of the keyframe .npz inputs (rate_e + t_s, 1 kHz; default 0.5 2)")
    ap.add_argument("--cli-npy", type=float, nargs="+", default=[0.2, 0.5, 1.0],
                    help="camera seconds of the per-interval .npy inputs (400 MB per 0.05 s: an 8 GB temporary file "
                         "for 1 s; default 0.2 0.5 1)")
    ap.add_argument("--only-cli", action="store_true", help="only the end-to-end section")
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
    if a.only_cli:
        a.models, a.no_memory_scan = [], True
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
    cli = []
    if not a.no_cli:
        if a.quick:
            a.cli_frames, a.cli_npy, a.cli_npz = [0.05, 0.1], [0.01, 0.02], [0.05]
        cli = cli_rows(a.profile, sorted(a.cli_frames), sorted(a.cli_npy), say=lambda m: print(m, flush=True),
                       repeats=1 if a.quick else 3, npz_durations=sorted(a.cli_npz))
    prof = _profile(a.profile)
    meta = {"command": "python benchmarks/run.py " + " ".join(argv if argv is not None else sys.argv[1:]),
            "date": time.strftime("%Y-%m-%d %H:%M:%S"), "machine": _machine(), "load_before": load_before,
            "load_after": tuple(round(x, 2) for x in os.getloadavg()), "profile": prof.name,
            "height": prof.height, "width": prof.width, "threshold_e": prof.threshold_e,
            "sink": "a file on disk (sensor.io.fileio.DirectStream)" if a.sink == "disk" else "nowhere (dropped)", "duration_s": a.duration,
            "ref_intervals": a.ref_intervals}
    path = write_tables(rows, mem_rows, meta, Path(a.out), cli)
    print(f"wrote {path} and {path.with_suffix('.csv')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
