"""Training loop of the RSIR-architecture network: checkpoints, resume, loss curve (CSV + PNG), progress bar.

Run directory layout::

    RUN_DIR/config.json              data spec, noise model, network and training settings, provenance
    RUN_DIR/checkpoints/last.pt      latest state (model, optimizer, step); --resume continues from it
    RUN_DIR/model.pt                 the final model (same format) when training ends
    RUN_DIR/loss.csv                 step, epoch, loss and its parts, learning rate, elapsed seconds
    RUN_DIR/loss.png                 the loss curve

Determinism: batch order of epoch ``e`` comes from
``SeedSequence(seed, spawn_key=(100, e))`` and every item draws its crop,
light level and noise from its own SeedSequence (``recon.datasets``), so a
resumed run sees exactly the batches the uninterrupted run would have seen
(network weights then agree up to floating-point nondeterminism of the
kernels).
"""

from __future__ import annotations

import csv
import io
import json
import math
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

from sensor.errors import InputError
from sensor.io.fileio import atomic_path, provenance, write_json_atomic, write_text_atomic

LOSS_FIELDS = ["step", "epoch", "loss", "refine", "fusion", "denoise", "bands", "nim", "head", "route", "lr", "elapsed_s"]


@dataclass
class TrainConfig:
    """Optimisation settings. ``steps`` optimiser steps of ``batch_size`` items each."""

    steps: int = 2000
    batch_size: int = 4
    lr: float = 1e-3
    lr_final_fraction: float = 0.1
    checkpoint_every: int = 100
    log_every: int = 10
    seed: int = 0
    workers: int = 0
    max_minutes: float | None = None
    device: str = "auto"
    threads: int | None = None
    train_only: str | None = None

    def __post_init__(self):
        if self.train_only not in (None, "head"):
            raise InputError(f"train_only must be None or 'head', got '{self.train_only}'", field="train_only")

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names})


def collate(items: list[dict]):
    """List of training dicts -> dict of float32 tensors (B, ...)."""
    import torch
    shapes = {tuple(it["windows"].shape) for it in items}
    if len(shapes) > 1:
        raise InputError(f"items of one batch differ in shape {sorted(shapes)}: give every --data the same "
                         "crop=HxW", field="--data")
    return {k: torch.from_numpy(np.stack([it[k] for it in items]).astype(np.float32)) for k in items[0]}


def estimate_intensity_scale(dataset, n: int = 8) -> float:
    """0.5 / mean target of the first ``n`` items: makes the network's typical values ~0.5."""
    n = min(n, len(dataset))
    m = float(np.mean([dataset[i]["target"].mean() for i in range(n)]))
    if not m > 0:
        raise InputError("the training targets are all zero (no light?); cannot set the intensity scale",
                         field="--data")
    return 0.5 / m


def lr_at(step: int, cfg: TrainConfig) -> float:
    """Cosine decay from ``lr`` to ``lr * lr_final_fraction`` over ``steps``."""
    t = min(max(step / max(cfg.steps, 1), 0.0), 1.0)
    return cfg.lr * (cfg.lr_final_fraction + (1 - cfg.lr_final_fraction) * 0.5 * (1 + math.cos(math.pi * t)))


def epoch_order(seed: int, epoch: int, n: int) -> np.ndarray:
    """The item order of one epoch."""
    ss = np.random.SeedSequence(int(seed), spawn_key=(100, int(epoch)))
    return np.random.Generator(np.random.PCG64(ss)).permutation(n)


def read_loss_csv(path) -> list[dict]:
    path = Path(path)
    if not path.is_file():
        return []
    with path.open(newline="") as f:
        try:
            return [{k: float(v) for k, v in row.items() if v not in ("", None)} for row in csv.DictReader(f)]
        except (TypeError, ValueError, csv.Error) as exc:
            raise InputError(f"the loss log is corrupt ({exc}); delete it to resume without the earlier curve",
                             path=path) from exc


