import sys, time, os, resource, threading
tree = sys.argv[2]; mode = sys.argv[3]; sys.path.insert(0, tree)
sys.argv[0] = "render2spike"
import render2spike; render2spike.cli_process = lambda: True
import sensor.buffers as B
if mode == "off":
    B.RecyclingPool.reserve = lambda self, shape, count: None
import render2spike.commands.simulate as S
cpu = {}
o = S.RateSource._read_next
def rn(self, *a):
    try: return o(self, *a)
    finally: cpu["r"] = time.thread_time()
S.RateSource._read_next = rn
from render2spike.cli import main
t = time.perf_counter()
try:
    main(["simulate", sys.argv[1], "--out", "/work/exp/s10/o3.dat", "--profile", "vidar-default", "--seed", "1", "--quiet"])
except SystemExit: pass
w = time.perf_counter() - t
os.unlink("/work/exp/s10/o3.dat")
u = resource.getrusage(resource.RUSAGE_SELF)
print("%s reader_cpu %.3f wall %.3f proc_cpu %.3f" % (mode, cpu["r"], w, u.ru_utime + u.ru_stime), flush=True)
