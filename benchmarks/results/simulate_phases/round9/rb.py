import sys, time, os; sys.path.insert(0, "/work/main")
import numpy as np
from sensor.frames import read_frames
seqs = {k: read_frames(f"/work/exp/{k}") for k in ("f4", "f4m", "f4p")}
out = np.empty((500,) + seqs["f4"].shape, np.float32)
res = {k: [] for k in seqs}
for r in range(7):
    for k, seq in seqs.items():
        t0 = time.perf_counter(); c0 = time.thread_time()
        for s0 in range(1000, 3000, 500):
            seq.read_scaled_many(s0, s0 + 500, 2.0, out)
        res[k].append((time.perf_counter() - t0, time.thread_time() - c0))
for k, v in res.items():
    w = sorted(x[0] for x in v[1:]); c = sorted(x[1] for x in v[1:])
    print(k, "wall ms/frame %.4f  cpu ms/frame %.4f" % (w[len(w)//2] / 2000 * 1e3, c[len(c)//2] / 2000 * 1e3))
print("load", os.getloadavg())
