"""The spike stage's speed: the torch implementation against the numba ``fast`` kernels, in one run.

For each reset and light level, the same input (keyframes at 1 kHz, i.e. every 20 intervals, of a fixed
texture x a slow flicker, on a centred window of ``vidar-default`` with all its effects) goes through
``SpikeSimulator.iter_feed_packed`` with ``implementation="torch"`` on ``--device`` and with ``fast`` (numba)
at each thread count of ``--threads`` (``RENDER2SPIKE_THREADS``). Every timed run includes the packed spikes'
copy to the host (nothing is written to disk). Throughput is pixel-steps/s = pixels x intervals / wall
seconds; the ratio torch / fast is taken against the fast row with the most threads, measured right after the
torch row on the same input; the load average (1 min) is printed beside each figure. One warm-up run per implementation (numba's
cache load, torch's CUDA start) is not timed.

    python benchmarks/spike_stage.py [--device cpu|cuda|auto] [--threads 1 2 4 8 16] [--size 250x400]
        [--intervals 4000] [--lam-e 160 1600 8000] [--resets crossing interval] [--out FILE.md]

The fast kernels cut the pixels into tiles of 8192 (sensor.models.fast.TILE_PIXELS): a window of P pixels keeps
at most ceil(P / 8192) threads busy (13 for the full 250 x 400 sensor).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import sensor  # noqa: E402
from sensor.simulator import SpikeSimulator  # noqa: E402


def _load() -> float:
    return float(open("/proc/loadavg").read().split()[0]) if os.path.exists("/proc/loadavg") else float("nan")


def _input(h: int, w: int, T: int, lam_e: float, seed: int = 0):
    """Keyframes (K, h, w) float32 [e-/interval] every 20 intervals and their times [s]."""
    rng = np.random.default_rng(seed)
    K = T // 20 + 1
    t = np.arange(K) * 20 * sensor.INTERVAL_S
    texture = rng.uniform(0.5, 1.5, (1, h, w))
    flicker = 1.0 + 0.3 * np.sin(np.arange(K) / 7.0)[:, None, None]
    return (lam_e * texture * flicker).astype(np.float32), t


def _run(profile, rate, t, implementation, device=None, seed=1):
    """(wall s, intervals, spikes per pixel-interval, implementation, device) of one stream."""
    t0 = time.perf_counter()
    sim = SpikeSimulator(profile, "elssim", seed, implementation=implementation, device=device)
    n = spikes = 0
    for bits in sim.iter_feed_packed(rate, t):
        n += bits.shape[0]
        spikes += int(np.unpackbits(bits).sum())
    for bits in sim.iter_finish_packed():
        n += bits.shape[0]
        spikes += int(np.unpackbits(bits).sum())
    wall = time.perf_counter() - t0
    return wall, n, spikes / max(n * profile.height * profile.width, 1), sim.implementation, sim.device


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="auto", help="device of the torch implementation (cpu, cuda, auto)")
    ap.add_argument("--threads", type=int, nargs="+", default=None,
                    help="numba thread counts for the fast rows (default: this process's CPUs)")
    ap.add_argument("--size", default="250x400", help="window HxW of vidar-default (default: the full sensor)")
    ap.add_argument("--intervals", type=int, default=4000, help="intervals per run (default 4000 = 0.2 s)")
    ap.add_argument("--lam-e", type=float, nargs="+", default=[160.0, 1600.0, 8000.0],
                    help="mean light [e-/interval] (threshold 16000 e-); default 160 1600 8000")
    ap.add_argument("--resets", nargs="+", default=["crossing", "interval"], choices=["crossing", "interval"])
    ap.add_argument("--out", default="benchmarks/results/spike_stage.md")
    args = ap.parse_args(argv)

    import torch
    from sensor.models.fast import n_threads
    from sensor.models.torch_models import spike_device
    device = spike_device(None if args.device == "auto" else args.device)
    threads = args.threads or [n_threads()]
    h, w = (int(x) for x in args.size.lower().split("x"))
    base = sensor.SensorProfile.load("vidar-default").centred(h, w)
    P = h * w

    rows, scaling = [], []
    t_start = time.strftime("%Y-%m-%d %H:%M:%S")
    load0 = _load()
    for reset in args.resets:
        prof = base.replace(reset=reset)
        # warm-up (untimed): numba's cache load, torch's device start, on a short stream
        wr, wt = _input(h, w, 40, args.lam_e[0])
        _run(prof, wr, wt, "fast")
        _run(prof, wr, wt, "torch", device)
        for lam in args.lam_e:
            rate, t = _input(h, w, args.intervals, lam)
            la = _load()
            wall, n, sp, impl, dev = _run(prof, rate, t, "torch", device)
            assert impl == "torch"
            torch_rate = P * n / wall
            fast = {}
            for nt in threads:
                os.environ["RENDER2SPIKE_THREADS"] = str(nt)
                lf = _load()
                fw, fn, fsp, fimpl, _ = _run(prof, rate, t, "fast")
                fast[nt] = (P * fn / fw, fw, fsp, lf)
                scaling.append((reset, lam, nt, P * fn / fw, fw, lf))
            os.environ.pop("RENDER2SPIKE_THREADS", None)
            top = max(threads)
            rows.append((reset, lam, n, dev, wall, torch_rate, sp, la, top, fast[top][0], fast[top][2], fast[top][3],
                         torch_rate / fast[top][0]))
            print(f"{reset} lam {lam:g}: torch/{dev} {torch_rate:.3g} px-steps/s (load {la:.2f}), fast x{top} "
                  f"{fast[top][0]:.3g} (load {fast[top][3]:.2f}): ratio {torch_rate / fast[top][0]:.3g}", flush=True)
    load1 = _load()

    cpu = platform.processor() or platform.machine()
    gpu = torch.cuda.get_device_name(0) if device.startswith("cuda") else "none used"
    lines = [
        "# Spike stage: torch implementation against the numba fast kernels",
        "",
        f"Command: `python benchmarks/spike_stage.py {' '.join(argv if argv is not None else sys.argv[1:])}`  ",
        f"Date: {t_start}  ",
        f"Machine: {cpu}, {os.cpu_count()} CPUs ({len(os.sched_getaffinity(0))} usable); GPU: {gpu}; "
        f"Python {platform.python_version()}, numpy {np.__version__}, torch {torch.__version__} "
        f"({torch.get_num_threads()} CPU threads)  ",
        f"Load average (1 min) at start / end: {load0:.2f} / {load1:.2f}  ",
        f"Input: vidar-default window {h} x {w} ({P} pixels, threshold {base.threshold_e:g} e-, dark mode {base.dark}, "
        f"PRNU, {int(base.hot_mask.sum())} hot pixels), elssim, keyframes every 20 intervals, "
        f"{args.intervals} intervals per run; the packed spikes are copied to the host, not written.",
        "",
        "| reset | e-/interval | intervals | torch device | torch wall s | torch pixel-steps/s | torch spikes/px/int "
        "| load | fast threads | fast pixel-steps/s | fast spikes/px/int | load | torch / fast |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(f"| {r[0]} | {r[1]:g} | {r[2]} | {r[3]} | {r[4]:.2f} | {r[5]:.3g} | {r[6]:.3g} | {r[7]:.2f} | "
                     f"{r[8]} | {r[9]:.3g} | {r[10]:.3g} | {r[11]:.2f} | {r[12]:.3g} |")
    lines += ["", "Numba fast kernels by thread count (RENDER2SPIKE_THREADS; speed-up against 1 thread where measured):",
              "", "| reset | e-/interval | threads | pixel-steps/s | wall s | speed-up | load |", "|---|---|---|---|---|---|---|"]
    one = {(r, lam): v for r, lam, nt, v, _, _ in scaling if nt == 1}
    for r, lam, nt, v, wall, la in scaling:
        su = f"{v / one[(r, lam)]:.2f}" if (r, lam) in one else "-"
        lines.append(f"| {r} | {lam:g} | {nt} | {v:.3g} | {wall:.2f} | {su} | {la:.2f} |")
    n_cpu = len(os.sched_getaffinity(0))
    loads = [load0, load1] + [r[7] for r in rows] + [r[11] for r in rows] + [x[5] for x in scaling]
    if max(loads) >= n_cpu - 0.5:
        lines += ["", f"The load average reached {max(loads):.2f} on {n_cpu} usable CPUs: other work shared them, so "
                      "the thread rows show contention rather than the kernels' scaling."]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(out.suffix + ".tmp")
    tmp.write_text("\n".join(lines) + "\n")
    os.replace(tmp, out)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    try:
        raise SystemExit(main())
    except sensor.InputError as e:  # a bad --device, or CUDA asked for where none works: one line
        print(f"spike_stage.py: {e}", file=sys.stderr)
        raise SystemExit(2)
