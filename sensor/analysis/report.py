"""The realism report: its result and how it is written (CSV, PNG, JSON and Markdown)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sensor.analysis.statistics import DISTANCE_MEANING
from sensor.io.fileio import provenance


@dataclass
class RealismResult:
    rows: list
    distances: dict
    notes: dict = field(default_factory=dict)

    def summary(self) -> dict:
        return {"distance_meaning": DISTANCE_MEANING, "distances": self.distances, **self.notes}


CSV_COLUMNS = ("source", "statistic", "bin", "bin_lo", "bin_hi", "value", "se", "n_pixels", "n_samples")


def write_csv(path, rows):
    import csv
    import io

    from sensor.io.fileio import write_text_atomic
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=CSV_COLUMNS, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: (f"{r[k]:.6g}" if isinstance(r[k], float) else r[k]) for k in CSV_COLUMNS})
    return write_text_atomic(path, buf.getvalue())


def plot(result: RealismResult, path, title: str = ""):
    """One PNG: a panel per statistic, real (black) against each model."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sensor.io.fileio import atomic_path
    rows = result.rows
    sources = list(dict.fromkeys(r["source"] for r in rows))
    real_stats = {r["statistic"] for r in rows if r["source"] == "real"}
    fano = sorted((st for st in real_stats if st.startswith("fano_w")), key=lambda st: int(st[6:]))
    panels = [st for st in ("isi_cv", "isi_lag1") if st in real_stats] + fano + ["rate_hist", "outliers"]
    ncol = 3
    nrow = int(np.ceil(len(panels) / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.2 * ncol, 3.0 * nrow))
    axes = np.atleast_1d(axes).ravel()
    colors = {src: ("k" if src == "real" else f"C{i}") for i, src in enumerate(sources)}
    names = {"isi_cv": "ISI CV", "isi_lag1": "lag-1 ISI correlation", "rate_hist": "pixels per rate bin",
             "outliers": "dark / hot pixels"}
    for ax, st in zip(axes, panels):
        if st == "outliers":
            labels = ["dark_fraction", "hot_fraction", "rate_q0.001", "rate_q0.999"]
            width = 0.8 / max(len(sources), 1)
            for j, src in enumerate(sources):
                v = {r["bin"]: r for r in rows if r["source"] == src and r["statistic"] == st}
                x = np.arange(len(labels)) + (j - (len(sources) - 1) / 2) * width
                ax.bar(x, [v[b]["value"] if b in v else np.nan for b in labels], width,
                       yerr=[v[b]["se"] if b in v else 0 for b in labels], color=colors[src], label=src)
            ax.set_xticks(np.arange(len(labels)), ["dark frac", "hot frac", "rate q0.1%", "rate q99.9%"], fontsize=7)
            ax.set_yscale("log")
            ax.set_ylim(bottom=1e-5)
        else:
            for src in sources:
                rr = [r for r in rows if r["source"] == src and r["statistic"] == st]
                if not rr:
                    continue
                lo = np.array([r["bin_lo"] for r in rr])
                hi = np.array([r["bin_hi"] for r in rr])
                x = np.where(lo > 0, np.sqrt(np.maximum(lo, 1e-12) * hi), hi / 2)
                v = np.array([r["value"] for r in rr])
                e = np.array([r["se"] for r in rr])
                if st == "rate_hist":  # log axis: leave out empty bins, keep error bars above zero
                    v = np.where(v > 0, v, np.nan)
                    e = np.vstack([np.minimum(e, 0.9 * np.nan_to_num(v)), e])
                ax.errorbar(x, v, yerr=e, color=colors[src],
                            marker="o" if src == "real" else ".", ms=4, lw=1.6 if src == "real" else 1.0,
                            capsize=2, label=src)
            ax.set_xscale("log")
            ax.set_xlabel("spikes per interval" if st == "rate_hist" else "mean ISI [intervals]")
            if st == "rate_hist":
                ax.set_yscale("log")
        ax.set_title(names.get(st, st.replace("fano_w", "Fano factor, window ") + (" intervals"
                                                                                 if st.startswith("fano") else "")),
                     fontsize=9)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    for ax in axes[len(panels):]:
        ax.axis("off")
    leg = [f"{s} (D = {result.distances[s]['D']:.1f})" if s in result.distances else s for s in sources]
    handles = [plt.Line2D([], [], color=colors[s], marker="o", lw=1.5) for s in sources]
    fig.legend(handles, leg, loc="lower center", ncol=len(sources), fontsize=8, frameon=False)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0.05, 1, 0.97 if title else 1))
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=72)
    plt.close(fig)
    return path


