import sys, time, os, resource
tree = sys.argv[2]; sys.path.insert(0, tree)
sys.argv[0] = "render2spike"
import render2spike; render2spike.cli_process = lambda: True
assert render2spike.__file__.startswith(tree), render2spike.__file__
import sensor.spikefile as SF
cpu = {}
orig = SF.SpikeWriter._drain
def drain(self):
    try: orig(self)
    finally: cpu["w"] = time.thread_time()
SF.SpikeWriter._drain = drain
from render2spike.cli import main
t = time.perf_counter()
try:
    main(["simulate", sys.argv[1], "--out", "/work/exp/s10/o3.dat", "--profile", "vidar-default", "--seed", "1", "--quiet"])
except SystemExit: pass
w = time.perf_counter() - t
os.unlink("/work/exp/s10/o3.dat")
u = resource.getrusage(resource.RUSAGE_SELF)
print("%s writer_cpu %.3f wall %.3f proc_cpu %.3f" % (tree, cpu["w"], w, u.ru_utime + u.ru_stime))
