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

The whole spec is checked before anything renders (every value, scene,
profile and model; no value twice), and the plan is printed. DIR is locked
while the command runs: a second run into it is refused, naming this one's
pid and host. A DIR holding a dataset of another spec, or other files, is
refused unless --overwrite (which makes the dataset afresh).

Runs on Dask: a LocalCluster of --workers processes by default, an existing
cluster with --scheduler tcp://HOST:8786, or in this process with --workers 0.
Train on the result with `render2spike train --data rendered:DIR`.
--export spikezoo[=FOLDER] then writes the finished samples as Spike-Zoo /
SpikeCV pairs (docs/studies.md, "Export for Spike-Zoo and SpikeCV").
"""
EXAMPLES = """\
examples:
  render2spike dataset spec.yaml --out data/trans
  render2spike dataset spec.yaml --out data/trans --workers 2
  render2spike dataset spec.yaml --out data/big --scheduler tcp://head-node:8786
  render2spike train --data rendered:data/trans:crop=48x48 --out runs/trans --steps 200
  render2spike dataset spec.yaml --out data/trans --export spikezoo     (Spike-Zoo pairs in data/trans/spikezoo)

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
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="Dask scheduler of an existing cluster (tcp://HOST:8786); checked before anything is made, "
                        "with a connect timeout")
    p.add_argument("--workers", type=_whole(0, "0 (run here, without Dask) or a number of worker processes"),
                   default=None, help="LocalCluster worker processes (default: one per CPU); 0: run here without Dask")
    p.add_argument("--resources", metavar="NAME=N[,...]",
                   help="Dask resources every task claims, e.g. GPU=1 with workers started with --resources GPU=1 "
                        "(one task per GPU)")
    p.add_argument("--retries", type=_whole(0, "a number of retries"), default=2,
                   help="retries of a failed sample before it is reported (default: 2)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace what --out holds: a dataset of another spec, other files, or this spec's dataset "
                        "(made afresh); without it such a folder is refused and a dataset of this spec is resumed")
    p.add_argument("--export", metavar="spikezoo[=FOLDER]",
                   help="then write the finished samples as Spike-Zoo / SpikeCV pairs (train|test/spike/NAME.dat, "
                        "train|test/gt/NAME.png, export.json) in FOLDER (default DIR/spikezoo; an existing one is "
                        "refused unless --overwrite)")
    p.add_argument("--export-intervals", type=_whole(1, "intervals per exported spike file"), default=301,
                   metavar="N", help="intervals per exported spike file, centred on the ground truth (default: 301)")
    p.add_argument("--export-test-fraction", type=float, default=0.2, metavar="F",
                   help="fraction of the renders whose pairs go to test/ (default: 0.2)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _whole(minimum: int, what: str):
    """argparse type: a whole number >= ``minimum`` (one-line error naming what was expected)."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what} (a whole number >= {minimum}), got '{text}'") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"expected {what} (a whole number >= {minimum}), got {value}")
        return value
    return parse


def run(args) -> int:
    from render2spike.dataset import build_dataset, check_run_options, parse_resources
    from sensor.errors import InputError
    if not args.out.strip():
        raise InputError("expected a folder name, got ''", field="--out")
    from render2spike.commands._common import check_output
    check_output(args.out, overwrite=True, folder=True)  # a file, or a file above it; resuming and --overwrite: below
    resources = parse_resources(args.resources)
    check_run_options(args.workers, args.retries, resources, args.scheduler)
    export = None
    if args.export is not None:
        from render2spike.dataset_export import check_export_target, parse_export
        export = check_export_target(parse_export(args.export, args.out)[1], args.out, args.overwrite,
                                     intervals=args.export_intervals, test_fraction=args.export_test_fraction)
    res = build_dataset(args.spec, args.out, scheduler=args.scheduler, workers=args.workers, retries=args.retries,
                        resources=resources, progress=not args.quiet, overwrite=args.overwrite)
    print((res.out / "summary.md").read_text())
    if export is not None:
        from render2spike.dataset_export import export_spikezoo
        export_spikezoo(args.out, export, intervals=args.export_intervals, test_fraction=args.export_test_fraction,
                        overwrite=args.overwrite)
    return 1 if res.failed else 0
