"""``render2spike train``: train an RSIR-architecture reconstruction network on simulated (or paired) spikes."""

from __future__ import annotations

from pathlib import Path

HELP_DATA = ("data spec KIND:PATH[,PATH...][:key=value...], KIND davis | sdmd | rendered; e.g. "
             "davis:/data/DAVIS:crop=64x64:lux=5-50 (see docs/recon.md)")


EXAMPLES = """\
examples:
  python -m recon.synth data/dvsynth --sequences 90 --frames 12 --size 96x128 --seed 7
  render2spike train --data davis:data/dvsynth:crop=64x64:res=96x128 --noise-model elssim \\
      --out runs/dvsynth --steps 1500 --max-minutes 18
  render2spike train --data davis:data/dvsynth:crop=64x64 --out runs/dvsynth --steps 3000 --resume
  render2spike train --data rendered:out/demo/frames --out runs/ft --init runs/dvsynth/model.pt --steps 200
"""


def register(subparsers) -> None:
    from render2spike.commands._common import HelpFormatter
    p = subparsers.add_parser(
        "train", help="train a reconstruction network (RSIR architecture)",
        description="Train an RSIR-architecture network on spikes simulated from DAVIS-layout or rendered data "
                    "(or on SDMD-style real pairs). Input: 10 TFP windows of 32 intervals (M = 320); target: the "
                    "clean intensity at the window centre in ideal spikes per interval (rate_e / threshold_e).",
        epilog=EXAMPLES, formatter_class=HelpFormatter)
    p.add_argument("--data", required=True, help=HELP_DATA)
    p.add_argument("--noise-model", default="elssim", choices=["elssim", "ideal", "isi"],
                   help="spike model the training spikes are simulated with (a model= spec option wins)")
    p.add_argument("--out", required=True, metavar="RUN_DIR", help="run directory (checkpoints, loss curve)")
    p.add_argument("--resume", action="store_true", help="continue the run in RUN_DIR from its last checkpoint")
    p.add_argument("--overwrite", action="store_true",
                   help="start a new run in RUN_DIR, deleting its checkpoints, loss curve and model")
    p.add_argument("--init", metavar="CKPT", help="start from these weights (fine-tuning)")
    p.add_argument("--steps", type=int, default=2000, help="optimiser steps in total")
    p.add_argument("--batch-size", type=int, default=4, help="items per optimiser step")
    p.add_argument("--lr", type=float, default=1e-3, help="initial learning rate (cosine decay to 10%%)")
    p.add_argument("--size", default="tiny", choices=["tiny", "paper"],
                   help="network size preset: tiny (CPU minutes) or paper (RSIR-like widths)")
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
    p.add_argument("--seed", type=int, default=0, help="spike seed of the training data; also seeds batch order "
                   "and weight init")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def clear_run(out: Path) -> None:
    """Remove what `train` wrote into ``out`` (checkpoints, loss curve, model, config), nothing else."""
    for p in sorted((out / "checkpoints").glob("*.pt")) if (out / "checkpoints").is_dir() else []:
        p.unlink()
    for name in ("loss.csv", "loss.png", "config.json", "summary.json", "model.pt"):
        (out / name).unlink(missing_ok=True)


def run(args) -> int:
    import sys

    from recon.nets import RSIRConfig
    from recon.spec import build_dataset, parse_data_spec
    from recon.train import TrainConfig, train

    from sensor.errors import InputError
    if args.overwrite and args.resume:
        raise InputError("--overwrite starts a new run and --resume continues one: give one of them",
                         field="--overwrite")
    if args.init and Path(args.init).exists() and Path(args.out).exists() and \
            Path(args.init).resolve().is_relative_to(Path(args.out).resolve()) and args.overwrite:
        raise InputError("--init lies inside the run directory that --overwrite would empty; copy it elsewhere "
                         "first", path=args.init, field="--init")
    spec = parse_data_spec(args.data)
    if args.overwrite:
        clear_run(Path(args.out))
    ds = build_dataset(spec, split="train", model=args.noise_model, seed=args.seed)
    net = RSIRConfig.tiny() if args.size == "tiny" else RSIRConfig()
    for name in ("width", "res_blocks", "attn_depth", "heads", "attn_window"):
        v = getattr(args, name)
        if v is not None:
            setattr(net, name, v)
    cfg = TrainConfig(steps=args.steps, batch_size=args.batch_size, lr=args.lr,
                      checkpoint_every=args.checkpoint_every, seed=args.seed, workers=args.workers,
                      max_minutes=args.max_minutes, device=args.device,
                      threads=args.threads)
    info = {"data": args.data, "noise_model": ds.model, "items": len(ds), "command": " ".join(sys.argv)}
    summary = train(ds, args.out, net_config=net, train_config=cfg, resume=args.resume, init_checkpoint=args.init,
                    run_info=info, progress=not args.quiet)
    print(f"trained {summary['steps_done']} steps in {summary['elapsed_s'] / 60:.1f} min on {summary['device']}; "
          f"final loss {summary['final_loss']:.4g}; model: {summary['model']}")
    return 0
