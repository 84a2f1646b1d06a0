"""``render2spike train``: train an RSIR-architecture reconstruction network on simulated (or paired) spikes."""

from __future__ import annotations

from render2spike.commands._common import seed as _seed_type

from pathlib import Path

EXAMPLES = """presets (--size):
  tiny   width 16, 2 residual blocks, 2 attention blocks (2 heads) at width 16: 20,587 parameters;
         trains on a CPU in minutes (the default)
  paper  width 32, 4 residual blocks, 2 attention blocks (4 heads) at width 32: 96,047 parameters;
         wider than tiny, NOT the released RSIR layout
  rsir   the released RSIR network (BIT-Vision/RSIR MainDenoise): 16-channel residual blocks, a 96-wide
         windowed-attention stage (3 heads, MLP ratio 4), trainable wavelet taps: 254,502 parameters
         (remaining deviations in docs/recon.md)

normalisation (--normalise):
  mean   divide input and output by the mean spike rate of the input itself: one model for every light
         level (default)
  fixed  one intensity scale estimated from the training data (the network works near that level only)

examples:
  python -m recon.synth data/dvsynth --sequences 90 --frames 12 --size 96x128 --seed 7
  render2spike train --data davis:data/dvsynth:crop=64x64:res=96x128:lux=0.5-500 --out runs/a --steps 2000
  render2spike train --data davis:data/dvsynth:crop=64x64:res=96x128:lux=0.5-500 \\
      --data rendered:out/disk,out/room:crop=64x64:lux=0.5-500 --size rsir --out runs/b
  render2spike train --data davis:data/dvsynth:crop=64x64:res=96x128:lux=0.5-500 --out runs/a --steps 3000 --resume
  render2spike train --data sdmd:data/SDMD:split=train --init runs/a/model.pt --out runs/ft
  render2spike train --data davis:data/dvsynth:crop=64x64:res=96x128:lux=0.5-500 --init runs/a/model.pt \\
      --head --train-only head --lr 2e-3 --out runs/head      # add the output head, train it alone
"""

HELP_DATA = ("data spec KIND:PATH[,PATH...][:key=value...], KIND davis | sdmd | rendered; e.g. "
             "davis:/data/DAVIS:crop=64x64:lux=5-50 (see docs/recon.md)")


#: the presets of recon.nets.RSIRConfig.preset (kept here so --help does not import torch; a test checks them)
PRESETS = ("tiny", "paper", "rsir")


