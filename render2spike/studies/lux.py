"""Lux sweep: how well a rendered scene is recovered from spikes across light levels and noise models.

Rendering is linear in emitter power, so the irradiance of a scene at
illuminance ``L`` equals its rendering at the reference illuminance ``L0``
(``illuminance_lux`` in ``frames.json``) times ``L / L0`` exactly; one
rendering serves every light level (its Monte Carlo noise scales with it, and
was budgeted at ``L0``). For each (lux, model, seed) job the study converts
the frames to ``rate_e``, simulates the spike stream after a pre-roll
(:mod:`render2spike.studies.common`: default 2000 intervals = 0.1 s, so the
sensor starts the clip in its stationary state), reconstructs images at window
centres with every method (``recon.evaluate``'s registry: ``tfp``, ``tfp-dt``,
``tfi``, ``rsir:CKPT``, ...) and scores them against the clean rate at the
centre interval (PSNR/SSIM with :func:`recon.evaluate.psnr_ssim`, on the
scale of an ideal pixel's spikes per interval, ``lambda / theta``).

Also scored: the *noise-free window average* (the clean rate averaged over the
window; the ceiling set by motion blur alone). Error bars are the spread
(standard deviation, ddof = 1) of the per-seed means over seeds; window
centres and scene content are averaged inside each seed. Cells whose expected
light spikes per pixel per window fall below
:data:`~render2spike.studies.common.MIN_LIGHT_SPIKES` are flagged.

Jobs are independent and seeded, so they run the same sequentially or on a
Dask cluster (``client`` = a ``dask.distributed.Client``).
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sensor.errors import DependencyError, InputError
from sensor.io.fileio import provenance, write_json_atomic, write_text_atomic

from .common import (DEFAULT_PREROLL, MIN_LIGHT_SPIKES, NOISE_FREE_LABEL, clean_image, clean_window_average,
                     load_study_models, parse_model_spec, parse_study_methods, profile_for, pyplot,
                     reconstruct_all, save_figure, seed_spread, simulate_clip, unsettled_fraction, window_centers,
                     write_csv)

#: the methods of the old interface (any recon method string works)
STUDY_METHODS = ("tfp", "tfp-dt", "tfp-dt-denoised", "tfi", "rsir:CKPT")


@dataclass(frozen=True)
class SweepJob:
    """One cell of a sweep: frames scaled to ``lux``, simulated with ``model`` and ``seed``."""

    frames: str
    profile: str
    lux: float
    reference_lux: float
    model: str
    seed: int
    window: int
    centers: tuple
    methods: tuple
    preroll: int = DEFAULT_PREROLL
    emit_reference: bool = False


def reference_lux_of(frames_folder) -> float:
    """The scene illuminance [lux] the frames were rendered at (``illuminance_lux`` in the manifest)."""
    from sensor.io.frames import read_frames
    fs = read_frames(frames_folder)
    for key in ("illuminance_lux", "target_lux"):
        if key in fs.manifest:
            return float(fs.manifest[key])
    hdr = fs.read(0).header
    if "target_lux" in hdr:
        return float(hdr["target_lux"])
    raise InputError("the frames do not say at which illuminance they were rendered (no 'illuminance_lux' in "
                     "frames.json); pass --reference-lux", path=Path(frames_folder) / "frames.json",
                     field="illuminance_lux")


@functools.lru_cache(maxsize=4)
def _frames(folder: str):
    from sensor.io.frames import read_frames
    fs = read_frames(folder)
    return fs.phi_stack().astype(np.float32), np.asarray(fs.times_s, np.float64), fs.shape


def run_job(job: SweepJob) -> list[dict]:
    """Simulate and score one job; one row per (method, centre). Pure function of ``job``."""
    from recon.evaluate import psnr_ssim

    from sensor import photoelectron_rate


    t0 = time.perf_counter()
    phi, t, shape = _frames(job.frames)
    prof = profile_for(job.profile, shape, job.model)
    rate = photoelectron_rate(phi, prof) * np.float32(job.lux / job.reference_lux)
    spikes = simulate_clip(rate, t, prof, job.model, job.seed, job.preroll)
    methods = parse_study_methods(list(job.methods), job.window)
    load_study_models(methods)
    dark = float(np.mean(prof.dark_spike_rate)) * job.window
    unsettled = unsettled_fraction(rate[0], prof.threshold_e, job.preroll)
    rows = []
    for c in job.centers:
        gt = clean_image(rate, t, c, prof)
        avg = clean_window_average(rate, t, c, job.window, prof)
        common = {"lux": job.lux, "signal_e_per_interval": float(gt.mean() * prof.threshold_e),
                  "center": int(c), "light_spikes_per_window": float(avg.mean() * job.window),
                  "dark_spikes_per_window": dark, "unsettled_fraction": unsettled}
        imgs = reconstruct_all(methods, spikes, prof, c, job.window)
        lo, hi = c - job.window // 2, c - job.window // 2 + job.window
        rate_hz = float(spikes[max(lo, 0):hi].mean() / prof.interval_s)
        for label, pred in imgs.items():
            psnr, ssim = psnr_ssim(pred, gt)
            rows.append({**common, "model": job.model, "seed": job.seed, "method": label, "psnr_db": psnr,
                         "ssim": ssim, "spike_rate_hz": rate_hz})
        if job.emit_reference:
            psnr, ssim = psnr_ssim(avg, gt)
            rows.append({**common, "model": "noise-free", "seed": job.seed, "method": NOISE_FREE_LABEL,
                         "psnr_db": psnr, "ssim": ssim, "spike_rate_hz": float("nan")})
    for r in rows:
        r["job_seconds"] = time.perf_counter() - t0
    return rows


def plan_lux_sweep(frames, lux_values, models, seeds, *, profile="vidar-default", window=320, n_centers=3,
                   methods=("tfp", "tfp-dt", "tfp-dt-denoised"), reference_lux=None, preroll: int = DEFAULT_PREROLL) -> list[SweepJob]:
    """The jobs of a lux sweep (validated; nothing is simulated yet)."""
    from sensor.io.frames import read_frames
    from sensor.profile import SensorProfile
    from sensor.rates import n_intervals_spanned
    fs = read_frames(frames)
    ref = float(reference_lux) if reference_lux else reference_lux_of(frames)
    if not (0 < ref < float("inf")):
        raise InputError(f"the reference illuminance must be finite and > 0, got {ref!r}",
                         path=None if reference_lux else Path(frames) / "frames.json",
                         field="--reference-lux" if reference_lux else "illuminance_lux")
    for m in models:
        parse_model_spec(m)
        profile_for(profile, fs.shape, m)
    methods = tuple(methods) if not isinstance(methods, str) else tuple(x for x in methods.split(",") if x)
    parse_study_methods(list(methods), window)
    if any(not (0 < lx < float("inf")) for lx in lux_values):
        raise InputError(f"lux values must be finite and > 0, got {list(lux_values)}", field="--lux")
    if int(preroll) < 0:
        raise InputError(f"the pre-roll must be >= 0 intervals, got {preroll}", field="--preroll")
    prof = SensorProfile.load(profile)
    T = n_intervals_spanned(fs.times_s[0], fs.times_s[-1], prof.interval_s)
    try:
        centers = window_centers(T, window, n_centers)
    except InputError as exc:
        raise InputError(str(exc).split(" (")[0], path=frames, field="--window") from None
    jobs = []
    for lx in lux_values:
        for i, m in enumerate(models):
            for j, s in enumerate(seeds):
                jobs.append(SweepJob(str(Path(frames).resolve()), str(profile), float(lx), ref, m, int(s),
                                     int(window), centers, methods, int(preroll),
                                     emit_reference=(i == 0)))
    return jobs


def run_jobs(jobs: list, client=None, progress: bool = True, fn=run_job) -> list[dict]:
    """Run jobs sequentially (``client`` None) or on a Dask cluster; rows in job order."""
    from tqdm import tqdm
    if client is None:
        rows = []
        for j in tqdm(jobs, desc="study", unit="job", disable=not progress):
            rows.extend(fn(j))
        return rows
    try:
        from dask.distributed import as_completed
    except ImportError as exc:  # pragma: no cover
        raise DependencyError("Dask is not installed: pip install 'dask[distributed]'") from exc
    futures = client.map(fn, jobs, pure=False)
    index = {f.key: i for i, f in enumerate(futures)}
    results = [None] * len(jobs)
    for fut in tqdm(as_completed(futures), total=len(futures), desc="study (dask)", unit="job", disable=not progress):
        results[index[fut.key]] = fut.result()
    return [r for part in results for r in part]


def make_client(spec: str | None):
    """``None`` -> no cluster; ``local`` -> a LocalCluster on this machine; else a scheduler address."""
    if not spec:
        return None
    try:
        from dask.distributed import Client, LocalCluster
    except ImportError as exc:
        raise DependencyError("--dask needs Dask: pip install 'dask[distributed]'") from exc
    if spec == "local":
        import os
        return Client(LocalCluster(n_workers=os.cpu_count() or 1, threads_per_worker=1, processes=True,
                                   dashboard_address=None))
    return Client(spec)


def summarise(rows: list[dict]) -> list[dict]:
    """Per (lux, model, method): mean over seeds of the per-seed means, and their spread over seeds.

    ``psnr_sd`` / ``ssim_sd`` are the standard deviation (ddof = 1) of the per-seed means (NaN with one seed);
    ``few_light_spikes`` flags cells with fewer than MIN_LIGHT_SPIKES expected light spikes per pixel per window.
    """
    ps = seed_spread(rows, ("lux", "model", "method"), "psnr_db")
    ss = seed_spread(rows, ("lux", "model", "method"), "ssim")
    out = []
    for p, s in zip(ps, ss):
        sel = [r for r in rows if (r["lux"], r["model"], r["method"]) == (p["lux"], p["model"], p["method"])]
        light = float(np.mean([r["light_spikes_per_window"] for r in sel]))
        out.append({"lux": p["lux"], "signal_e_per_interval": float(np.mean([r["signal_e_per_interval"] for r in sel])),
                    "model": p["model"], "method": p["method"], "n_seeds": p["n_seeds"], "n": p["n"],
                    "psnr_db": p["mean"], "psnr_sd": p["sd"], "ssim": s["mean"], "ssim_sd": s["sd"],
                    "spike_rate_hz": float(np.mean([r["spike_rate_hz"] for r in sel])),
                    "light_spikes_per_window": light,
                    "dark_spikes_per_window": float(np.mean([r["dark_spikes_per_window"] for r in sel])),
                    "unsettled_fraction": float(np.mean([r["unsettled_fraction"] for r in sel])),
                    "few_light_spikes": bool(light < MIN_LIGHT_SPIKES)})
    return out


def warnings_of(summ: list[dict], window: int) -> list[str]:
    """One line per light level with too few light spikes, or with pixels not settled by the pre-roll."""
    out = []
    for lx in sorted({r["lux"] for r in summ}):
        r = next(x for x in summ if x["lux"] == lx)
        if r["few_light_spikes"]:
            out.append(f"{lx:g} lux: only {r['light_spikes_per_window']:.2g} expected light spikes per pixel per "
                       f"{window}-interval window (dark: {r['dark_spikes_per_window']:.2g}); scores there measure "
                       "quantisation and dark noise more than the method")
        if r["unsettled_fraction"] > 0.05:
            out.append(f"{lx:g} lux: {100 * r['unsettled_fraction']:.0f} % of pixels collect less than the threshold "
                       "over half the pre-roll, so their phase is not randomised (lengthen --preroll)")
    return out


def _fmt(v, sd, digits):
    return f"{v:.{digits}f}" + ("" if not np.isfinite(sd) else f" ± {sd:.{digits}f}")


def _signal_axis(ax, summ):
    """A secondary x axis in e- per interval (signal = lux * e-/interval per lux, linear in lux)."""
    k = np.mean([r["signal_e_per_interval"] / r["lux"] for r in summ])
    if not np.isfinite(k) or k <= 0:
        return
    sec = ax.secondary_xaxis("top", functions=(lambda x: x * k, lambda s: s / k))
    sec.set_xlabel("mean signal [e- per interval]")


def plot_vs_lux(path, summ, key, ylabel, title):
    """Mean of ``key`` vs lux per (model, method), error bars = sd over seeds, noise-free reference dashed."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.6))
    for m in sorted({r["model"] for r in summ if r["model"] != "noise-free"}):
        for meth in sorted({r["method"] for r in summ if r["model"] == m}):
            sel = sorted([r for r in summ if r["model"] == m and r["method"] == meth], key=lambda r: r["lux"])
            ax.errorbar([r["lux"] for r in sel], [r[key] for r in sel],
                        yerr=[0 if not np.isfinite(r[key.replace("_db", "") + "_sd"]) else
                              r[key.replace("_db", "") + "_sd"] for r in sel],
                        marker="o", capsize=3, label=f"{m} / {meth}")
    ref = sorted([r for r in summ if r["model"] == "noise-free"], key=lambda r: r["lux"])
    if ref:
        ax.plot([r["lux"] for r in ref], [r[key] for r in ref], "k--", label=NOISE_FREE_LABEL)
    ax.set_xscale("log")
    ax.set_xlabel("scene illuminance at the reference [lux]")
    ax.set_ylabel(ylabel)
    n_seeds = max(r["n_seeds"] for r in summ)
    ax.set_title(f"{title}\nerror bars: sd of per-seed means over {n_seeds} seed(s)", fontsize=9)
    _signal_axis(ax, summ)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return save_figure(fig, path)


