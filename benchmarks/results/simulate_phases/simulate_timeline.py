"""When each phase of `render2spike simulate FRAMES_FOLDER` starts and ends (s from this script's start), per
thread: the command run in this process (as `python -m render2spike`, so its process-wide settings apply) with
its phases wrapped by timers. A diagnostic, not a benchmark: python simulate_timeline.py FRAMES_FOLDER"""
import sys, time, threading
from pathlib import Path
T0 = time.perf_counter()
sys.argv[0] = "render2spike"
sys.path.insert(0, str(Path(__file__).resolve().parents[3]))
log = []
def L(m): log.append((time.perf_counter() - T0, threading.current_thread().name[:10], m))
def wrap(obj, name, label=None):
    f = getattr(obj, name)
    def w(*a, **k):
        L(f"{label or name} >"); r = f(*a, **k); L(f"{label or name} <"); return r
    setattr(obj, name, w)
import render2spike.commands.simulate as S
L("imported")
import render2spike; render2spike.cli_process = lambda: True
wrap(S, "_lean_numba")
from sensor import SpikeSimulator, SensorProfile
wrap(S, "plan_reads")
wrap(S.RateSource, "__init__", "RateSource()")
wrap(SpikeSimulator, "warm_up")
wrap(S.RateSource, "_read_next", "read")
wrap(S.RateSource, "chunks", "chunks")
import sensor.spikefile as SF
wrap(SF.SpikeWriter, "close", "writer.close")
o_f = SpikeSimulator.iter_feed_packed
def ifp(self, *a, **k):
    for x in o_f(self, *a, **k):
        L("block"); yield x
SpikeSimulator.iter_feed_packed = ifp
from render2spike.cli import main
L("main")
try:
    main(["simulate", sys.argv[1], "--out", "/tmp/o.dat", "--profile", "vidar-default", "--seed", "1", "--quiet", "--overwrite"])
except SystemExit: pass
L("done")
bl = [x for x in log if x[2] == "block"]
rd = [x for x in log if x[2].startswith("read")]
keep = [x for x in log if x[2] != "block" and not x[2].startswith("read")] + rd[:4] + rd[-2:] + bl[:1] + bl[-1:]
for t, th, m in sorted(keep):
    print(f"{t:7.3f} {th:10s} {m}")
