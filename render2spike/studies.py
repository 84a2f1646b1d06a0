"""Studies: how well can a scene be recovered from spikes, across light levels and noise models.

Lux sweep
---------
Rendering is linear in emitter power, so the irradiance of a scene at
illuminance ``L`` equals its rendering at the reference illuminance ``L0``
(``illuminance_lux`` in ``frames.json``) times ``L / L0`` exactly; one
rendering serves every light level (its Monte Carlo noise scales with it, and
was budgeted at ``L0``). For each (lux, model, seed) job the study converts
the frames to ``rate_e``, simulates the spike stream, reconstructs images at
window centres and scores them against the clean rate at the centre interval
(PSNR/SSIM with :func:`recon.evaluate.psnr_ssim`, on the scale of an ideal
pixel's spikes per interval, ``lambda / theta``).

Jobs are independent and seeded, so they run the same sequentially or on a
Dask cluster (``client`` = a ``dask.distributed.Client``).
"""

from __future__ import annotations

import csv
import io
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sensor.errors import DependencyError, InputError
from sensor.fileio import atomic_path, provenance, write_json_atomic, write_text_atomic

STUDY_METHODS = ("tfp", "tfp-dt", "tfi")


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


def reference_lux_of(frames_folder) -> float:
    """The scene illuminance [lux] the frames were rendered at (``illuminance_lux`` in the manifest)."""
    from sensor.frames import read_frames
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


def run_job(job: SweepJob) -> list[dict]:
    """Simulate and score one job; returns one row per (method, centre). Pure function of ``job``."""
    from recon.classic import tfi, tfp, tfp_deadtime
    from recon.evaluate import psnr_ssim

    from sensor import SensorProfile, photoelectron_rate, simulate
    from sensor.frames import read_frames
    from sensor.rates import interval_rates

    t0 = time.perf_counter()
    fs = read_frames(job.frames)
    prof = SensorProfile.load(job.profile)
    if prof.shape != fs.shape:
        if prof.height < fs.shape[0] or prof.width < fs.shape[1]:
            raise InputError(f"profile {prof.name} ({prof.height}x{prof.width}) is smaller than the frames "
                             f"{fs.shape}", field="--profile")
        top, left = (prof.height - fs.shape[0]) // 2, (prof.width - fs.shape[1]) // 2
        prof = prof.window(top, left, *fs.shape)
    scale = job.lux / job.reference_lux
    rate = photoelectron_rate(fs.phi_stack(), prof) * np.float32(scale)
    t = fs.times_s
    spikes = simulate(rate, prof, job.model, seed=job.seed, t_s=t)
    rows = []
    for c in job.centers:
        gt = interval_rates(rate, t, n_intervals=1, m0=int(c))[0] / np.float32(prof.threshold_e)
        for meth in job.methods:
            if meth == "tfp":
                pred = tfp(spikes, job.window, int(c))
            elif meth == "tfp-dt":
                pred = tfp_deadtime(spikes, prof, job.window, int(c)) / np.float32(prof.threshold_e)
            elif meth == "tfi":
                pred = tfi(spikes, int(c))
            else:
                from sensor.errors import UnknownMethodError
                raise UnknownMethodError("study method", meth, STUDY_METHODS)
            psnr, ssim = psnr_ssim(pred, gt)
            rows.append({"lux": job.lux, "model": job.model, "seed": job.seed, "method": meth, "center": int(c),
                         "psnr_db": psnr, "ssim": ssim, "spike_rate_hz": float(spikes.mean() / prof.interval_s),
                         "signal_e_per_interval": float(gt.mean() * prof.threshold_e)})
    for r in rows:
        r["job_seconds"] = time.perf_counter() - t0
    return rows


def plan_lux_sweep(frames, lux_values, models, seeds, *, profile="vidar-default", window=320, n_centers=3,
                   methods=("tfp", "tfp-dt"), reference_lux=None) -> list[SweepJob]:
    """The jobs of a lux sweep (validated; nothing is simulated yet)."""
    from sensor.frames import read_frames
    from sensor.models import MODELS
    from sensor.errors import UnknownMethodError
    from sensor.rates import n_intervals_spanned
    from sensor.profile import SensorProfile
    fs = read_frames(frames)
    ref = float(reference_lux) if reference_lux else reference_lux_of(frames)
    if not (0 < ref < float("inf")):
        raise InputError(f"the reference illuminance must be finite and > 0, got {ref!r}",
                         path=None if reference_lux else Path(frames) / "frames.json",
                         field="--reference-lux" if reference_lux else "illuminance_lux")
    for m in models:
        if m not in MODELS:
            raise UnknownMethodError("spike model", m, MODELS)
    for m in methods:
        if m not in STUDY_METHODS:
            raise UnknownMethodError("study method", m, STUDY_METHODS)
    if any(not (0 < lx < float("inf")) for lx in lux_values):
        raise InputError(f"lux values must be finite and > 0, got {list(lux_values)}", field="--lux")
    prof = SensorProfile.load(profile)
    T = n_intervals_spanned(fs.times_s[0], fs.times_s[-1], prof.interval_s)
    if T < window:
        raise InputError(f"the frames span {T} intervals, fewer than the window of {window}; render a longer "
                         "clip or pass a smaller --window", path=frames, field="--window")
    half = window // 2
    centers = tuple(int(c) for c in np.linspace(half, T - (window - half), n_centers).round())
    return [SweepJob(str(Path(frames).resolve()), str(profile), float(lx), ref, m, int(s), int(window), centers,
                     tuple(methods))
            for lx in lux_values for m in models for s in seeds]