def register(subparsers) -> None:
    from render2spike.commands._common import HelpFormatter
    p = subparsers.add_parser(
        "train", help="train a reconstruction network (RSIR architecture)",
        description="Train an RSIR-architecture network on spikes simulated from DAVIS-layout or rendered data "
                    "(or on SDMD-style real pairs). Input: 10 TFP windows of 32 intervals (M = 320); target: the "
                    "clean intensity at the window centre in ideal spikes per interval (rate_e / threshold_e).",
        epilog=EXAMPLES, formatter_class=HelpFormatter)
    p.add_argument("--data", required=True, action="append",
                   help=HELP_DATA + "; repeat to train on several sources at once (same crop)")
    p.add_argument("--noise-model", default="elssim", choices=["elssim", "ideal", "isi"],
                   help="spike model the training spikes are simulated with (a model= spec option wins)")
    p.add_argument("--out", required=True, metavar="RUN_DIR", help="run directory (checkpoints, loss curve)")
    p.add_argument("--resume", action="store_true", help="continue the run in RUN_DIR from its last checkpoint")
    p.add_argument("--overwrite", action="store_true",
                   help="start a new run in RUN_DIR, deleting its checkpoints, loss curve and model")
    p.add_argument("--init", metavar="CKPT", help="start from these weights (fine-tuning)")
    p.add_argument("--steps", type=int, default=2000, help="optimiser steps in total (default 2000)")
    p.add_argument("--batch-size", type=int, default=4, help="items per step (default 4)")
    p.add_argument("--lr", type=float, default=1e-3, help="initial learning rate (cosine decay to 10%%; 1e-3)")
    p.add_argument("--size", choices=list(PRESETS),
                   help="network preset (default tiny): see 'presets' below; not with --init")
    p.add_argument("--cumulative", action="store_true",
                   help="feed step t the running mean of windows 0..t (the untrained network outputs the full TFP; "
                        "see docs/recon.md); not with --init")
    p.add_argument("--linearise", action="store_true",
                   help="remove the expected dark spikes and divide by the PRNU gain before the network (see "
                        "docs/recon.md); not with --init")
    p.add_argument("--level-input", action="store_true",
                   help="give the denoiser and refine stage the log mean spike count (the light level the mean "
                        "normalisation divides out); not with --init")
    p.add_argument("--head", action="store_true",
                   help="add the output head: per-pixel weights over the network's image and Gaussian-smoothed "
                        "classic estimates (see docs/recon.md, 'The output head'); allowed with --init (the "
                        "checkpoint's network plus a new head)")
    p.add_argument("--head-sigmas", metavar="LIST", type=_sigmas,
                   help="with --head: widths [pixels] of the head's Gaussian-smoothed classic candidates, e.g. "
                        "0,0.75,1.5,3,6,12 (default 0,0.75,1.5,3,6); with --init, a head of the checkpoint is "
                        "replaced by a new one of these widths")
    p.add_argument("--head-windows", metavar="LIST", type=_counts,
                   help="with --head: the candidates' temporal support, window counts around the centre (0 = all), "
                        "e.g. 1,2,4,0 (default 0); each at every --head-sigmas width")
    p.add_argument("--head-motion", action="store_true",
                   help="with --head and a short --head-windows entry: give the head the per-pixel motion cue "
                        "(short- vs all-window disagreement in units of shot noise)")
    p.add_argument("--head-edges", choices=["symmetric", "replicate"],
                   help="with --head: how the candidates' Gaussians treat the image border: symmetric (mirrored, as "
                        "the classic baseline smooths; the default for a new head) or replicate (the edge pixel "
                        "repeated)")
    p.add_argument("--train-only", choices=["head"],
                   help="train only the output head, keeping the rest of the network fixed (with --init "
                        "CKPT --head: a few CPU minutes)")
    p.add_argument("--normalise", choices=["mean", "fixed"],
                   help="input/output normalisation (default mean; see below); not with --init")
    p.add_argument("--width", type=int, help="channels of the denoiser (overrides the preset)")
    p.add_argument("--res-blocks", type=int, help="residual blocks in the denoiser")
    p.add_argument("--attn-depth", type=int, help="windowed self-attention blocks")
    p.add_argument("--heads", type=int, help="attention heads")
    p.add_argument("--attn-window", type=int, help="attention window (pixels of the half-resolution bands)")
    p.add_argument("--checkpoint-every", type=int, default=100, help="steps between checkpoints")
    p.add_argument("--max-minutes", type=float, help="stop (with a checkpoint) after this much wall time")
    p.add_argument("--workers", type=int, default=0, help="data-loading worker processes")
    p.add_argument("--threads", type=int, help="torch CPU threads (default: torch's choice; 1 is best on a busy "
                   "2-core machine with --workers 1)")
    p.add_argument("--device", default="auto", help="auto (CUDA if present, else CPU), cpu or cuda")
    p.add_argument("--seed", type=_seed_type, default=0, help="spike seed of the training data; also seeds batch order "
                   "and weight init")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


#: largest --attn-window [pixels]: a 64 x 64 window's attention (4096 tokens) already holds 16 M weights per head
MAX_ATTN_WINDOW = 64
#: largest --width [channels]
MAX_WIDTH = 1024
SIZE_FLAGS = ("width", "res_blocks", "attn_depth", "heads", "attn_window")


def clear_run(out: Path) -> None:
    """Remove what `train` wrote into ``out`` (checkpoints, loss curve, model, config), nothing else."""
    for p in sorted((out / "checkpoints").glob("*.pt")) if (out / "checkpoints").is_dir() else []:
        p.unlink()
    for name in ("loss.csv", "loss.png", "config.json", "summary.json", "model.pt"):
        (out / name).unlink(missing_ok=True)


