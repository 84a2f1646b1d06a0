"""cProfile of the render job (frozen launch, lambertian_plane 32 x 48, 16 spp, adaptive off, 800 frames) with its
frame files left out (write_frame a no-op): where the job's time per frame goes besides the render (docs/performance.md,
sixth round). Run: python benchmarks/results/frozen_launch/pipeline_files/job_profile.py"""
import cProfile, pstats, tempfile, time, sys, io
from pathlib import Path
import numpy as np
import sensor.frames as sf
sf.write_frame = lambda *a, **k: None
import render2spike.render.renderer as rmod
from render2spike.render.job import render_scene
from render2spike.render.scene import load_scene
frames = 800
sets = ["render.spp=16", "render.adaptive.enabled=false"]
rate = float(load_scene("lambertian_plane", sets).render["keyframe_rate_hz"])
sc = load_scene("lambertian_plane", sets, duration_s=(frames - 1) / rate)
pr = cProfile.Profile()
orig = rmod.SceneRenderer.render_frame
st = {}
def wrapped(self, t_s, *a, **k):
    if "t" not in st:
        st["t"] = time.perf_counter(); pr.enable()
    return orig(self, t_s, *a, **k)
rmod.SceneRenderer.render_frame = wrapped
with tempfile.TemporaryDirectory() as d:
    render_scene(sc, Path(d) / "f", progress=False, log=lambda *a: None)
    pr.disable()
    print("ms/frame", 1e3 * (time.perf_counter() - st["t"]) / frames)
s = io.StringIO()
pstats.Stats(pr, stream=s).sort_stats("tottime").print_stats(25)
print(s.getvalue()[:6000])
