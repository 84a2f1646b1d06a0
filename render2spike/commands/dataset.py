"""``render2spike dataset``: scene files -> spike datasets (render, simulate, ground truth), on Dask."""

from __future__ import annotations

import argparse

HELP = "make a spike dataset from a spec (scenes x lux x parameters x models x seeds), on one machine or a cluster"
DESCRIPTION = """\
Render scenes, simulate spike streams and store them with their ground truth,
as the spec SPEC.yaml lists (docs/studies.md describes every key):

  scenes, set, duration_s, lux, params (any numeric scene key or named scene
  parameter such as speed_px_per_ms), profiles, models (ideal, isi, elssim,
  MODEL:RESET), seeds -- as a grid (every combination) or as `samples` seeded
  random draws (mode: random; uniform / log_uniform ranges).

Each sample: DIR/samples/<id>/ with spikes.npz, truth.npz (clean rate, clean
image at each window centre, noise-free window average), its frames (scaled to
its lux) and sample.json. One render serves every lux of the same scene and
parameters. DIR/manifest.json records each sample; rerunning the command skips
finished samples (resume after a kill) and retries failed ones. Failures are
listed in the manifest and DIR/summary.md, never dropped.

Runs on Dask: a LocalCluster of --workers processes by default, an existing
cluster with --scheduler tcp://HOST:8786, or in this process with --workers 0.
Train on the result with `render2spike train --data rendered:DIR`.
"""
EXAMPLES = """\
examples:
  render2spike dataset spec.yaml --out data/trans
  render2spike dataset spec.yaml --out data/trans --workers 2
  render2spike dataset spec.yaml --out data/big --scheduler tcp://head-node:8786
  render2spike train --data rendered:data/trans:crop=48x48 --out runs/trans --steps 200

a small spec.yaml:
  scenes: [translating_object]
  set: ["render.spp=16"]
  duration_s: 0.03
  lux: [5, 50]
  params: {speed_px_per_ms: [0.1, 0.5]}
  models: [elssim, isi]
  seeds: [0, 1]
"""


def register(sub) -> None:
    p = sub.add_parser("dataset", help=HELP, description=DESCRIPTION, epilog=EXAMPLES,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("spec", metavar="SPEC.yaml", help="dataset spec (YAML or JSON)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (resumed when it exists)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="Dask scheduler of an existing cluster (tcp://HOST:8786)")
    p.add_argument("--workers", type=int, default=None,
                   help="LocalCluster worker processes (default: one per CPU); 0: run here without Dask")
    p.add_argument("--resources", metavar="NAME=N[,...]",
                   help="Dask resources every task claims, e.g. GPU=1 with workers started with --resources GPU=1 "
                        "(one task per GPU)")
    p.add_argument("--retries", type=int, default=2, help="retries of a failed sample before it is reported")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args) -> int:
    from render2spike.dataset import build_dataset, parse_resources
    res = build_dataset(args.spec, args.out, scheduler=args.scheduler, workers=args.workers, retries=args.retries,
                        resources=parse_resources(args.resources), progress=not args.quiet)
    print((res.out / "summary.md").read_text())
    return 1 if res.failed else 0
