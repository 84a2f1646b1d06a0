"""Do this machine's CPUs add up? A single-threaded loop timed alone and beside a busy process on another CPU.

The spike kernel keeps every CPU busy, so anything run beside it (a reader, a writer) competes with it.
On a machine whose CPUs share a physical core or memory bandwidth, a CPU's work also slows its
neighbour's: then work added beside the kernel costs more than its own time. This prints, per round,
the loop's time alone, beside a process busy-looping on another CPU (scalar work), and beside one
streaming through 64 MB of memory, as ratios to the loop alone, with the load average. Each time is
the median of 3 loops of ~0.09 s (one loop alone scattered by up to 20 % on the project's VM).

    python benchmarks/cpu_pair.py [--rounds 3]

Linux only (CPU affinity). Needs two CPUs.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from multiprocessing import Event, Process

import numpy as np


def _loop(reps: int = 4000) -> float:
    """Seconds of a numpy loop over a 512 kB array and its temporaries (~1.5 MB in all: compute-bound,
    mostly in the core's own caches)."""
    a = np.random.default_rng(0).random(1 << 16)
    t = time.perf_counter()
    for _ in range(reps):
        a = a * 1.0000001 + 0.1
    return time.perf_counter() - t


def _neighbour(kind: str, cpu: int, ready, stop) -> None:
    os.sched_setaffinity(0, {cpu})
    if kind == "scalar":
        ready.set()
        x = 0
        while not stop.is_set():
            for _ in range(10000):
                x += 1
    else:  # memory: read and write 64 MB over and over (far beyond the caches)
        b = np.ones(64 << 20, np.uint8)
        ready.set()
        while not stop.is_set():
            b += 1


def _median_loop(n: int = 3) -> float:
    return float(np.median([_loop() for _ in range(n)]))


def _beside(kind: str, cpu: int) -> float:
    ready, stop = Event(), Event()
    p = Process(target=_neighbour, args=(kind, cpu, ready, stop), daemon=True)
    p.start()
    try:
        if not ready.wait(30):
            raise RuntimeError(f"the {kind} neighbour process did not start (exit code {p.exitcode})")
        time.sleep(0.2)
        return _median_loop()
    finally:
        stop.set()
        p.join(10)
        if p.is_alive():
            p.terminate()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=3, help="rounds of alone / beside scalar / beside memory")
    a = ap.parse_args(argv)
    if not hasattr(os, "sched_getaffinity"):
        print("needs Linux CPU affinity", file=sys.stderr)
        return 2
    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < 2:
        print("needs two CPUs", file=sys.stderr)
        return 2
    os.sched_setaffinity(0, {cpus[0]})
    _loop(200)  # warm
    print(f"loop on CPU {cpus[0]}, neighbour on CPU {cpus[1]}; load average before {os.getloadavg()}")
    print("round | alone s | beside scalar | beside memory")
    for r in range(a.rounds):
        alone = _median_loop()
        s = _beside("scalar", cpus[1])
        m = _beside("memory", cpus[1])
        print(f"{r + 1} | {alone:.3f} | {s / alone:.2f}x | {m / alone:.2f}x")
    print(f"load average after {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
