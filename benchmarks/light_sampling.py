"""Light sampling: render variance and mean with the sky left to BSDF-sampled rays, against the sky also taking
shadow rays, in one run.

One command::

    python benchmarks/light_sampling.py                  # the bundled scenes with a sky and another light
    python benchmarks/light_sampling.py --spp 64 --renders 8 --out DIR

writes ``light_sampling.md`` and ``light_sampling.json`` in ``--out`` (default benchmarks/results; overwritten:
one current table).

For each scene (its own camera window, t = 0, the frozen launch) it renders ``--renders`` independent frames at
``--spp`` with each emitter weighting (:func:`render2spike.render.builder.emitter_sampling_weights`: the default,
where the sky takes no shadow rays when another light is on, and ``sky_by_nee=True``, where it takes them in
proportion to its light), both with one light-meter reading (the same ``k``, so the same physical units). Per
mode: the mean over pixels of each pixel's variance between renders (one render's variance, in rate_e^2 with
rate_e in expected photoelectrons per interval), the frame's render-noise ratio at that spp
(:mod:`render2spike.render.noise`, ``K`` keyframes per window as the scene's budget takes them), and the median
seconds per render. Between the modes: the variance ratio and the mean difference over the frame, relative, with
its standard error from the pixels' own variances. The load average is recorded before and after; the ratios,
measured in one process, are the figures.
"""

from __future__ import annotations

import argparse
import functools
import os
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

SCENES = ("rotating_disk", "translating_object", "room_pan")


def renders(scene_name: str, sky_by_nee: bool, spp: int, n: int, seed0: int, calibration=None) -> dict:
    """``n`` renders of ``scene_name`` at t = 0 and ``spp`` with the given emitter weighting: their rate_e (n, H, W),
    the seconds of each and the renderer's light-meter calibration."""
    import numpy as np

    import render2spike.render.builder as builder
    from render2spike.render.noise import dark_current_mean_e, keyframes_per_window
    from render2spike.render.photometry import to_physical
    from render2spike.render.renderer import SceneRenderer
    from render2spike.render.scene import load_scene
    orig = builder.emitter_sampling_weights
    builder.emitter_sampling_weights = functools.partial(orig, sky_by_nee=sky_by_nee)
    try:
        scene = load_scene(scene_name)
        rnd = SceneRenderer(scene, None, launch="frozen", calibration=calibration)
    finally:
        builder.emitter_sampling_weights = orig
    rnd.render_raw(0.0, seed0 + 999, spp)  # records the launch: not timed
    rs = rnd.rate_scale()
    out, secs = [], []
    for i in range(n):
        t0 = time.perf_counter()
        p, e = rnd.render_raw(0.0, seed0 + i, spp)
        secs.append(time.perf_counter() - t0)
        out.append(to_physical(p, e, rnd.k, rnd.f_number, rnd.transmission, rnd.cos4)[0] * rs)
    rcfg = scene.render
    W = int(rcfg["noise"]["window_intervals"])
    K = keyframes_per_window(W, scene.profile.interval_s, float(rcfg["keyframe_rate_hz"]))
    return {"rate_e": np.asarray(out), "seconds": secs, "calibration": rnd.calibration, "W": W, "K": K,
            "dark_e": dark_current_mean_e(scene.profile), "size": [scene.profile.height, scene.profile.width]}


def compare(scene_name: str, spp: int, n: int) -> dict:
    import numpy as np

    from render2spike.render.noise import render_noise_ratio
    mixed = renders(scene_name, True, spp, n, 1000)
    bsdf = renders(scene_name, False, spp, n, 2000, calibration=mixed["calibration"])
    row = {"scene": scene_name, "spp": spp, "renders": n, "size": mixed["size"]}
    for name, r in (("mixed", mixed), ("bsdf", bsdf)):
        x = r["rate_e"]
        var = x.var(axis=0, ddof=1)
        row[name] = {"mean_rate_e": float(x.mean()), "mean_var_rate_e2": float(var.mean()),
                     "ratio": render_noise_ratio(x.mean(axis=0), var, r["W"], r["K"], r["dark_e"]),
                     "median_s": statistics.median(r["seconds"])}
    d = bsdf["rate_e"].mean(axis=0) - mixed["rate_e"].mean(axis=0)
    se = float(np.sqrt((bsdf["rate_e"].var(axis=0, ddof=1) + mixed["rate_e"].var(axis=0, ddof=1)).sum() / n)
               / d.size)
    m = row["mixed"]["mean_rate_e"]
    row["variance_ratio"] = row["mixed"]["mean_var_rate_e2"] / row["bsdf"]["mean_var_rate_e2"]
    row["mean_difference_relative"] = float(d.mean()) / m
    row["mean_difference_se_relative"] = se / m
    row["mean_difference_z"] = float(d.mean()) / se if se > 0 else float("nan")
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default=",".join(SCENES), help="bundled scenes, comma-separated")
    ap.add_argument("--spp", type=int, default=64, help="samples per pixel of each render (default 64)")
    ap.add_argument("--renders", type=int, default=8, help="independent renders per mode (default 8)")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    a = ap.parse_args(argv)
    from benchmarks.tables import machine, write_report
    load0 = os.getloadavg()
    rows = [compare(s, a.spp, a.renders) for s in a.scenes.split(",")]
    load1 = os.getloadavg()
    rec = {"machine": machine(), "load_before": load0, "load_after": load1, "command": " ".join(sys.argv),
           "rows": rows}
    lines = ["# Light sampling: the sky left to BSDF-sampled rays against the sky also taking shadow rays", "",
             f"Machine: {rec['machine']['cpu']}, {rec['machine']['cores']} cores; load average {load0[0]:.1f} "
             f"before, {load1[0]:.1f} after. `python benchmarks/light_sampling.py` ({a.renders} renders per mode at "
             f"{a.spp} spp, t = 0, each scene's own window; module docstring: what each figure counts).", "",
             "| scene | H x W | variance, shadow rays to the sky too [rate_e^2] | variance, sky by BSDF rays | "
             "variance ratio | ratio at this spp (before / after) | mean difference (relative, z) | "
             "s per render (before / after) |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['size'][0]} x {r['size'][1]} | {r['mixed']['mean_var_rate_e2']:.4g} | "
                     f"{r['bsdf']['mean_var_rate_e2']:.4g} | {r['variance_ratio']:.2f}x | "
                     f"{r['mixed']['ratio']:.3f} / {r['bsdf']['ratio']:.3f} | "
                     f"{r['mean_difference_relative']:+.1e} ({r['mean_difference_z']:+.2f}) | "
                     f"{r['mixed']['median_s']:.3f} / {r['bsdf']['median_s']:.3f} |")
    write_report(a.out, "light_sampling", lines, rec)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
