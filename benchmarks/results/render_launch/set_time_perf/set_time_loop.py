"""4,000 calls of SceneRenderer.set_time on a bundled scene (its default launch), nothing rendered between them:
what `perf record -g` of this loop spends its time in (set_time_perf.txt). A diagnostic: python set_time_loop.py SCENE"""
import sys, time
from pathlib import Path; sys.path.insert(0, str(Path(__file__).resolve().parents[4]))
import numpy as np
from render2spike.render.renderer import SceneRenderer
from render2spike.render.scene import load_scene
sc = load_scene(sys.argv[1], [])
r = SceneRenderer(sc, launch="frozen")
ts = np.linspace(0, float(sc.duration_s), 400, endpoint=False)
t0 = time.perf_counter()
for k in range(10):
    for t in ts:
        r._t_set = None; r.set_time(float(t))
print("ms per set_time", (time.perf_counter() - t0) / 4000 * 1e3)
