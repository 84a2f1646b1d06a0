"""Alternate e2e `render2spike simulate` of several trees and the kernel child, on one frames folder.
usage: ab4.py FOLDER DUR ROUNDS name=tree[%PYTHONPATH-prefix][@folder],...  (the prefix part was added for ab_swi.txt)"""
import sys, os, json, time, subprocess
sys.path.insert(0, "/work/main/benchmarks")
from pathlib import Path
import run
src = Path(sys.argv[1]); dur = float(sys.argv[2]); rounds = int(sys.argv[3])
spec = dict(x.split("=") for x in sys.argv[4].split(","))
trees = {k: v.split("@")[0].split("%")[0] for k, v in spec.items()}
pre = {k: (v.split("@")[0].split("%")[1] + ":") if "%" in v.split("@")[0] else "" for k, v in spec.items()}
folders = {k: Path(v.split("@")[1]) if "@" in v else src for k, v in spec.items()}
d = Path("/work/exp/s9/tmp"); d.mkdir(exist_ok=True)
def cli(tree, src, prefix=''):
    cmd = [sys.executable, "-m", "render2spike", "simulate", str(src), "--out", str(d / "o.dat"), "--profile",
           "vidar-default", "--seed", "1", "--quiet"]
    env = dict(os.environ, PYTHONPATH=prefix + tree)
    r = subprocess.run([sys.executable, "-c", run._WRAP, *cmd], capture_output=True, text=True, cwd=tree, env=env)
    res = json.loads(r.stdout.strip().splitlines()[-1])
    assert res["rc"] == 0, res["err"]
    (d / "o.dat").unlink()
    return res["wall_s"], res["cpu_s"]
res = {v: [] for v in trees}; ker = []; cpu = {t: [] for t in trees}
for r in range(rounds):
    order = list(trees) if r % 2 == 0 else list(trees)[::-1]
    for v in order:
        os.sync(); run._warm(folders[v])
        w_, c_ = cli(trees[v], folders[v], pre[v]); res[v].append(w_); cpu[v].append(c_)
    os.sync()
    k = run._kernel_child({"profile": "vidar-default", "sink": "disk", "threads": 0, "model": "elssim",
                           "implementation": "fast", "lux": 5.0, "duration_s": dur, "input": "keyframes",
                           "tmpdir": str(d), "trace": False})
    ker.append(k["wall_s"])
    print(r, {v: (round(res[v][-1], 3), round(cpu[v][-1], 2)) for v in trees}, "kernel", round(ker[-1], 3), "load %.2f" % os.getloadavg()[0], flush=True)
kb = min(ker)
for v in trees:
    print(v, "best e2e %.3f ratio %.3f median e2e %.3f median ratio(per-round) %.3f" % (min(res[v]), kb / min(res[v]),
          sorted(res[v])[len(res[v]) // 2], sorted(k / e for k, e in zip(ker, res[v]))[rounds // 2]))
print("kernel best %.3f median %.3f" % (kb, sorted(ker)[rounds // 2]))
for v in trees:
    c = sorted(cpu[v]); print(v, "cpu median %.3f min %.3f" % (c[len(c) // 2], c[0]))
import statistics
d = [a - b for a, b in zip(cpu[list(trees)[1]], cpu[list(trees)[0]])]
print("paired cpu diff (2nd - 1st): median %.3f mean %.3f sd %.3f n %d" % (statistics.median(d), statistics.mean(d), statistics.stdev(d), len(d)))
w = [a - b for a, b in zip(res[list(trees)[1]], res[list(trees)[0]])]
print("paired wall diff (2nd - 1st): median %.3f mean %.3f sd %.3f" % (statistics.median(w), statistics.mean(w), statistics.stdev(w)))
