"""In-process `render2spike simulate` with the fast model's blocks and tiles timed (wall, per thread)."""
import sys, time, threading, os, json
sys.path.insert(0, "/work/main")
import sensor.fast as fast
rec_t, rec_b = [], []
orig_tile = fast._FastModel._tile_into
orig_run = fast._FastModel.run_segments
def tile_into(self, *a):
    t0 = time.perf_counter(); c0 = time.thread_time()
    orig_tile(self, *a)
    rec_t.append((threading.get_ident(), t0, time.perf_counter(), time.thread_time() - c0))
def run_segments(self, seg, *a, **k):
    t0 = time.perf_counter(); n0 = len(rec_t)
    out = orig_run(self, seg, *a, **k)
    rec_b.append((t0, time.perf_counter(), n0, len(rec_t)))
    return out
fast._FastModel._tile_into = tile_into
fast._FastModel.run_segments = run_segments
from render2spike.cli import main
folder = sys.argv[1]
T0 = time.perf_counter()
main(["simulate", folder, "--out", "/work/exp/s11/out/b.dat", "--profile", "vidar-default", "--seed", "1", "--overwrite", "--quiet"])
T1 = time.perf_counter()
big = [b for b in rec_b if b[3] - b[2] > 3]  # the real blocks (not warm-up)
wall = sum(b[1] - b[0] for b in big)
gaps = sum(b2[0] - b1[1] for b1, b2 in zip(big, big[1:]))
tails, heads, cpu, tw = 0, 0, 0, 0
for b0, b1, i, j in big:
    ts = rec_t[i:j]
    cpu += sum(t[3] for t in ts); tw += sum(t[2] - t[1] for t in ts)
    ends = {}
    for tid, s, e, c in ts:
        ends[tid] = max(ends.get(tid, 0), e)
    e = sorted(ends.values())
    tails += (e[-1] - e[0]) if len(e) > 1 else 0
    heads += min(t[1] for t in ts) - b0
print(json.dumps({"command_s": round(T1 - T0, 3), "blocks": len(big), "block_wall_s": round(wall, 3),
    "between_blocks_s": round(gaps, 3), "tile_cpu_s": round(cpu, 3), "tile_wall_s": round(tw, 3),
    "tails_s (one thread done, block not)": round(tails, 3), "dispatch_s": round(heads, 3),
    "first_block_at_s": round(big[0][0] - T0, 3), "load": os.getloadavg()[0]}))