def light_level_note(summ: list[dict], profile) -> list[str]:
    """Markdown lines explaining why TFP can lose PSNR at high light, with the numbers of this study.

    Each spike resets the pixel at the end of the interval in which its charge crossed the threshold
    theta, so a noiseless pixel collecting lambda e- per interval fires every ceil(theta / lambda)
    intervals: TFP reads 1 / ceil(theta / lambda) spikes per interval instead of lambda / theta. While
    theta / lambda is large the two agree; when it falls to a few intervals, neighbouring brightness
    levels collapse onto the steps 1/2, 1/3, 1/4, ... and PSNR against the true rate falls.
    """
    from sensor import SensorProfile
    theta = float(SensorProfile.load(profile).threshold_e)
    rows = ["## Reading the table: the light level", "",
            "Each spike resets the pixel at the end of the interval in which it crossed the threshold, so a "
            "noiseless pixel with lambda e-/interval fires every ceil(theta/lambda) intervals and TFP reads "
            "1/ceil(theta/lambda) instead of lambda/theta. At low light the two agree; once theta/lambda is a few "
            "intervals, bright pixels collapse onto the levels 1/2, 1/3, 1/4, ... and TFP's PSNR can fall as the "
            "light rises. `tfp-dt` corrects this dead time. For this study (theta = "
            f"{theta:g} e-):", "",
            "| lux | mean signal [e-/interval] | theta / signal [intervals] | ideal TFP / true rate at the mean signal |", "|---|---|---|---|"]
    seen = {}
    for r in summ:
        seen.setdefault(r["lux"], r["signal_e_per_interval"])
    for lx in sorted(seen):
        lam = float(seen[lx])
        if lam > 0:
            k = int(np.ceil(theta / lam - 1e-9))
            rows.append(f"| {lx:g} | {lam:.3g} | {theta / lam:.3g} | {(1.0 / k) / (lam / theta):.3f} |")
    return rows + [""]


