"""``render2spike reconstruct``: images from a spike file with TFP, TFI, dead-time-corrected TFP or a network."""

from __future__ import annotations

EXAMPLES = """examples:
  render2spike reconstruct out/demo/spikes.npz --method rsir --out rec            (the shipped network)
  render2spike reconstruct ../shared/data/real/uhsr.npz --method rsir --out rec   (Spike-Zoo/UHSR .npz, 200
      intervals: the 10 windows shrink to 20 intervals each; or --windows 5 --window-length 40)
  render2spike reconstruct scene.dat --height 250 --width 400 --method tfp-dt-denoised --out rec
  render2spike reconstruct capture.dat --layout vidar-raw --method tfp --window 200 --every 100 --out rec
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
                    "(rate_e / threshold_e; tfp-dt: the same scale, from its rate_e). Reads every layout "
                    "sensor.read_spikes knows (container .npz, .dat, Spike-Zoo/UHSR 'spk' .npz, SpikingSIM "
                    "'arr_0' .npz, RSIR packed .npz, HDF5); any height and width.",
        epilog=EXAMPLES, formatter_class=HelpFormatter)
    p.add_argument("spikes", metavar="SPIKES", help="spike file (.npz, .dat, .h5)")
    p.add_argument("--method", default="tfp", choices=["tfp", "tfi", "tfp-dt", "tfp-dt-denoised", "rsir"],
                   help="tfp (default), tfi, tfp-dt (dead-time corrected), tfp-dt-denoised (the strong classic "
                        "baseline: window and width tuned per light level and measured speed), rsir (a network)")
    p.add_argument("--checkpoint", metavar="CKPT",
                   help="network checkpoint for rsir (default: the pretrained network shipped with the package)")
    p.add_argument("--out", required=True, metavar="DIR")
    p.add_argument("--window", type=int,
                   help="TFP / tfp-dt window [intervals] (default min(320, recording length))")
    p.add_argument("--windows", type=int, metavar="N",
                   help="rsir: TFP windows fed to the network (default the checkpoint's, 10)")
    p.add_argument("--window-length", type=int, metavar="L",
                   help="rsir: intervals per window (default the checkpoint's, 32, or recording // N if shorter)")
    p.add_argument("--sigma", type=float, help="tfp-dt-denoised: fixed Gaussian width [pixels] "
                   "(default: from the mean spike count with the tuned table)")
    p.add_argument("--center", type=int, help="interval to reconstruct (default: the stream's middle)")
    p.add_argument("--every", type=int, help="reconstruct every N intervals instead of one instant")
    p.add_argument("--profile", help="sensor profile (name or path): maps for rsir, the model for tfp-dt "
                   "(default: a uniform vidar-like sensor, no PRNU, with the hot pixels found in the recording "
                   "itself; a warning says so)")
    p.add_argument("--layout", help="spike-file layout (default: detected; see `render2spike info --layouts` "
                   "or sensor.spike_layouts())")
    p.add_argument("--height", type=int, help=".dat frame height (default 250)")
    p.add_argument("--width", type=int, help=".dat frame width as stored (default 400)")
    p.add_argument("--drop-columns", type=int, default=0, help=".dat columns to drop on the right (16 for raw 416)")
    p.add_argument("--formats", default="png,exr,npy", help="comma-separated subset of png, exr, npy")
    p.add_argument("--device", default="auto", help="auto (CUDA if present, else CPU), cpu or cuda (rsir only)")
    add_overwrite(p, "write into an existing, non-empty output folder")
    p.set_defaults(func=run)


def run(args) -> int:
    from recon.reconstruct import reconstruct_file

    from render2spike.commands._common import check_numbers, check_output
    check_numbers(args, at_least=dict(window=1, windows=1, window_length=1, every=1, center=0, drop_columns=0),
                  positive=("sigma",))
    only = {"checkpoint": "rsir", "windows": "rsir", "window_length": "rsir", "sigma": "tfp-dt-denoised"}
    for name, method in only.items():
        if getattr(args, name) is not None and args.method != method:
            from sensor.errors import InputError
            flag = "--" + name.replace("_", "-")
            raise InputError(f"applies only to --method {method} (this is --method {args.method}); drop it or "
                             "change the method", field=flag)
    from recon.baselines import MAX_SIGMA_PX
    if args.sigma is not None and args.sigma > MAX_SIGMA_PX:
        from sensor.errors import InputError
        raise InputError(f"must be at most {MAX_SIGMA_PX:g} pixels; got {args.sigma}", field="--sigma")
    check_output(args.out, inputs=[args.spikes, args.checkpoint], overwrite=args.overwrite, folder=True)
    written = reconstruct_file(args.spikes, method=args.method, checkpoint=args.checkpoint, out_dir=args.out,
                               window=args.window, center=args.center, every=args.every, profile=args.profile,
                               height=args.height, width=args.width, drop_columns=args.drop_columns,
                               formats=args.formats, device=args.device, layout=args.layout,
                               n_windows=args.windows, window_length=args.window_length, sigma=args.sigma)
    print(f"wrote {len(written)} file(s) to {args.out}")
    return 0
