"""One check of the keyframe criterion's noise floor against high-spp truth frames (not a timing benchmark).

    python benchmarks/keyframe_floor_check.py [LUX] [--clip S] [--truth-spp N]

Renders the rotating disk's 64 x 96 window over a short clip twice with ``render_scene`` (fixed 8 spp, and
the budget's auto spp) and reports the keyframe counts; then renders every tick of the finest grid at
``--truth-spp`` and reports, for the base grid, (a) the refinement criterion evaluated on the truth frames
(``sampling.interpolation_metric`` with the truth's own variance as its floor) and (b) the actual midpoint
error of linear interpolation between base keyframes in the same units (window error over shot noise; the
truth's noise subtracted at 3.9 sigma), against the scene's tolerance. Prints only; nothing is written.
"""

from __future__ import annotations

import argparse
import tempfile
import warnings

import numpy as np


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("lux", type=float, nargs="?", default=5.0)
    ap.add_argument("--clip", type=float, default=0.01, help="camera seconds (default 0.01)")
    ap.add_argument("--truth-spp", type=int, default=512)
    a = ap.parse_args(argv)
    warnings.filterwarnings("ignore")
    from render2spike.render.job import render_scene
    from render2spike.render.renderer import SceneRenderer
    from render2spike.render.sampling import TimeGrid, interpolation_metric
    from render2spike.render.scene import load_scene
    for spp in ("8", "auto"):
        sc = load_scene("rotating_disk", [f"render.spp={spp}"], lux=a.lux, duration_s=a.clip)
        with tempfile.TemporaryDirectory() as d:
            res = render_scene(sc, d, progress=False, log=lambda *x: None)
        print(f"spp {spp} -> {res.spp}: {res.n_frames} keyframes, verified render-noise ratio "
              f"{res.manifest['render_noise_ratio'].get('verified_mean')}")
    sc = load_scene("rotating_disk", ["render.spp=8"], lux=a.lux, duration_s=a.clip)
    r = SceneRenderer(sc)
    rs = r.rate_scale()
    W = int(sc.render["noise"]["window_intervals"])
    g = TimeGrid.make(a.clip, float(sc.render["keyframe_rate_hz"]), float(sc.render["adaptive"]["max_rate_hz"]))
    h = g.time(g.step) - g.time(0)
    fr = {tick: r.render_frame(g.time(tick), 9, a.truth_spp) for tick in range(g.n_ticks + 1)}
    base = g.base_ticks()
    crit = []
    for i in range(1, len(base) - 1):
        x, y, z = (fr[base[j]] for j in (i - 1, i, i + 1))
        var = np.maximum(np.maximum(x["phi_var"], y["phi_var"]), z["phi_var"])
        crit.append(interpolation_metric(var, rs, W, sc.profile.interval_s, z=4.0)(x["phi"], y["phi"], z["phi"], h))
    seg = min(W, h / sc.profile.interval_s)
    act = []
    for i in range(len(base) - 1):
        x, y, m = fr[base[i]], fr[base[i + 1]], fr[(base[i] + base[i + 1]) // 2]
        e = np.abs(0.5 * (x["phi"] + y["phi"]) - m["phi"]) * rs
        sd = np.sqrt(0.25 * x["phi_var"] + 0.25 * y["phi_var"] + m["phi_var"]) * rs
        e = np.maximum(0.0, e - 3.9 * sd)
        act.append(float(np.max((2 / 3) * e * seg / np.sqrt(W * np.maximum(m["phi"] * rs, 1 / W)))))
    print(f"criterion on {a.truth_spp}-spp truth, base triplets: median {np.median(crit):.3f}, max {max(crit):.3f}")
    print(f"actual base-grid midpoint error (same units): median {np.median(act):.3f}, max {max(act):.3f}")
    print(f"tolerance {sc.render['adaptive']['tolerance']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
