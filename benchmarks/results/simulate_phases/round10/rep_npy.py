"""Alternate benchmarks/run.py cli_rows([0.5], [0.5, 1], npz [2]) of two trees: python rep.py TREE_A TREE_B ROUNDS"""
import sys, os, json, time, subprocess
trees = sys.argv[1:3]; rounds = int(sys.argv[3])
code = ("import sys, json, os; sys.path.insert(0, sys.argv[1] + '/benchmarks'); import run; "
        "assert run.ROOT == __import__('pathlib').Path(sys.argv[1]), run.ROOT; "
        "l0 = os.getloadavg()[0]; rows = run.cli_rows('vidar-default', [0.5], [0.5, 1], npz_durations=[2], repeats=3, tmpdir='/work/exp/s12/rep', say=lambda m: None); "
        "print(json.dumps({'load0': l0, 'load1': os.getloadavg()[0], 'rows': rows}, default=str))")
for r in range(rounds):
    for tree in (trees if r % 2 == 0 else trees[::-1]):
        t = time.strftime("%H:%M:%S")
        p = subprocess.run([sys.executable, "-c", code, tree], capture_output=True, text=True, cwd=tree,
                           env=dict(os.environ, PYTHONPATH=tree))
        if p.returncode:
            print(tree, "failed", p.stderr[-2000:], flush=True); continue
        res = json.loads(p.stdout.strip().splitlines()[-1])
        out = [tree, t, time.strftime("%H:%M:%S"), "load %.2f-%.2f" % (res["load0"], res["load1"])]
        for row in res["rows"]:
            out.append({k: row.get(k) for k in row if k in ("input", "camera_s", "e2e_wall_s", "kernel_wall_s", "startup_s", "e2e_vs_kernel", "e2e_vs_kernel_after_startup", "e2e_vs_kernel_marginal")})
        print(json.dumps(out), flush=True)
