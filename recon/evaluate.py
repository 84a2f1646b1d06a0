"""Evaluation: run methods on test items, PSNR / SSIM, the Table-1-style table and an example grid.

Methods (``--methods`` of ``render2spike evaluate``, comma-separated)
--------------------------------------------------------------------
``tfp``        TFP over the M = 320 network-input intervals ("TFP (M=320)")
``tfp:N``      TFP over N centred intervals (needs ``intervals=N`` in the data spec when N > 320)
``tfi``        TFI at the centre interval, using the item's spikes
``tfp-dt``     dead-time-corrected TFP (``recon.classic.tfp_deadtime``) with the item's profile
``tfp-dt-denoised``   the strong classic baseline: ``tfp-dt`` over a window, then a Gaussian; window (at most
               M) and width chosen from the item's light level and motion score (measured from its spikes)
               with the table tuned on training data (``recon.baselines``)
``tfp-dt-denoised:S`` a fixed width of S pixels over the whole M-interval window
``rsir:CKPT``  an RSIR-architecture checkpoint; ``rsir:CKPT=LABEL`` names its row

Metrics and normalisation
-------------------------
Each method returns an image in the target unit (ideal spikes per interval,
``rate_e / threshold_e``; ``tfp-dt`` divides its ``rate_e`` by the threshold).
Reference and reconstruction are both divided by the reference's white level
``w`` (its 99.5th percentile) and clipped to [0, 1]; PSNR
(``skimage.metrics.peak_signal_noise_ratio``) and SSIM
(``skimage.metrics.structural_similarity``, 7x7 uniform window, or the
largest odd window that fits) use ``data_range = 1`` on these
linear values. No per-method gain or offset is fitted. Scores are averaged
over the items.

A real recording without a reference image (``--data real:FILE``) is scored
by :mod:`recon.realscore` instead: stationary pixels against their
dead-time-corrected rate outside the clip, at each method's best-fit gain,
with the reference's own noise floor.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sensor.errors import InputError, UnknownMethodError
from sensor.io.fileio import atomic_path, write_json_atomic, write_text_atomic

from .classic import tfi, tfp, tfp_deadtime, tfp_windows
from .imageio import show_image_row, white_level
from .metrics import PSNR_CAP_DB, WHITE_PERCENTILE, normalise, psnr_ssim  # noqa: F401  (re-exported)

#: the method names ``--methods`` accepts (stable: studies refer to them)
METHOD_NAMES = ("tfp", "tfp:N", "tfi", "tfp-dt", "tfp-dt-denoised", "tfp-dt-denoised:S", "rsir:CKPT")


@dataclass
class Method:
    """A parsed method: ``kind`` in tfp, tfi, tfp-dt, rsir; ``arg`` the window or checkpoint; ``label``."""

    kind: str
    arg: str | None
    label: str
    model: object = None


def parse_methods(text: str) -> list[Method]:
    """``tfp,tfp:4000,tfi,tfp-dt,rsir:run/model.pt=ELSSim`` -> list of :class:`Method`."""
    out = []
    for tok in [t.strip() for t in text.split(",") if t.strip()]:
        kind, _, arg = tok.partition(":")
        kind = kind.lower()
        if kind == "tfp":
            if arg:
                try:
                    n = int(arg)
                except ValueError:
                    raise InputError(f"tfp:N needs an integer window, got '{arg}'", field="--methods") from None
                if n < 1:
                    raise InputError(f"tfp:N needs a window of 1 or more intervals, got {n}", field="--methods")
                out.append(Method("tfp", str(n), f"TFP (M={n})"))
            else:
                out.append(Method("tfp", None, "TFP (M=320)"))
        elif kind == "tfi":
            out.append(Method("tfi", None, "TFI"))
        elif kind in ("tfp-dt", "tfpdt"):
            out.append(Method("tfp-dt", None, "TFP dead-time corrected"))
        elif kind == "tfp-dt-denoised":
            if arg:
                try:
                    sig = float(arg)
                except ValueError:
                    raise InputError(f"tfp-dt-denoised:S needs a width in pixels, got '{arg}'",
                                     field="--methods") from None
                from .baselines import MAX_SIGMA_PX
                if not (math.isfinite(sig) and 0 < sig <= MAX_SIGMA_PX):
                    raise InputError(f"tfp-dt-denoised:S needs a finite width in pixels above 0 and at most "
                                     f"{MAX_SIGMA_PX:g}, got {arg}", field="--methods")
                out.append(Method("tfp-dt-denoised", str(sig), f"TFP-DT + Gaussian (sigma={sig:g})"))
            else:
                out.append(Method("tfp-dt-denoised", None, "TFP-DT + Gaussian (tuned)"))
        elif kind == "rsir":
            if not arg:
                raise InputError("rsir needs a checkpoint: rsir:PATH[=LABEL]", field="--methods")
            path, _, label = arg.partition("=")
            out.append(Method("rsir", path, label or f"RSIR-arch ({Path(path).parent.name or Path(path).stem})"))
        else:
            raise UnknownMethodError("reconstruction method", kind, METHOD_NAMES)
    if not out:
        raise InputError("no methods given", field="--methods")
    return out


def load_models(methods: list[Method], device="auto") -> None:
    """Load the checkpoints of the ``rsir`` methods (in place)."""
    from .nets import load_checkpoint, pick_device
    dev = pick_device(device)
    for m in methods:
        if m.kind == "rsir" and m.model is None:
            m.model, _ = load_checkpoint(m.arg, dev)


def apply_method(m: Method, sample) -> np.ndarray:
    """Reconstruct one item with ``m``: float32 (H, W) in ideal spikes per interval."""
    if m.kind == "tfp":
        if m.arg is None:
            s = sample.spikes
            return tfp(s, sample.windows.shape[0] * _window_of(sample), sample.center)
        n = int(m.arg)
        if sample.spikes.shape[0] < n:
            raise InputError(f"tfp:{n} needs {n} intervals per item; the data keep {sample.spikes.shape[0]} "
                             f"(add intervals={n} to the data spec)", field="--methods")
        return tfp(sample.spikes, n, sample.center)
    if m.kind == "tfi":
        return tfi(sample.spikes, sample.center)
    if m.kind == "tfp-dt":
        M = sample.windows.shape[0] * _window_of(sample)
        lam = tfp_deadtime(sample.spikes, sample.profile, M, sample.center)
        return lam / np.float32(sample.profile.threshold_e)
    if m.kind == "tfp-dt-denoised":
        from .baselines import tfp_dt_denoised
        M = sample.windows.shape[0] * _window_of(sample)
        lam = tfp_dt_denoised(sample.spikes, sample.profile, M, sample.center,
                              sigma=None if m.arg is None else float(m.arg))
        return lam / np.float32(sample.profile.threshold_e)
    if m.kind == "rsir":
        import torch
        model = m.model
        dev = next(model.parameters()).device
        wins = sample.windows
        N, Lw = model.config.input_layout
        if (wins.shape[0], _window_of(sample)) != (N, Lw) and N * Lw == wins.shape[0] * _window_of(sample) \
                and getattr(sample, "spikes", None) is not None and np.ndim(sample.spikes) == 3:
            # the same span cut as this network takes it (e.g. split windows)
            wins = tfp_windows(sample.spikes, N, Lw, center=sample.center)
        w = torch.from_numpy(wins[None]).to(dev)
        maps = torch.from_numpy(sample.maps[None]).to(dev)
        return model.reconstruct(w, maps)[0, 0].cpu().numpy().astype(np.float32)
    raise UnknownMethodError("reconstruction method", m.kind, METHOD_NAMES)


def _window_of(sample) -> int:
    return int(sample.meta.get("window", 32))


def evaluate(dataset, methods: list[Method], out_dir, *, n_examples: int = 4, progress: bool = True,
             data_label: str = "") -> dict:
    """Run every method on every item; write table.md, table.csv, per_item.csv, grid.png, summary.json."""
    from tqdm import tqdm
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if len(dataset) == 0:
        raise InputError("the evaluation data hold no items", field="--data")
    per_item, examples = [], []
    n = len(dataset)
    M = getattr(dataset, "n_windows", 10) * getattr(dataset, "window", 32)
    for m in methods:  # the network-input length of these data (320 unless windows/window say otherwise)
        if m.kind == "tfp" and m.arg is None:
            m.label = f"TFP (M={M})"
    show = set(np.unique(np.linspace(0, n - 1, min(n_examples, n)).round().astype(int)).tolist()) if n_examples else set()
    for i in tqdm(range(n), desc="evaluate", unit="item", disable=not progress):
        s = dataset.sample(i)
        s.meta.setdefault("window", getattr(dataset, "window", 32))
        ref = s.target[0]
        imgs = {}
        for m in methods:
            img = apply_method(m, s)
            imgs[m.label] = img
            ps, ss = psnr_ssim(img, ref)
            per_item.append({"item": s.name, "method": m.label, "psnr_db": ps, "ssim": ss})
        if i in show:
            examples.append((s.name, ref, imgs))
    rows = []
    for m in methods:
        vals = [r for r in per_item if r["method"] == m.label]
        rows.append({"method": m.label, "psnr_db": float(np.mean([r["psnr_db"] for r in vals])),
                     "ssim": float(np.nanmean([r["ssim"] for r in vals])), "items": len(vals)})
    write_tables(out_dir, rows, per_item, data_label)
    write_grid(out_dir / "grid.png", examples, [m.label for m in methods])
    summary = {"data": data_label, "items": len(dataset), "rows": rows,
               "normalisation": f"pred and reference / reference {WHITE_PERCENTILE}th percentile, clipped to "
                                "[0, 1]; data_range = 1; unit: ideal spikes per interval (rate_e / threshold_e)"}
    write_json_atomic(out_dir / "summary.json", summary)
    return summary


def write_tables(out_dir: Path, rows: list[dict], per_item: list[dict], data_label: str = "") -> None:
    """table.md (Table 1 layout: Methods | PSNR | SSIM), table.csv and per_item.csv, atomically."""
    lines = ["| Methods | PSNR | SSIM |", "|---|---|---|"]
    lines += [f"| {r['method']} | {r['psnr_db']:.2f} | {r['ssim']:.3f} |" for r in rows]
    n = rows[0]["items"] if rows else 0
    caption = (f"\nTable: PSNR (dB) and SSIM of each method on {data_label or 'the test data'} ({n} items). "
               f"Reference and reconstruction divided by the reference's {WHITE_PERCENTILE}th percentile and "
               "clipped to [0, 1]; data range 1.\n")
    write_text_atomic(out_dir / "table.md", "\n".join(lines) + "\n" + caption)
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["Methods", "PSNR", "SSIM"])
    for r in rows:
        w.writerow([r["method"], f"{r['psnr_db']:.4f}", f"{r['ssim']:.5f}"])
    write_text_atomic(out_dir / "table.csv", buf.getvalue())
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=["item", "method", "psnr_db", "ssim"])
    w.writeheader()
    for r in per_item:
        w.writerow({**r, "psnr_db": f"{r['psnr_db']:.4f}", "ssim": f"{r['ssim']:.5f}"})
    write_text_atomic(out_dir / "per_item.csv", buf.getvalue())


def write_grid(path, examples, labels: list[str]) -> None:
    """PNG grid: one row per example, columns = reference then each method (display: / white, sRGB)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    if not examples:
        return
    cols = 1 + len(labels)
    h, w = examples[0][1].shape
    scale = 2.2 / max(h, w) * max(w, 1)
    fig, axes = plt.subplots(len(examples), cols, figsize=(cols * scale, len(examples) * 2.2 * h / max(h, w) + 0.4),
                             dpi=110, squeeze=False)
    for r, (name, ref, imgs) in enumerate(examples):
        wl = white_level(ref, WHITE_PERCENTILE)
        panels = [("Reference", ref)] + [(lab, imgs[lab]) for lab in labels]
        show_image_row(axes[r], panels, wl, titles=r == 0, ylabel=name, label_size=6)
    fig.tight_layout()
    with atomic_path(Path(path)) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