def write_study(out_dir, rows: list[dict], jobs: list[SweepJob], title: str) -> list[Path]:
    """rows.csv, summary.csv, summary.md (models x lux per method, ± sd over seeds, warnings), psnr_vs_lux.png,
    ssim_vs_lux.png and study.json."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    summ = summarise(rows)
    paths = [write_csv(out_dir / "rows.csv", rows), write_csv(out_dir / "summary.csv", summ)]
    luxes = sorted({r["lux"] for r in summ})
    sig = {lx: next(r["signal_e_per_interval"] for r in summ if r["lux"] == lx) for lx in luxes}
    j0 = jobs[0]
    n_seeds = len({j.seed for j in jobs})
    lines = [f"# {title}", "",
             f"Frames: `{j0.frames}` rendered at {j0.reference_lux:g} lux; profile `{j0.profile}`; window {j0.window} "
             f"intervals; centres {list(j0.centers)}; seeds {sorted({j.seed for j in jobs})}; pre-roll {j0.preroll} "
             "intervals before the clip (phase randomised, see docs/studies.md). PSNR [dB] / SSIM against the clean "
             "rate at the window centre (scale: ideal spikes per interval, normalised by the reference's 99.5th "
             f"percentile). ± is the standard deviation of the per-seed means over {n_seeds} seed(s) (centres "
             "averaged inside each seed); none with one seed. The noise-free row is the clean rate averaged over "
             "the window: the ceiling set by motion blur alone.", ""]
    warns = warnings_of(summ, j0.window)
    if warns:
        lines += ["**Warnings**", ""] + [f"- {w}" for w in warns] + [""]
    models = [m for m in dict.fromkeys(j.model for j in jobs)]
    for meth in [m for m in dict.fromkeys(r["method"] for r in rows) if m != NOISE_FREE_LABEL]:
        lines += [f"## {meth}", "", "| model | " + " | ".join(f"{lx:g} lux ({sig[lx]:.3g} e-/int)" for lx in luxes)
                  + " |", "|---|" + "---|" * len(luxes)]
        for m in models + ["noise-free"]:
            cells = []
            for lx in luxes:
                want = NOISE_FREE_LABEL if m == "noise-free" else meth
                r = [x for x in summ if x["lux"] == lx and x["model"] == m and x["method"] == want]
                cells.append(f"{_fmt(r[0]['psnr_db'], r[0]['psnr_sd'], 2)} / {_fmt(r[0]['ssim'], r[0]['ssim_sd'], 3)}"
                             + (" ⚠" if r[0]["few_light_spikes"] and m != "noise-free" else "") if r else "")
            if any(cells):
                lines.append(f"| {m} | " + " | ".join(cells) + " |")
        lines.append("")
    lines.append("⚠: fewer than %g expected light spikes per pixel per window." % MIN_LIGHT_SPIKES)
    lines += [""] + light_level_note(summ, j0.profile)
    paths.append(write_text_atomic(out_dir / "summary.md", "\n".join(lines) + "\n"))
    paths.append(plot_vs_lux(out_dir / "psnr_vs_lux.png", summ, "psnr_db", "PSNR [dB]", title))
    paths.append(plot_vs_lux(out_dir / "ssim_vs_lux.png", summ, "ssim", "SSIM", title))
    paths.append(write_json_atomic(out_dir / "study.json", {"title": title, "jobs": [j.__dict__ for j in jobs],
                                                            "warnings": warns, "provenance": provenance()}))
    return paths
