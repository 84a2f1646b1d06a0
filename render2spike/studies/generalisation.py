"""Cross-noise-model generalisation: train one network per noise model, test each on data of every model.

The simulated counterpart of the RSIR paper's Table 1 claim (a network trained
on a realistic noise model transfers better): it tells which model to train on.

1. The dataset spec (``render2spike dataset`` schema) is built once into
   ``OUT/data`` with one simulation per frames sample (its ``models`` and
   ``seeds`` are replaced by the study's: only the clean frames are used). The
   samples, in spec order, are split: the last ``test_fraction`` are test
   frames, the rest training frames (so test scenes / parameters are unseen).
2. For every training model one network (``recon.nets``, tiny by default) is
   trained with ``recon.train.train`` on ``recon.datasets.RenderedDataset`` of
   the training frames simulated with that model (fresh noise every epoch),
   into ``OUT/nets/<model>``; a finished ``model.pt`` there (or ``--reuse
   MODEL=CKPT``) is reused.
3. Every network and every classic baseline reconstructs the test items of
   every test model. Test items of different models share frames, crops,
   centres and the simulation seed (each model draws from its own stream of
   that seed). Scores: PSNR / SSIM against the clean centre interval
   (``recon.evaluate.psnr_ssim``), mean ± sd over test items.

Model specs: ``ideal``, ``isi``, ``elssim`` and ``MODEL:RESET`` (e.g.
``elssim:crossing``, the pixel-reset option of the sensor profile, where the
installed sensor package has it).
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from sensor.errors import InputError
from sensor.io.fileio import provenance, write_json_atomic, write_text_atomic

from .common import parse_model_spec, profile_for, pyplot, save_figure, write_csv


def _label(model_spec: str) -> str:
    return model_spec.replace(":", "-")


def split_samples(folders: list, test_fraction: float) -> tuple[list, list]:
    """(train, test): the last ceil(n * test_fraction) samples are test (at least one of each)."""
    n = len(folders)
    if n < 2:
        raise InputError(f"the data hold {n} sample(s); a train / test split needs at least 2 (add lux values, "
                         "parameter values or scenes to the spec)", field="--data")
    if not 0 < test_fraction < 1:
        raise InputError(f"test fraction must be in (0, 1), got {test_fraction}", field="--test-fraction")
    k = min(n - 1, max(1, math.ceil(n * test_fraction)))
    return folders[:n - k], folders[n - k:]


def _dataset(folders, model_spec, profile, crop, seed, warmup, stride=None, include_spikes=False):
    from recon.datasets import RenderedDataset
    from sensor.io.frames import read_frames
    model, _ = parse_model_spec(model_spec)
    shape = read_frames(folders[0]).shape
    prof = profile_for(profile, shape, model_spec)
    return RenderedDataset(folders, profile=prof, crop=crop, stride=stride, model=model, seed=seed, warmup=warmup,
                           include_spikes=include_spikes)


def run_generalisation_study(data, out, *, train_models=("ideal", "isi", "elssim"), test_models=None,
                             baselines="tfp-dt,tfp-dt-denoised", reuse=(), steps=200, batch_size=4, size="tiny", width=None,
                             crop=None, test_fraction=0.25, profile="vidar-default", seed=0, threads=None,
                             workers=0, warmup=512, stride=64, overwrite=False, progress=True, log=print) -> dict:
    """Run the study (see the module docstring); writes matrix.csv, matrix.md, per_item.csv, heatmap.png.

    ``overwrite``: a dataset of another spec in ``out/data`` is made afresh (else refused)."""
    from recon.datasets import parse_hw
    from recon.evaluate import Method, apply_method, parse_methods, psnr_ssim
    from recon.nets import RSIRConfig, load_checkpoint
    from recon.train import TrainConfig, train
    from render2spike.dataset import build_dataset, done_sample_folders, load_spec

    t0 = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    train_models = list(train_models)
    test_models = list(test_models or train_models)
    for m in train_models + test_models:
        parse_model_spec(m)
    reuse_map = {}
    for item in reuse or []:
        k, sep, v = str(item).partition("=")
        if not sep or k not in train_models:
            raise InputError(f"--reuse needs MODEL=CKPT with MODEL one of {train_models}; got '{item}'",
                             field="--reuse")
        if not Path(v).is_file():
            raise InputError("checkpoint not found", path=v, field="--reuse")
        reuse_map[k] = v
    crop_hw = parse_hw(crop, "--crop") if crop else None
    base_methods = parse_methods(baselines) if baselines and str(baselines).strip() else []

    spec, spec_path = load_spec(data)
    spec = dict(spec, models=["elssim"], seeds=[int(seed)])
    res = build_dataset(spec, out / "data", workers=workers, progress=progress, overwrite=overwrite, log=log)
    if res.failed:
        raise InputError(f"{len(res.failed)} data sample(s) failed (see {out / 'data' / 'summary.md'}); first: "
                         f"{res.failed[0]['error']}", field="--data")
    folders = done_sample_folders(out / "data")
    train_f, test_f = split_samples(folders, test_fraction)
    log(f"generalisation: {len(train_f)} training and {len(test_f)} test frames samples")

    nets = {}
    train_info = {}
    for m in train_models:
        run_dir = out / "nets" / _label(m)
        if m in reuse_map:
            ckpt = reuse_map[m]
            train_info[m] = {"reused": ckpt}
        elif (run_dir / "model.pt").is_file():
            ckpt = str(run_dir / "model.pt")
            train_info[m] = {"reused": ckpt}
            log(f"generalisation: reusing {ckpt}")
        else:
            ds = _dataset(train_f, m, profile, crop_hw, seed, warmup, stride=stride)
            net = RSIRConfig.tiny() if size == "tiny" else RSIRConfig()
            if width:
                net.width = int(width)
            cfg = TrainConfig(steps=int(steps), batch_size=int(batch_size), seed=int(seed), threads=threads,
                              checkpoint_every=max(int(steps), 1), device="cpu")
            log(f"generalisation: training on {m} ({len(ds)} items, {steps} steps)")
            summ = train(ds, run_dir, net_config=net, train_config=cfg, progress=progress,
                         run_info={"noise_model": m, "data": str(out / "data"), "items": len(ds),
                                   "study": "generalisation"})
            ckpt = summ["model"]
            train_info[m] = {"trained": ckpt, "items": len(ds), "steps": summ["steps_done"],
                             "final_loss": summ["final_loss"], "seconds": summ["elapsed_s"]}
        model, _ = load_checkpoint(ckpt, "cpu")
        model.eval()
        nets[m] = Method("rsir", ckpt, f"net trained on {m}", model=model)

    rows_meth = [nets[m] for m in train_models] + base_methods
    per_item = []
    import torch
    for tm in test_models:
        ds = _dataset(test_f, tm, profile, crop_hw, seed + 1000, warmup, stride=stride, include_spikes=True)
        for i in range(len(ds)):
            s = ds.sample(i)
            s.meta.setdefault("window", ds.window)
            for meth in rows_meth:
                with torch.no_grad():
                    img = apply_method(meth, s)
                p, q = psnr_ssim(img, s.target[0])
                per_item.append({"test_model": tm, "method": meth.label, "item": s.name, "psnr_db": p, "ssim": q})
    matrix = []
    for meth in rows_meth:
        for tm in test_models:
            sel = [r for r in per_item if r["method"] == meth.label and r["test_model"] == tm]
            ps = np.array([r["psnr_db"] for r in sel])
            ss = np.array([r["ssim"] for r in sel])
            matrix.append({"method": meth.label, "test_model": tm, "n_items": len(sel),
                           "psnr_db": float(ps.mean()), "psnr_sd": float(ps.std(ddof=1)) if len(ps) > 1 else float("nan"),
                           "ssim": float(np.nanmean(ss)), "ssim_sd": float(np.nanstd(ss, ddof=1)) if len(ss) > 1 else float("nan")})
    info = {"data": str(spec_path or data), "train_models": train_models, "test_models": test_models,
            "baselines": [m.label for m in base_methods], "train_samples": [str(f) for f in train_f],
            "test_samples": [str(f) for f in test_f], "crop": crop_hw, "warmup_intervals": warmup,
            "stride_intervals": stride, "seed": seed, "networks": train_info, "size": size, "width": width,
            "seconds": time.perf_counter() - t0, "provenance": provenance(stage="study generalisation")}
    return write_generalisation(out, matrix, per_item, [m.label for m in rows_meth], test_models, info)


def write_generalisation(out: Path, matrix, per_item, methods, test_models, info) -> dict:
    write_csv(out / "matrix.csv", matrix)
    write_csv(out / "per_item.csv", per_item)
    n = matrix[0]["n_items"] if matrix else 0

    def cell(r, key, sd, d):
        return f"{r[key]:.{d}f}" + (f" ± {r[sd]:.{d}f}" if np.isfinite(r[sd]) else "")
    lines = ["# Cross-noise-model generalisation", "",
             f"Rows: reconstruction (networks trained on one noise model; classic baselines need no training). "
             f"Columns: the noise model of the test data ({n} test items each: the same frames, crops and seeds). "
             "PSNR [dB] / SSIM against the clean centre interval, mean ± sd over test items.", ""]
    for key, sd, d, name in (("psnr_db", "psnr_sd", 2, "PSNR [dB]"), ("ssim", "ssim_sd", 3, "SSIM")):
        lines += [f"## {name}", "", "| trained on \\ tested on | " + " | ".join(test_models) + " |",
                  "|---|" + "---|" * len(test_models)]
        for m in methods:
            cells = [cell(next(r for r in matrix if r["method"] == m and r["test_model"] == t), key, sd, d)
                     for t in test_models]
            lines.append(f"| {m} | " + " | ".join(cells) + " |")
        lines.append("")
    nets = info.get("networks", {})
    lines += ["Networks: " + "; ".join(f"{k}: {v.get('steps', '?')} steps on {v.get('items', '?')} items"
                                       if "trained" in v else f"{k}: reused {v['reused']}" for k, v in nets.items()),
              "", "![heat map](heatmap.png)", ""]
    write_text_atomic(out / "matrix.md", "\n".join(lines))
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(4.2 + 1.6 * len(test_models), 0.8 + 0.55 * len(methods)))
    for ax, (key, name) in zip(axes, (("psnr_db", "PSNR [dB]"), ("ssim", "SSIM"))):
        M = np.array([[next(r for r in matrix if r["method"] == m and r["test_model"] == t)[key] for t in test_models]
                      for m in methods])
        im = ax.imshow(M, cmap="viridis", aspect="auto")
        for i in range(M.shape[0]):
            for j in range(M.shape[1]):
                ax.text(j, i, f"{M[i, j]:.2f}" if key == "psnr_db" else f"{M[i, j]:.3f}", ha="center", va="center",
                        color="w" if M[i, j] < np.nanmean(M) else "k", fontsize=7)
        ax.set_xticks(range(len(test_models)))
        ax.set_xticklabels(test_models, fontsize=7)
        ax.set_yticks(range(len(methods)))
        ax.set_yticklabels(methods if ax is axes[0] else [], fontsize=7)
        ax.set_xlabel("test data model", fontsize=8)
        ax.set_title(name, fontsize=9)
        fig.colorbar(im, ax=ax, fraction=0.046)
    fig.tight_layout()
    save_figure(fig, out / "heatmap.png")
    write_json_atomic(out / "study.json", info)
    return {"matrix": matrix, "table": str(out / "matrix.md"), "csv": str(out / "matrix.csv"),
            "heatmap": str(out / "heatmap.png")}
