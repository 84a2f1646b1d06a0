import sys, time, collections
sys.path.insert(0, "/work/main")
import sensor.fast as fast, sensor.spikefile as sf, sensor.simulate
ssim = sys.modules["sensor.simulate"]
import sensor.rates as srates
import render2spike.commands.simulate as cs
acc = collections.defaultdict(float); cnt = collections.Counter()
def timed(obj, name, key):
    f = getattr(obj, name)
    def w(*a, **k):
        t0 = time.perf_counter()
        try: return f(*a, **k)
        finally: acc[key] += time.perf_counter() - t0; cnt[key] += 1
    setattr(obj, name, w)
timed(fast._FastModel, "run_segments", "run_segments (kernel)")
timed(ssim.SpikeSimulator, "_run", "_run (incl. kernel)")
timed(sf.SpikeWriter, "write_packed", "writer.write_packed")
timed(srates.RateSchedule, "segments", "schedule.segments")
timed(srates.RateSchedule, "add", "schedule.add")
timed(srates.RateSchedule, "detach", "schedule.detach")
# the reader's chunk generator: time spent waiting in next()
orig_chunks = cs.RateSource.chunks
def chunks(self, *a, **k):
    g = orig_chunks(self, *a, **k)
    def gen():
        while True:
            t0 = time.perf_counter()
            try: x = next(g)
            except StopIteration: return
            finally: acc["reader next()"] += time.perf_counter() - t0; cnt["reader next()"] += 1
            yield x
    return gen()
cs.RateSource.chunks = chunks
from render2spike.cli import main
t0 = time.perf_counter()
main(["simulate", sys.argv[1], "--out", "/work/exp/s11/out/bt%s.dat" % sys.argv[2], "--profile", "vidar-default", "--seed", "1", "--quiet"])
print("command %.3f" % (time.perf_counter() - t0))
for k in acc: print("  %-24s %.3f s in %d calls" % (k, acc[k], cnt[k]))