def run_jobs(jobs: list[SweepJob], client=None, progress: bool = True) -> list[dict]:
    """Run jobs sequentially (``client`` None) or on a Dask cluster; rows in job order."""
    from tqdm import tqdm
    if client is None:
        rows = []
        for j in tqdm(jobs, desc="study", unit="job", disable=not progress):
            rows.extend(run_job(j))
        return rows
    try:
        from dask.distributed import as_completed
    except ImportError as exc:  # pragma: no cover
        raise DependencyError("Dask is not installed: pip install 'dask[distributed]'") from exc
    futures = client.map(run_job, jobs, pure=False)
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
    """Mean PSNR/SSIM over seeds and centres per (lux, model, method)."""
    keys = sorted({(r["lux"], r["model"], r["method"]) for r in rows})
    out = []
    for lx, m, meth in keys:
        sel = [r for r in rows if (r["lux"], r["model"], r["method"]) == (lx, m, meth)]
        out.append({"lux": lx, "model": m, "method": meth, "n": len(sel),
                    "psnr_db": float(np.mean([r["psnr_db"] for r in sel])),
                    "psnr_sd": float(np.std([r["psnr_db"] for r in sel])),
                    "ssim": float(np.mean([r["ssim"] for r in sel])),
                    "spike_rate_hz": float(np.mean([r["spike_rate_hz"] for r in sel])),
                    "signal_e_per_interval": float(np.mean([r["signal_e_per_interval"] for r in sel]))})
    return out


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
    """CSV of every row, a Markdown table (models x lux per method), a PNG plot and a JSON record."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    summ = summarise(rows)
    paths = []
    for name, data in (("rows.csv", rows), ("summary.csv", summ)):
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=list(data[0].keys()))
        w.writeheader()
        w.writerows(data)
        paths.append(write_text_atomic(out_dir / name, buf.getvalue()))
    luxes = sorted({r["lux"] for r in summ})
    lines = [f"# {title}", "", f"Frames: `{jobs[0].frames}` rendered at {jobs[0].reference_lux:g} lux; profile "
             f"`{jobs[0].profile}`; window {jobs[0].window} intervals; centres {list(jobs[0].centers)}; seeds "
             f"{sorted({j.seed for j in jobs})}. PSNR [dB] / SSIM against the clean rate at the window centre "
             "(scale: ideal spikes per interval, normalised by the reference's 99.5th percentile).", ""]
    for meth in sorted({r["method"] for r in summ}):
        lines += [f"## {meth}", "", "| model | " + " | ".join(f"{lx:g} lux" for lx in luxes) + " |",
                  "|---|" + "---|" * len(luxes)]
        for m in sorted({r["model"] for r in summ}):
            cells = []
            for lx in luxes:
                r = [x for x in summ if x["lux"] == lx and x["model"] == m and x["method"] == meth]
                cells.append(f"{r[0]['psnr_db']:.2f} / {r[0]['ssim']:.3f}" if r else "")
            lines.append(f"| {m} | " + " | ".join(cells) + " |")
        lines.append("")
    lines += light_level_note(summ, jobs[0].profile)
    paths.append(write_text_atomic(out_dir / "summary.md", "\n".join(lines)))

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for m in sorted({r["model"] for r in summ}):
        for meth in sorted({r["method"] for r in summ}):
            sel = sorted([r for r in summ if r["model"] == m and r["method"] == meth], key=lambda r: r["lux"])
            ax.errorbar([r["lux"] for r in sel], [r["psnr_db"] for r in sel], yerr=[r["psnr_sd"] for r in sel],
                        marker="o", capsize=3, label=f"{m} / {meth}")
    ax.set_xscale("log")
    ax.set_xlabel("scene illuminance [lux]")
    ax.set_ylabel("PSNR [dB]")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(out_dir / "psnr_vs_lux.png") as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)
    paths.append(out_dir / "psnr_vs_lux.png")
    paths.append(write_json_atomic(out_dir / "study.json", {"title": title, "jobs": [j.__dict__ for j in jobs],
                                                            "provenance": provenance()}))
    return paths