def markdown(result: RealismResult, recording: str = "") -> str:
    lines = [f"# Realism report{': ' + recording if recording else ''}", ""]
    rec = result.notes.get("recording", {})
    if rec:
        lines += [f"{rec['intervals']} intervals of {rec['height']} x {rec['width']} pixels, mean "
                  f"{rec['mean_rate_per_interval']:.4f} spikes per pixel per interval; profile "
                  f"`{result.notes.get('profile')}`, seed {result.notes.get('seed')}.", ""]
    stats = sorted({g for d in result.distances.values() for g in d["per_statistic"]})
    lines += ["| model | D | " + " | ".join(stats) + " |", "|---|---|" + "---|" * len(stats)]
    for m, d in result.distances.items():
        lines.append(f"| {m} | {d['D']:.2f} | " + " | ".join(f"{d['per_statistic'][g]:.2f}" if g in
                                                            d["per_statistic"] else "undefined" for g in stats)
                     + " |")
    undefined = {m: d["statistics_undefined"] for m, d in result.distances.items() if d["statistics_undefined"]}
    if undefined:
        lines += ["", "A statistic is *undefined* for a model when no bin of it can be computed (e.g. the lag-1 "
                  "correlation when every ISI of a pixel is the same, as in the deterministic `ideal` model); "
                  "D is then the mean over the remaining statistics: "
                  + "; ".join(f"`{m}`: {', '.join(v)}" for m, v in undefined.items()) + "."]
    fit = result.notes.get("fit")
    if fit:
        dark_txt = (f"dark-current map x{fit['dark_scale']:.3g} +- {fit['dark_scale_sd']:.2g} of its dark firing "
                    f"rate (mean {fit.get('dark_current_e_mean', 0.0):.3g} e- per interval)"
                    if fit.get("dark") == "current" else
                    f"dark-rate map x{fit['dark_scale']:.3g} +- {fit['dark_scale_sd']:.2g} (mean "
                    f"{fit['dark_rate_mean_per_interval']:.3g} dark events per interval)")
        lines += ["", f"**Fit.** {dark_txt}, threshold "
                  f"x{fit['threshold_scale']:.3g} +- {fit['threshold_scale_sd']:.2g} (theta = {fit['threshold_e']:.4g} "
                  f"e-); +- = standard deviation over {len(fit['per_seed'])} pixel draws. " + fit["method"] + ". "
                  "Distance before -> after: " + "; ".join(f"`{m}` {fit['before_D'][m]:.2f} -> {fit['after_D'][m]:.2f}"
                                                          for m in fit.get("before_D", {})) + "."]
    lines += ["", "**What D means.** " + DISTANCE_MEANING, "", "**Motion.** " + result.notes.get("motion", ""), "",
              "**Light per pixel.**"]
    for m, info in result.notes.get("models", {}).items():
        reset = f" (reset {info['reset']})" if info["model"] == "elssim" else ""
        lines.append(f"- `{m}`{reset}: {info['light_estimate']}.")
    return "\n".join(lines) + "\n"


def write_report(result: RealismResult, out_dir, recording: str = "") -> dict:
    """Write ``realism.csv``, ``realism.png``, ``realism.json`` and ``realism.md`` into ``out_dir``."""
    from pathlib import Path

    from sensor.io.fileio import write_json_atomic, write_text_atomic
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"csv": out / "realism.csv", "png": out / "realism.png", "json": out / "realism.json",
             "md": out / "realism.md"}
    write_csv(paths["csv"], result.rows)
    plot(result, paths["png"], title=f"{Path(recording).name}: real vs models" if recording else "")
    write_json_atomic(paths["json"], {**result.summary(), "recording_file": str(recording),
                                      "provenance": provenance()})
    write_text_atomic(paths["md"], markdown(result, str(recording)))
    return paths