def write_loss_files(out_dir: Path, rows: list[dict]) -> None:
    """loss.csv and loss.png, atomically."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=LOSS_FIELDS)
    w.writeheader()
    for r in rows:
        w.writerow({k: (int(r[k]) if k in ("step", "epoch") else (f"{r[k]:.6g}" if k in r else ""))
                    for k in LOSS_FIELDS})
    write_text_atomic(out_dir / "loss.csv", buf.getvalue())
    if not rows:
        return
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    steps = [r["step"] for r in rows]
    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=100)
    ax.plot(steps, [r["loss"] for r in rows], label="total (mean over steps)", lw=1)
    ax.plot(steps, [r["refine"] for r in rows], label="refine L1 (mean over steps)", lw=1)
    if all("head" in r for r in rows):
        ax.plot(steps, [r["head"] for r in rows], label="head L1 (the output)", lw=1)
    ax.set_xlabel("optimiser step")
    ax.set_ylabel("loss (scaled units)")
    ax.set_yscale("log")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    with atomic_path(out_dir / "loss.png") as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def train(dataset, out_dir, *, net_config=None, train_config: TrainConfig | None = None, resume: bool = False,
          init_checkpoint=None, add_head: bool = False, head_sigmas=None, head_windows=None,
          head_motion: bool | None = None, head_edges: str | None = None, run_info: dict | None = None,
          progress: bool = True) -> dict:
    """Train (or resume) an RSIR-architecture network on ``dataset``; returns a summary dict.

    Parameters
    ----------
    dataset : recon.datasets dataset
        Training items (``set_epoch`` is called each epoch).
    out_dir : path
        Run directory (layout in the module docstring).
    net_config : RSIRConfig, optional
        Network size; ``intensity_scale`` is estimated from the data unless
        ``init_checkpoint`` or a resumed run supplies it.
    train_config : TrainConfig
    resume : bool
        Continue from ``out_dir/checkpoints/last.pt``.
    init_checkpoint : path, optional
        Start from these weights (fine-tuning, e.g. on SDMD training pairs); the
        network layout is the checkpoint's. A ``fixed``-normalised network
        adopts the intensity scale of the new data (``estimate_intensity_scale``);
        a ``mean``-normalised one needs none.
    add_head : bool
        With ``init_checkpoint``: add an output head (``RSIRConfig.head``) to
        the checkpoint's network when it has none (its weights are kept; the
        head starts at equal weights). ``train_config.train_only = "head"``
        then trains the head alone on the fixed network.
    head_sigmas : sequence of float, optional
        With ``add_head``: the widths [pixels] of the head's smoothed classic
        candidates (``RSIRConfig.head_sigmas``); a head of the checkpoint is
        then replaced by a new one with these widths.
    head_windows, head_motion : optional
        With ``add_head``: the candidates' temporal support and the motion cue
        (``RSIRConfig.head_windows``, ``RSIRConfig.head_motion``); as for
        ``head_sigmas``, a head of the checkpoint is replaced. The new head
        starts from the old one (:func:`_with_head`).
    head_edges : str, optional
        With ``add_head``: the border mode of the bank's Gaussians
        (``RSIRConfig.head_edges``); a new head gets ``"symmetric"`` unless told.
    run_info : dict
        Stored in config.json (data spec, noise model, command).
    """
    import torch
    from tqdm import tqdm

    from .nets import RSIRConfig, RSIRNet, load_checkpoint, pick_device, rsir_loss, save_checkpoint

    out_dir = Path(out_dir)
    cfg = train_config or TrainConfig()
    ckpt_dir = out_dir / "checkpoints"
    last = ckpt_dir / "last.pt"
    device = pick_device(cfg.device)
    if cfg.threads:
        torch.set_num_threads(int(cfg.threads))
    if len(dataset) == 0:
        raise InputError("the training data hold no items", field="--data")
    for name, lo in (("steps", 1), ("batch_size", 1), ("checkpoint_every", 1), ("log_every", 1)):
        if int(getattr(cfg, name)) < lo:
            raise InputError(f"must be an integer >= {lo}; got {getattr(cfg, name)}", field="--" + name.replace("_", "-"))

    step, rows = 0, []
    if resume:
        if not last.is_file():
            raise InputError("--resume: no checkpoints/last.pt in this run directory", path=out_dir)
        model, ckpt = load_checkpoint(last, device)
        if "step" not in ckpt:
            raise InputError("missing required field", path=last, field="step")
        step = int(ckpt["step"])
        stored = json.loads((out_dir / "config.json").read_text()) if (out_dir / "config.json").is_file() else {}
        for key, flag in (("data", "--data"), ("noise_model", "--noise-model")):
            if key in stored and key in (run_info or {}) and stored[key] != run_info[key]:
                raise InputError(f"--resume continues the run trained on {flag} {stored[key]!r}, but this command "
                                 f"gives {run_info[key]!r}; give the stored one, or start a new run in another "
                                 "--out", path=out_dir / "config.json", field=flag)
        if stored.get("train"):
            old = TrainConfig.from_dict(stored["train"])
            cfg = TrainConfig(**{**asdict(old), "steps": cfg.steps, "max_minutes": cfg.max_minutes,
                                 "device": cfg.device, "workers": cfg.workers,
                                 "threads": cfg.threads})
        rows = [r for r in read_loss_csv(out_dir / "loss.csv") if r["step"] <= step]
    else:
        if last.is_file():
            raise InputError("this run directory already holds a run; pass --resume to continue it or choose "
                             "another --out", path=out_dir)
        if init_checkpoint:
            model, _ = load_checkpoint(init_checkpoint, device)
            if model.config.normalise == "fixed" and cfg.train_only != "head":
                # adopt the new data's light level (the weights stay); not when the network is to stay as it is
                model.config.intensity_scale = estimate_intensity_scale(dataset)
            new_bank = any(v is not None for v in (head_sigmas, head_windows, head_motion, head_edges))
            if add_head and (model.head is None or new_bank):  # the network plus a new head
                model = _with_head(model, cfg.seed, device, head_sigmas, head_windows, head_motion, head_edges)
        else:
            nc = net_config or RSIRConfig.tiny()
            if nc.normalise == "fixed" and nc.intensity_scale == 1.0:
                nc.intensity_scale = estimate_intensity_scale(dataset)
            with torch.random.fork_rng(devices=[]):  # seeded weight init without touching the global generator
                torch.manual_seed(int(cfg.seed))
                model = RSIRNet(nc).to(device)
        ckpt = None
    model.train()
    N, w = model.config.input_layout
    if (dataset.n_windows, getattr(dataset, "window", w)) != (N, w) and hasattr(dataset, "use_layout") \
            and dataset.n_windows * dataset.window == N * w:
        dataset.use_layout(N, w)  # the same blocks, cut as the network takes them (e.g. split windows)
    if dataset.n_windows != N or getattr(dataset, "window", w) != w:
        raise InputError(f"the data give {dataset.n_windows} windows of {getattr(dataset, 'window', '?')} intervals "
                         f"but the network takes {N} of {w} (add windows={N}:window={w} to each --data spec)",
                         field="--data")
    head_only = cfg.train_only == "head"
    if head_only and not (init_checkpoint or resume):
        raise InputError("train_only='head' keeps the rest of the network as it is: start from a trained one "
                         "(init_checkpoint, CLI --init CKPT --head)", field="--train-only")
    if head_only and model.head is None:
        raise InputError("train_only='head' needs a network with an output head (add one with add_head / "
                         "--head when starting from --init)", field="--train-only")
    params = list(model.head.parameters()) if head_only else list(model.parameters())
    opt = torch.optim.Adam(params, lr=lr_at(step, cfg))
    if ckpt is not None and "optimizer" in ckpt:
        try:
            opt.load_state_dict(ckpt["optimizer"])
        except (ValueError, KeyError, TypeError, RuntimeError) as exc:
            raise InputError(f"the optimizer state does not fit the network ({exc})", path=last,
                             field="optimizer") from exc

    info = {"format": "render2spike-train-run", "version": 1, "network": model.config.to_dict(),
            "train": asdict(cfg), "device": str(device), "provenance": provenance()}
    info.update(run_info or {})
    created = not out_dir.exists()
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out_dir / "config.json", info)

    n = len(dataset)
    bs = min(cfg.batch_size, n)
    per_epoch = n // bs
    t0 = time.time()
    elapsed0 = rows[-1]["elapsed_s"] if rows else 0.0
    acc, acc_n = {}, 0
    stopped_early = False
    bar = tqdm(total=cfg.steps, initial=step, desc="train", unit="step", disable=not progress, dynamic_ncols=True)

    def checkpoint():
        save_checkpoint(last, model, opt, step=step, extra={"train": asdict(cfg), "run": run_info or {}})
        write_loss_files(out_dir, rows)

    try:
        while step < cfg.steps:
            epoch = step // per_epoch
            dataset.set_epoch(epoch)
            order = epoch_order(cfg.seed, epoch, n)
            first = step % per_epoch
            batches = [order[b * bs:(b + 1) * bs].tolist() for b in range(first, per_epoch)]
            loader = _loader(dataset, batches, cfg.workers)
            for batch in loader:
                for g in opt.param_groups:
                    g["lr"] = lr_at(step, cfg)
                batch = {k: v.to(device) for k, v in batch.items()}
                out = model(batch["windows"], batch["maps"], trunk_grad=not head_only)
                loss, parts = rsir_loss(model, out, batch["target"], head_only=head_only)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                step += 1
                parts["loss"] = float(loss.detach())
                for k, v in parts.items():
                    acc[k] = acc.get(k, 0.0) + v
                acc_n += 1
                bar.update(1)
                bar.set_postfix(loss=f"{parts['loss']:.4f}", epoch=epoch)
                if step % cfg.log_every == 0 or step == cfg.steps:
                    rows.append({"step": step, "epoch": epoch, **{k: v / acc_n for k, v in acc.items()},
                                 "lr": lr_at(step, cfg), "elapsed_s": elapsed0 + time.time() - t0})
                    acc, acc_n = {}, 0
                if step % cfg.checkpoint_every == 0:
                    checkpoint()
                if cfg.max_minutes is not None and (time.time() - t0) > 60 * cfg.max_minutes:
                    stopped_early = True
                    break
                if step >= cfg.steps:
                    break
            if stopped_early:
                break
    except BaseException:
        if not resume and not last.is_file():  # failed before its first checkpoint: no run to resume, none left
            (out_dir / "config.json").unlink(missing_ok=True)
            if created:
                import contextlib
                with contextlib.suppress(OSError):
                    out_dir.rmdir()
        raise
    finally:
        bar.close()
    checkpoint()
    final = out_dir / "model.pt"
    save_checkpoint(final, model, None, step=step, extra={"train": asdict(cfg), "run": run_info or {}})
    summary = {"steps_done": step, "steps_planned": cfg.steps, "stopped_early": stopped_early,
               "final_loss": rows[-1]["loss"] if rows else None, "elapsed_s": elapsed0 + time.time() - t0,
               "model": str(final), "intensity_scale": model.config.intensity_scale, "device": str(device)}
    write_json_atomic(out_dir / "summary.json", summary)
    return summary


#: starting logit of a candidate that the old head did not have (its weight starts near e^-8 of the others')
NEW_CANDIDATE_LOGIT = -8.0


def _with_head(model, seed: int, device, head_sigmas=None, head_windows=None, head_motion=None, head_edges=None):
    """A copy of ``model`` with a new output head (same weights otherwise).

    ``head_sigmas``, ``head_windows``, ``head_motion``: the new bank (default the
    config's); ``head_edges``: its Gaussians' border mode (default ``"symmetric"``,
    whatever the old head's); the head's loss and its light-level input are the current defaults
    (``RSIRConfig.head_loss``, ``head_light_level``). The head is seeded by ``seed``; where ``model``
    already has a head of the same CNN width, the new one starts as it: the weights of the
    candidates both banks hold (same window count and width), the mean-count level and
    rate inputs, the light level when both have it, and the correction are copied; other
    inputs (the motion cues among them) start at zero weight
    and new candidates at logit :data:`NEW_CANDIDATE_LOGIT`, so the output
    starts (nearly) at the old head's and training adds what the new candidates
    are worth.
    """
    import torch

    from .nets import RSIRConfig, RSIRNet
    extra = {"head_sigmas": list(head_sigmas)} if head_sigmas is not None else {}
    if head_windows is not None:
        extra["head_windows"] = list(head_windows)
    if head_motion is not None:
        extra["head_motion"] = bool(head_motion)
    extra["head_edges"] = str(head_edges or "symmetric")
    extra["head_loss"] = RSIRConfig.head_loss  # a new head: the current default loss and inputs
    extra["head_light_level"] = RSIRConfig.head_light_level
    extra["head_split"] = RSIRConfig.head_split
    cfg = RSIRConfig.from_dict({**model.config.to_dict(), "head": True, **extra})
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(seed))
        new = RSIRNet(cfg).to(device)
    trunk = {k: v for k, v in model.state_dict().items() if not k.startswith("head.")}
    missing, unexpected = new.load_state_dict(trunk, strict=False)
    if unexpected or any(not k.startswith("head.") for k in missing):
        raise InputError(f"could not add a head to the checkpoint's network (missing {missing}, unexpected "
                         f"{unexpected})", field="--head")
    if model.head is not None and model.config.head_width == cfg.head_width:
        _transplant_head(model, new)
    return new


def _bank_keys(model) -> list:
    """(window count, width) of each classic candidate of ``model``'s head, in bank order."""
    c = model.config
    n_all = c.n_windows
    return [(n_all if n <= 0 or n >= n_all else n, float(s)) for n in c.head_windows for s in c.head_sigmas]


def _transplant_head(old, new) -> None:
    """Start ``new``'s head from ``old``'s (see :func:`_with_head`)."""
    import torch
    ok, nk = _bank_keys(old), _bank_keys(new)
    Ko, Kn = 1 + len(ok), 1 + len(nk)
    # input channel and output row of each old one in the new head: network image, shared candidates, level, rate
    src = [0] + [1 + i for i, k in enumerate(ok) if k in nk]
    dst = [0] + [1 + nk.index(k) for k in ok if k in nk]
    o, n = old.head.net, new.head.net
    with torch.no_grad():
        w0 = torch.zeros_like(n[0].weight)
        w0[:, dst] = o[0].weight[:, src]
        w0[:, Kn:Kn + 2] = o[0].weight[:, Ko:Ko + 2]  # level, rate
        if old.config.head_light_level and new.config.head_light_level:
            w0[:, -1] = o[0].weight[:, -1]  # the light level (the last cue of both)
        n[0].weight.copy_(w0)
        n[0].bias.copy_(o[0].bias)
        n[2].weight.copy_(o[2].weight)
        n[2].bias.copy_(o[2].bias)
        w4 = torch.zeros_like(n[4].weight)
        b4 = torch.full_like(n[4].bias, NEW_CANDIDATE_LOGIT)
        w4[dst] = o[4].weight[src]
        b4[dst] = o[4].bias[src]
        w4[Kn] = o[4].weight[Ko]  # the correction
        b4[Kn] = o[4].bias[Ko]
        n[4].weight.copy_(w4)
        n[4].bias.copy_(b4)


def _loader(dataset, batches, workers: int):
    """Iterate collated batches; with ``workers`` > 0 through a torch DataLoader (items built in parallel)."""
    if workers <= 0:
        for b in batches:
            yield collate([dataset[i] for i in b])
        return
    import torch
    dl = torch.utils.data.DataLoader(dataset, batch_sampler=batches, num_workers=workers, collate_fn=collate,
                                     worker_init_fn=_worker_init)
    yield from dl


def _worker_init(_):
    import torch
    torch.set_num_threads(1)
