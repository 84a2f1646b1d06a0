"""``render2spike study``: lux sweeps and cross-noise-model tables over rendered frames."""

from __future__ import annotations

HELP = "sweep light levels and noise models over rendered frames; tables and plots of PSNR/SSIM"
DESCRIPTION = """\
Measure how well a rendered scene can be recovered from spikes, across light levels
and noise models.

FRAMES is a frames folder from `render2spike render`. Rendering is linear in the
light, so the frames are rescaled exactly from the illuminance they were rendered
at (frames.json: illuminance_lux) to each --lux value. Each (lux, model, seed) job
simulates the spike stream and reconstructs images (TFP, dead-time-corrected TFP,
TFI) at window centres, scored against the clean photoelectron rate.

Writes OUT/summary.md (models x lux tables per method), summary.csv, rows.csv,
psnr_vs_lux.png and study.json. Jobs run one after another, or on a Dask cluster
with --dask local (all cores of this machine) or --dask tcp://SCHEDULER:8786.
"""
EXAMPLES = """\
examples:
  render2spike render translating_object --out out/trans --duration 0.05
  render2spike study out/trans/frames --out out/lux_study --lux 0.5,5,50,500 --models elssim,isi
  render2spike study out/trans/frames --out out/lux_study --seeds 0,1,2 --dask local
"""


def _floats(text):
    return [float(x) for x in text.split(",") if x.strip()]


def _words(text):
    return [x.strip() for x in text.split(",") if x.strip()]


def register(sub) -> None:
    from render2spike.commands._common import HelpFormatter, add_overwrite
    p = sub.add_parser("study", help=HELP, description=DESCRIPTION, epilog=EXAMPLES, formatter_class=HelpFormatter)
    p.add_argument("frames", metavar="FRAMES", help="frames folder (from render2spike render)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--lux", type=_floats, default=[0.5, 5.0, 50.0, 500.0], metavar="L1,L2,...",
                   help="scene illuminances [lux] (default 0.5,5,50,500)")
    p.add_argument("--models", type=_words, default=["elssim", "isi", "ideal"], metavar="M1,M2",
                   help="noise models (default elssim,isi,ideal)")
    p.add_argument("--methods", type=_words, default=["tfp", "tfp-dt"], metavar="tfp,tfp-dt,tfi",
                   help="reconstructions to score (default tfp,tfp-dt)")
    p.add_argument("--seeds", type=lambda s: [int(x) for x in s.split(",")], default=[0], metavar="S1,S2",
                   help="spike seeds: one simulation per seed (default 0)")
    p.add_argument("--profile", default="vidar-default", metavar="NAME|PATH",
                   help="sensor profile (centre-windowed to the frames; default vidar-default)")
    p.add_argument("--window", type=int, default=320, help="reconstruction window [intervals] (default 320)")
    p.add_argument("--centers", type=int, default=3, help="window centres per stream (default 3)")
    p.add_argument("--reference-lux", type=float, default=None,
                   help="illuminance the frames were rendered at, if frames.json does not say")
    p.add_argument("--dask", default=None, metavar="local|ADDRESS", help="run the jobs on a Dask cluster")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_overwrite(p, "write into an existing, non-empty output folder")
    p.set_defaults(func=run)


def run(args) -> int:
    from render2spike.commands._common import check_output
    from render2spike.studies import make_client, plan_lux_sweep, run_jobs, write_study
    check_output(args.out, inputs=[args.frames], overwrite=args.overwrite, folder=True)
    jobs = plan_lux_sweep(args.frames, args.lux, args.models, args.seeds, profile=args.profile, window=args.window,
                          n_centers=args.centers, methods=args.methods, reference_lux=args.reference_lux)
    client = make_client(args.dask)
    try:
        rows = run_jobs(jobs, client, progress=not args.quiet)
    finally:
        if client is not None:
            client.close()
    paths = write_study(args.out, rows, jobs, title="Reconstruction quality vs illuminance and noise model")
    print((paths[2]).read_text())
    print("wrote " + ", ".join(str(p) for p in paths))
    return 0
