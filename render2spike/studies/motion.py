"""Controlled-motion sweep: reconstruction quality and blur width against a scene parameter (e.g. speed).

For each value of the swept parameter (a named scene parameter such as the
bundled scenes' ``speed_px_per_ms``, or any numeric dotted scene key) the
scene is rendered once (cached by content hash under ``OUT/renders``); for
each model and seed the spike stream is simulated after the pre-roll, every
method reconstructs the window at each centre, and is scored against the
clean image of the centre interval (PSNR/SSIM, :func:`recon.evaluate.psnr_ssim`).
The noise-free window average (clean rate averaged over the window) is scored
too: the ceiling set by motion blur alone.

Blur width
----------
The 10-90 % edge spread [pixels] along the motion. Lines are taken along the
motion (image rows for ``x``, columns for ``y``, circles around the image
centre sampled at 1 px of arc for ``polar``, i.e. a disk spinning about the
optical axis). On each line the edge is where the clean image changes most
around the centre (``|clean(c + W/4) - clean(c - W/4)|``, W the window,
smoothed by a 1 px Gaussian against render noise: a moving edge, not static
texture; kept if above 6x its median, the level of the keyframes' render
noise on static pixels) and the (smoothed) clean image has a step there. The profiles of every
image around those edges (``radius`` px each side, sign-flipped so all rise)
are averaged into one edge spread function per image; the width is the
distance between its 10 % and 90 % crossings nearest the edge (linear
interpolation; levels: the lowest value before the edge and the highest after). A box blur of ``w`` px gives 0.8 w, so the noise-free window
average of a translation at ``v`` px/ms over a window of ``D`` ms reads about
0.8 v D (plus the pixel's own edge width, under a pixel). Blur wider than the
object (or than ``radius``) cannot be measured this way: keep ``v D`` below
the object's size.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from sensor.errors import InputError
from sensor.io.fileio import provenance, write_json_atomic, write_text_atomic

from .common import (DEFAULT_PREROLL, NOISE_FREE_LABEL, nanmean, clean_image, clean_window_average, load_study_models,
                     parse_model_spec, parse_study_methods, profile_for, pyplot, reconstruct_all, save_figure,
                     seed_spread, simulate_clip, window_centers, write_csv)

CLEAN_LABEL = "clean (centre interval)"


# ------------------------------------------------------------------------------------------ blur width
def motion_lines(img, axis: str) -> list[np.ndarray]:
    """1-D profiles of ``img`` along the motion: rows (x), columns (y) or circles about the centre (polar)."""
    img = np.asarray(img, np.float64)
    if axis == "x":
        return list(img)
    if axis == "y":
        return list(img.T)
    if axis == "polar":
        from scipy.ndimage import map_coordinates
        H, W = img.shape
        cy, cx = (H - 1) / 2.0, (W - 1) / 2.0
        out = []
        for r in range(3, int(min(H, W) / 2) - 1):
            n = int(2 * np.pi * r)
            th = np.arange(n) / r
            out.append(map_coordinates(img, [cy + r * np.sin(th), cx + r * np.cos(th)], order=1, mode="nearest"))
        return out
    raise InputError(f"blur axis must be x, y or polar; got '{axis}'", field="--blur-axis")


def _width_10_90(esf: np.ndarray) -> float:
    """10-90 % rise [samples] of a (noisy) rising edge profile centred in ``esf``.

    Levels: the lowest value left of the centre and the highest right of it (the plateaus next to the edge;
    objects are often narrower than the profile, so its ends are other structures)."""
    c = len(esf) // 2
    lo, hi = float(np.min(esf[:c + 1])), float(np.max(esf[c:]))
    if not hi - lo > 1e-12:
        return float("nan")
    n = (esf - lo) / (hi - lo)
    # the 50 % crossing nearest the centre
    cross = [i for i in range(len(n) - 1) if (n[i] - 0.5) * (n[i + 1] - 0.5) <= 0 and n[i] != n[i + 1]]
    if not cross:
        return float("nan")
    i50 = min(cross, key=lambda i: abs(i - c))

    def walk(level, step):
        i = i50 if step < 0 else i50 + 1
        while 0 <= i + step < len(n) and ((n[i] >= level) if step < 0 else (n[i] < level)):
            i += step
        j = i - step  # the neighbour on the other side of the level
        a, b = n[i], n[j]
        return i + (level - a) / (b - a) * (j - i) if b != a else float(i)
    return float(walk(0.9, +1) - walk(0.1, -1))


def edge_spread(images: dict, clean, moving, axis: str, radius: int = 20, min_lines: int = 3) -> dict:
    """{label: 10-90 % edge spread [px] along the motion} for each image, and ``lines_used``.

    ``moving`` is the clean image's change around the centre (clean(c + d) - clean(c - d)): on each line the
    edge is the pixel where it is largest (a moving edge, not static texture), required to be a step of the
    clean image (|gradient| > 10 % of white). Profiles of ``radius`` px either side, sign-flipped to rise,
    are averaged over lines into one edge spread function per image. See the module docstring.
    """
    from scipy.ndimage import gaussian_filter
    from scipy.ndimage import gaussian_filter1d
    ref = [gaussian_filter1d(ln, 1.0, mode="wrap" if axis == "polar" else "nearest")  # render noise off the picks
           for ln in motion_lines(clean, axis)]
    mov_img = gaussian_filter(np.abs(np.asarray(moving, np.float64)), 1.0)
    mov = motion_lines(mov_img, axis)
    white = float(np.percentile(np.asarray(clean), 99.5)) or 1.0
    # static pixels differ only by the keyframes' render noise: keep changes well above its typical level
    floor = max(0.02 * white, 6.0 * float(np.median(mov_img)))
    picks = []
    for j, (r, d) in enumerate(zip(ref, mov)):
        L = len(r)
        if L < 2 * radius + 3:
            continue
        score = np.abs(d).copy()
        if axis != "polar":
            score[:radius] = 0
            score[L - radius:] = 0
        k = int(np.argmax(score))
        if score[k] < floor:
            continue
        # anchor on the steepest point of the clean edge near there (the smoothed change is a broad band)
        near = np.arange(k - 3, k + 3) % L
        grad = r[(near + 1) % L] - r[near]  # the edge lies between k and k + 1
        k = int(near[np.argmax(np.abs(grad))])
        if axis != "polar" and not radius <= k < L - radius:
            continue
        g = r[(k + 1) % L] - r[k]
        if score[k] < floor or abs(g) < 0.05 * white:
            continue
        picks.append((j, k, np.sign(g)))
    out = {"lines_used": len(picks)}
    for label, img in images.items():
        if len(picks) < min_lines:
            out[label] = float("nan")
            continue
        lines = motion_lines(img, axis)
        esf = np.mean([sgn * lines[j][np.arange(k - radius + 1, k + radius + 1) % len(lines[j])]
                       for j, k, sgn in picks], axis=0)
        out[label] = _width_10_90(esf)
    return out


# ------------------------------------------------------------------------------------------ the sweep
def parse_param(text: str) -> tuple[str, list[float]]:
    """``KEY=v1,v2,...`` -> (KEY, [v1, v2, ...])."""
    key, sep, vals = str(text).partition("=")
    if not sep or not key.strip():
        raise InputError(f"expected KEY=v1,v2,... got '{text}'", field="--param")
    try:
        values = [float(v) for v in vals.split(",") if v.strip()]
    except ValueError:
        raise InputError(f"values of '{key}' must be numbers, got '{vals}'", field="--param") from None
    if not values:
        raise InputError(f"no values for '{key}'", field="--param")
    if len(set(values)) != len(values):
        raise InputError(f"values of '{key}' repeat ({vals}); give each value once", field="--param")
    return key.strip(), values


def _lookup(data, key: str):
    node = data
    for part in key.split("."):
        if isinstance(node, list):
            idx = int(part) if part.lstrip("-").isdigit() else next(
                (i for i, el in enumerate(node) if isinstance(el, dict) and el.get("name") == part), None)
            if idx is None or not -len(node) <= idx < len(node):
                return None
            node = node[idx]
        elif isinstance(node, dict) and part in node:
            node = node[part]
        else:
            return None
    return node


def check_param(scene, key: str) -> str:
    """Validate that ``key`` is a named scene parameter or a numeric scene key; returns the blur axis it implies."""
    params = scene.data.get("parameters") or {}
    if key in params:
        return params[key].get("blur_axis", "x")
    v = _lookup(scene.data, key)
    if not isinstance(v, (int, float)) or isinstance(v, bool):
        names = ", ".join(sorted(params)) or "none"
        raise InputError(f"'{key}' is neither a named parameter of the scene ({names}) nor a numeric scene key "
                         f"(found {v!r})", path=scene.path, field="--param")
    return "x"


def render_value(scene, sets, key, value, out_dir, lux=None, duration_s=None, progress=True, log=print):
    """Render the scene with ``key=value`` under ``out_dir/renders/<content hash>``; returns the frames folder."""
    from render2spike.render.job import render_scene
    from render2spike.render.scene import load_scene
    sc = load_scene(scene, list(sets) + [f"{key}={value!r}"], lux=lux, duration_s=duration_s)
    folder = Path(out_dir) / "renders" / sc.content_hash({"study": "motion"})
    render_scene(sc, folder, progress=progress, log=log)
    return folder, sc


def run_motion_study(scene, param: str, values, out, *, methods="tfp,tfp-dt,tfp-dt-denoised", models=("elssim",), seeds=(0, 1, 2),
                     lux=None, duration_s=None, sets=(), profile=None, window=320, n_centers=1,
                     preroll=DEFAULT_PREROLL, blur_axis="auto", edge_radius=20, progress=True, log=print) -> dict:
    """Run the sweep and write rows.csv, summary.csv, summary.md, {psnr,ssim,blur}_vs_<param>.png, strip.png."""
    from recon.evaluate import psnr_ssim

    from render2spike.render.scene import load_scene
    from sensor import photoelectron_rate
    from sensor.io.frames import read_frames
    from sensor.rates import n_intervals_spanned

    out = Path(out)
    sc0 = load_scene(scene, list(sets), lux=lux, duration_s=duration_s)
    axis = check_param(sc0, param) if blur_axis == "auto" else blur_axis
    motion_lines(np.zeros((4, 4)), axis)  # validates the axis
    meths = parse_study_methods(methods, window)
    load_study_models(meths)
    for m in models:
        parse_model_spec(m)
    for v in values:  # every value's scene is checked before the first render (and before OUT is made)
        scv = load_scene(scene, list(sets) + [f"{param}={v!r}"], lux=lux, duration_s=duration_s)
        # the clip must hold a whole window: refused now, not after the render
        window_centers(n_intervals_spanned(0.0, scv.duration_s, scv.profile.interval_s), window, n_centers)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rows, strips, renders = [], [], []
    for v in values:
        folder, sc = render_value(scene, sets, param, v, out, lux, duration_s, progress, log)
        renders.append({"value": v, "frames": str(folder), "scene_hash": sc.content_hash()})
        fs = read_frames(folder)
        phi, t = fs.phi_stack().astype(np.float32), np.asarray(fs.times_s)
        T = n_intervals_spanned(t[0], t[-1], sc.profile.interval_s)
        centers = window_centers(T, window, n_centers)
        for mi, m in enumerate(models):
            prof = profile_for(profile or sc.profile, fs.shape, m)
            rate = photoelectron_rate(phi, prof).astype(np.float32)
            for s in seeds:
                spikes = simulate_clip(rate, t, prof, m, s, preroll)
                for c in centers:
                    gt = clean_image(rate, t, c, prof)
                    avg = clean_window_average(rate, t, c, window, prof)
                    imgs = reconstruct_all(meths, spikes, prof, c, window)
                    d = max(window // 4, 1)
                    moving = clean_image(rate, t, min(c + d, T - 1), prof) - clean_image(rate, t, max(c - d, 0), prof)
                    blur = edge_spread({**imgs, NOISE_FREE_LABEL: avg, CLEAN_LABEL: gt}, gt, moving, axis,
                                       edge_radius)
                    base = {param: v, "center": int(c), "edge_lines": blur["lines_used"],
                            "clean_blur_px": blur[CLEAN_LABEL]}
                    for label, img in imgs.items():
                        p, q = psnr_ssim(img, gt)
                        rows.append({**base, "model": m, "seed": s, "method": label, "psnr_db": p, "ssim": q,
                                     "blur_px": blur[label]})
                    if mi == 0:
                        p, q = psnr_ssim(avg, gt)
                        rows.append({**base, "model": "noise-free", "seed": s, "method": NOISE_FREE_LABEL,
                                     "psnr_db": p, "ssim": q, "blur_px": blur[NOISE_FREE_LABEL]})
                    if mi == 0 and s == seeds[0] and c == centers[len(centers) // 2]:
                        strips.append((v, gt, avg, imgs))
    if not rows:
        raise InputError("the sweep produced no rows", field="--param")
    return write_motion_study(out, rows, strips, param, axis, {
        "scene": str(sc0.path), "param": param, "values": list(values), "methods": [m.label for m in meths],
        "models": list(models), "seeds": list(seeds), "window": window, "preroll": preroll, "blur_axis": axis,
        "edge_radius": edge_radius, "renders": renders, "seconds": time.perf_counter() - t0,
        "provenance": provenance(stage="study motion")})


def summarise_motion(rows, param):
    """Per (value, model, method): mean over seeds and sd of the per-seed means, for PSNR, SSIM and blur."""
    group = (param, "model", "method")
    out = []
    parts = {k: seed_spread(rows, group, k) for k in ("psnr_db", "ssim", "blur_px")}
    for i, p in enumerate(parts["psnr_db"]):
        out.append({param: p[param], "model": p["model"], "method": p["method"], "n_seeds": p["n_seeds"],
                    "psnr_db": p["mean"], "psnr_sd": p["sd"], "ssim": parts["ssim"][i]["mean"],
                    "ssim_sd": parts["ssim"][i]["sd"], "blur_px": parts["blur_px"][i]["mean"],
                    "blur_sd": parts["blur_px"][i]["sd"]})
    return out


def _plot(path, summ, param, key, ylabel, title, unit):
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    sd_key = {"psnr_db": "psnr_sd", "ssim": "ssim_sd", "blur_px": "blur_sd"}[key]
    for m in sorted({r["model"] for r in summ if r["model"] != "noise-free"}):
        for meth in sorted({r["method"] for r in summ if r["model"] == m}):
            sel = sorted([r for r in summ if r["model"] == m and r["method"] == meth], key=lambda r: r[param])
            ax.errorbar([r[param] for r in sel], [r[key] for r in sel],
                        yerr=[r[sd_key] if np.isfinite(r[sd_key]) else 0 for r in sel], marker="o", capsize=3,
                        label=f"{m} / {meth}")
    ref = sorted([r for r in summ if r["model"] == "noise-free"], key=lambda r: r[param])
    ax.plot([r[param] for r in ref], [r[key] for r in ref], "k--", marker="s", label=NOISE_FREE_LABEL)
    ax.set_xlabel(f"{param}" + (f" [{unit}]" if unit else ""))
    ax.set_ylabel(ylabel)
    n = max(r["n_seeds"] for r in summ)
    ax.set_title(f"{title}\nerror bars: sd of per-seed means over {n} seed(s)", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return save_figure(fig, path)


def write_strip(path, strips, param):
    """Image strip: one row per swept value; clean, noise-free window average, then each method."""
    from recon.imageio import show_image_row, white_level
    plt = pyplot()
    labels = [CLEAN_LABEL, NOISE_FREE_LABEL] + list(strips[0][3])
    H, W = strips[0][1].shape
    fig, axes = plt.subplots(len(strips), len(labels), figsize=(1.9 * len(labels), 1.9 * H / W * len(strips) + 0.5),
                             squeeze=False)
    for i, (v, gt, avg, imgs) in enumerate(strips):
        wl = white_level(gt, 99.5)
        panels = list(zip(labels, [gt, avg] + [imgs[k] for k in imgs]))
        show_image_row(axes[i], panels, wl, titles=i == 0, ylabel=f"{param}\n= {v:g}")
    fig.tight_layout()
    return save_figure(fig, path)


def write_motion_study(out: Path, rows, strips, param, axis, info) -> dict:
    summ = summarise_motion(rows, param)
    write_csv(out / "rows.csv", rows)
    write_csv(out / "summary.csv", summ)
    unit = "px/ms" if "px_per_ms" in param else ""
    short = param.split(".")[-1]
    title = f"{Path(info['scene']).stem}: quality vs {short}"
    plots = {k: _plot(out / f"{k.split('_')[0]}_vs_{short}.png", summ, param, k, lab, title, unit)
             for k, lab in (("psnr_db", "PSNR [dB]"), ("ssim", "SSIM"),
                            ("blur_px", f"10-90 % edge width along the motion ({axis}) [px]"))}
    strip = write_strip(out / "strip.png", strips, short)
    values = sorted({r[param] for r in summ})
    lines = [f"# Motion sweep: {info['scene']}", "",
             f"Swept `{param}` over {values}; window {info['window']} intervals; pre-roll {info['preroll']} "
             f"intervals; seeds {info['seeds']}. Scores against the clean image of the centre interval; ± is the sd "
             "of the per-seed means. Blur: 10-90 % edge spread along the motion "
             f"({axis}) [px], averaged over the moving edges; the clean image's own edge reads "
             f"{nanmean([r['clean_blur_px'] for r in rows]):.2f} px.", "",
             f"| {short} | model | method | PSNR [dB] | SSIM | blur [px] |", "|---|---|---|---|---|---|"]

    def f(v, sd, d):
        return f"{v:.{d}f}" + (f" ± {sd:.{d}f}" if np.isfinite(sd) else "")
    for r in sorted(summ, key=lambda r: (r[param], r["model"] == "noise-free", r["model"], r["method"])):
        lines.append(f"| {r[param]:g} | {r['model']} | {r['method']} | {f(r['psnr_db'], r['psnr_sd'], 2)} | "
                     f"{f(r['ssim'], r['ssim_sd'], 3)} | {f(r['blur_px'], r['blur_sd'], 2)} |")
    lines += ["", "![strip](strip.png)", ""]
    write_text_atomic(out / "summary.md", "\n".join(lines))
    write_json_atomic(out / "study.json", info)
    return {"summary": summ, "plots": {k: str(v) for k, v in plots.items()}, "strip": str(strip),
            "table": str(out / "summary.md")}
