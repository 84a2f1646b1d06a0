"""``render2spike reconstruct``: images from a spike file with TFP, TFI, dead-time-corrected TFP or a network."""

from __future__ import annotations

import argparse


EXAMPLES = """\
examples:
  render2spike reconstruct out/demo/spikes.npz --out out/demo/tfp                  # TFP at the middle
  render2spike reconstruct out/demo/spikes.npz --method tfi --every 200 --out out/demo/tfi
  render2spike reconstruct rec.dat --height 250 --width 416 --drop-columns 16 --out rec_tfp
  render2spike reconstruct out/demo/spikes.npz --method rsir --checkpoint runs/x/model.pt --out out/demo/rsir
"""


def register(subparsers) -> None:
    from render2spike.commands._common import HelpFormatter, add_overwrite
    p = subparsers.add_parser(
        "reconstruct", help="reconstruct images from a spike file",
        description="Reconstruct the image at one or more instants of a spike stream. Outputs per instant: "
                    "NAME.png (display: divided by the image's 99.5th percentile, sRGB-encoded), NAME.exr "
                    "(linear, channel Y) and NAME.npy (linear float32), in ideal spikes per interval "
                    "(rate_e / threshold_e; tfp-dt: the same scale, from its rate_e).",
        epilog=EXAMPLES, formatter_class=HelpFormatter)
    p.add_argument("spikes", metavar="SPIKES", help="spike container (.npz) or SpikeCV .dat")
    p.add_argument("--method", default="tfp", choices=["tfp", "tfi", "tfp-dt", "rsir"])
    p.add_argument("--checkpoint", metavar="CKPT", help="network checkpoint (required for --method rsir)")
    p.add_argument("--out", required=True, metavar="DIR")
    p.add_argument("--window", type=int, default=320,
                   help="TFP / tfp-dt window [intervals] (rsir always uses 10 windows of 32)")
    p.add_argument("--center", type=int, help="interval to reconstruct (default: the stream's middle)")
    p.add_argument("--every", type=int, help="reconstruct every N intervals instead of one instant")
    p.add_argument("--profile", help="sensor profile (name or path): maps for rsir, the model for tfp-dt")
    p.add_argument("--height", type=int, default=250, help=".dat frame height")
    p.add_argument("--width", type=int, default=400, help=".dat frame width as stored")
    p.add_argument("--drop-columns", type=int, default=0, help=".dat columns to drop on the right (16 for raw 416)")
    p.add_argument("--formats", default="png,exr,npy", help="comma-separated subset of png, exr, npy")
    p.add_argument("--device", default="auto", help="auto (CUDA if present, else CPU), cpu or cuda (rsir only)")
    add_overwrite(p, "write into an existing, non-empty output folder")
    p.set_defaults(func=run)


def run(args) -> int:
    from recon.reconstruct import reconstruct_file

    from render2spike.commands._common import check_output
    check_output(args.out, inputs=[args.spikes, args.checkpoint], overwrite=args.overwrite, folder=True)
    written = reconstruct_file(args.spikes, method=args.method, checkpoint=args.checkpoint, out_dir=args.out,
                               window=args.window, center=args.center, every=args.every, profile=args.profile,
                               height=args.height, width=args.width, drop_columns=args.drop_columns,
                               formats=args.formats, device=args.device)
    print(f"wrote {len(written)} file(s) to {args.out}")
    return 0
