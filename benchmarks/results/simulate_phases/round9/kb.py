import sys, time; sys.path.insert(0, "/work/main"); sys.path.insert(0, "/work/main/benchmarks")
import numpy as np, run
from sensor import SensorProfile
from sensor.fast import ELSSimFast
from sensor.rates import RateSchedule
from sensor.models import block_generator
prof = run._profile("vidar-default")
scene = run.MovingScene(prof, 5.0, seed=0, duration_s=0.3)
K = scene.n_keyframes
rate = np.stack([scene.frame(i) for i in range(K)]).astype(np.float32)
t = np.arange(K) * scene.dt
sch = RateSchedule(prof.interval_s); sch.add(rate, t)
m = ELSSimFast(prof)
segs = [sch.segments(k * 1000, (k + 1) * 1000) for k in range(5)]
out = np.empty((1000, m.n_bytes), np.uint8)
res = {"top-down": [], "bottom-up": []}
for r in range(12):
    for rows in (("top-down", "bottom-up") if r % 2 == 0 else ("bottom-up", "top-down")):
        st = m.init_state()
        t0 = time.perf_counter()
        for k, seg in enumerate(segs):
            m.run_segments(seg, st, block_generator(1, "elssim", k, "fast"), out=out, rows=rows)
        res[rows].append(time.perf_counter() - t0)
import os
for k, v in res.items(): print(k, ["%.3f" % x for x in v], "median %.3f" % sorted(v)[6])
print("load", os.getloadavg())