def _sigmas(text: str) -> list:
    """``--head-sigmas``: comma-separated widths >= 0 [pixels]."""
    import argparse
    import math
    try:
        v = [float(x) for x in str(text).split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated widths in pixels, got '{text}'") from None
    if not v or any(not math.isfinite(x) or x < 0 for x in v):
        raise argparse.ArgumentTypeError(f"expected finite widths >= 0 [pixels], got '{text}'")
    return v


def _counts(text: str) -> list:
    """``--head-windows``: comma-separated window counts >= 0 (0 = all windows)."""
    import argparse
    try:
        v = [int(x) for x in str(text).split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated window counts, got '{text}'") from None
    if not v or any(x < 0 for x in v) or len(set(v)) != len(v):
        raise argparse.ArgumentTypeError(f"expected distinct window counts >= 0, got '{text}'")
    return v


def run(args) -> int:
    import sys

    from recon.nets import RSIRConfig
    from recon.spec import build_datasets
    from recon.train import TrainConfig, train
    from sensor.errors import InputError

    from render2spike.commands._common import check_numbers, check_output
    check_output(args.out, overwrite=True, folder=True)  # a file or a file above it is refused; runs: below
    check_numbers(args, at_least=dict(steps=1, batch_size=1, checkpoint_every=1, workers=0, threads=1, width=1,
                                      res_blocks=0, attn_depth=0, heads=1, attn_window=1),
                  positive=("lr", "max_minutes"),
                  at_most=dict(attn_window=(MAX_ATTN_WINDOW, "pixels of the half-resolution bands; the attention "
                                                             "of one window grows as its fourth power"),
                               width=(MAX_WIDTH, "channels; memory grows as its square")))
    if args.overwrite and args.resume:
        raise InputError("--overwrite starts a new run and --resume continues one: give one of them",
                         field="--overwrite")
    if args.init and Path(args.init).exists() and Path(args.out).exists() and \
            Path(args.init).resolve().is_relative_to(Path(args.out).resolve()) and args.overwrite:
        raise InputError("--init lies inside the run directory that --overwrite would empty; copy it elsewhere "
                         "first", path=args.init, field="--init")
    given = [f"--{n.replace('_', '-')}" for n in SIZE_FLAGS + ("size", "normalise") if getattr(args, n) is not None]
    given += [f for f, on in (("--cumulative", args.cumulative), ("--linearise", args.linearise),
                              ("--level-input", args.level_input)) if on]
    if args.init and given:
        raise InputError(f"--init takes the network layout from the checkpoint; drop {', '.join(given)}",
                         field="--init")
    if args.resume and (given or args.head or args.train_only):
        extra = ["--head"] * args.head + ["--train-only"] * bool(args.train_only)
        raise InputError(f"--resume continues the stored network and training settings; drop "
                         f"{', '.join(given + extra)}", field="--resume")
    for flag, on in (("--head-sigmas", args.head_sigmas is not None), ("--head-windows", args.head_windows is not None),
                     ("--head-motion", args.head_motion), ("--head-edges", args.head_edges is not None)):
        if on and not args.head:
            raise InputError(f"{flag} sets the output head's bank: add --head", field=flag)
    if args.train_only and not args.init:
        raise InputError("--train-only head keeps the rest of the network as it is: start from a trained one with "
                         "--init CKPT --head", field="--train-only")
    ds = build_datasets(args.data, split="train", model=args.noise_model, seed=args.seed)
    if args.overwrite:
        clear_run(Path(args.out))
    net = RSIRConfig.preset(args.size or "tiny", normalise=args.normalise or "mean", cumulative=args.cumulative,
                             linearise=args.linearise, level_input=args.level_input, head=args.head,
                             **{k: v for k, v in (("head_sigmas", args.head_sigmas), ("head_windows", args.head_windows),
                                                  ("head_motion", args.head_motion or None),
                                                  ("head_edges", args.head_edges)) if v is not None})
    for name in SIZE_FLAGS:
        v = getattr(args, name)
        if v is not None:
            setattr(net, name, v)
    cfg = TrainConfig(steps=args.steps, batch_size=args.batch_size, lr=args.lr,
                      checkpoint_every=args.checkpoint_every, seed=args.seed, workers=args.workers,
                      max_minutes=args.max_minutes, device=args.device,
                      threads=args.threads, train_only=args.train_only)
    info = {"data": args.data, "noise_model": ds.model, "items": len(ds), "command": " ".join(sys.argv),
            "size": args.size or "tiny"}
    summary = train(ds, args.out, net_config=net, train_config=cfg, resume=args.resume, init_checkpoint=args.init,
                    add_head=args.head, head_sigmas=args.head_sigmas, head_windows=args.head_windows,
                    head_motion=args.head_motion or None, head_edges=args.head_edges, run_info=info,
                    progress=not args.quiet)
    print(f"trained {summary['steps_done']} steps in {summary['elapsed_s'] / 60:.1f} min on {summary['device']}; "
          f"final loss {summary['final_loss']:.4g}; model: {summary['model']}")
    return 0
