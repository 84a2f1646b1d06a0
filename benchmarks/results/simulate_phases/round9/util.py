import sys, time, os; sys.path.insert(0, "/work/main"); sys.path.insert(0, "/work/main/benchmarks")
import numpy as np, run
import sensor.fast as fast
from sensor.fast import ELSSimFast
from sensor.rates import RateSchedule
from sensor.models import block_generator
prof = run._profile("vidar-default")
scene = run.MovingScene(prof, 5.0, seed=0, duration_s=1.0)
K = scene.n_keyframes
rate = np.stack([scene.frame(i) for i in range(K)]).astype(np.float32)
t = np.arange(K) * scene.dt
sch = RateSchedule(prof.interval_s); sch.add(rate, t)
m = ElSSim = ELSSimFast(prof)
cpu = []
orig = m._tile_into
def tile_into(*a):
    c0 = time.thread_time(); t0 = time.perf_counter()
    orig(*a)
    cpu.append((time.thread_time() - c0, t0, time.perf_counter()))
m._tile_into = tile_into
out = np.empty((1000, m.n_bytes), np.uint8)
st = m.init_state()
walls = []; tails = []
nb = 19
for k in range(nb):
    seg = sch.segments(k * 1000, (k + 1) * 1000)
    cpu.clear()
    t0 = time.perf_counter()
    m.run_segments(seg, st, block_generator(1, "elssim", k, "fast"), out=out)
    w = time.perf_counter() - t0
    walls.append(w)
    tot = sum(c[0] for c in cpu)
    ends = sorted(c[2] for c in cpu)
    tails.append((tot, ends[-1] - ends[-2]))
W = sum(walls[1:]); C = sum(t[0] for t in tails[1:])
print("blocks", nb - 1, "wall %.3f s, tile CPU %.3f s, utilisation %.3f of 2 cores; idle core-s %.3f" % (W, C, C / (2 * W), 2 * W - C))
print("per-block tile cost spread (ms):", ["%.1f" % (1e3 * min(c[0] for c in cpu)), "%.1f" % (1e3 * max(c[0] for c in cpu))], "last-two-tile end gap median %.1f ms" % (1e3 * sorted(x[1] for x in tails)[nb // 2]))
print("n tiles", len(m.tiles), "threads", fast.n_threads(), "load", os.getloadavg()[0])
