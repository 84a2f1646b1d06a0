import sys, time
sys.path.insert(0, "/work/main")
import sensor.fast as fast, sensor.spikefile as sf, sensor.fileio as fio
T = {}
orig_run = fast._FastModel.run_segments
def run_segments(self, *a, **k):
    out = orig_run(self, *a, **k); T["last_block_end"] = time.perf_counter(); return out
fast._FastModel.run_segments = run_segments
for name in ("close", "_stop", "_finish_zip"):
    if hasattr(sf.SpikeWriter, name):
        f = getattr(sf.SpikeWriter, name)
        def wrap(self, *a, _f=f, _n=name, **k):
            t0 = time.perf_counter(); r = _f(self, *a, **k); T.setdefault(_n, []).append((t0, time.perf_counter())); return r
        setattr(sf.SpikeWriter, name, wrap)
f = fio.DirectStream.close
def dclose(self, _f=f):
    t0 = time.perf_counter(); r = _f(self); T.setdefault("DirectStream.close", []).append((t0, time.perf_counter())); return r
fio.DirectStream.close = dclose
from render2spike.cli import main
t0 = time.perf_counter()
main(["simulate", sys.argv[1], "--out", "/work/exp/s11/out/t.dat", "--profile", "vidar-default", "--seed", "1", "--overwrite", "--quiet"])
t1 = time.perf_counter()
e = T["last_block_end"]
print("command %.3f s; after the last block %.3f s" % (t1 - t0, t1 - e))
for k, v in T.items():
    if isinstance(v, list):
        for a, b in v: print("  %-22s starts +%.3f s after the last block, takes %.3f s" % (k, a - e, b - a))
