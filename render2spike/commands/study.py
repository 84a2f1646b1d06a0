"""``render2spike study lux|motion|generalisation``: sweeps over light, motion and noise models."""

from __future__ import annotations

from render2spike.commands._common import seed as _seed_type
from render2spike.commands._common import seed_list as _seed_list

import argparse
from pathlib import Path

HELP = "studies: quality vs light level (lux), vs a scene parameter such as speed (motion), across noise models"
DESCRIPTION = """\
Three studies, each writing a CSV of every row, a Markdown summary and PNG plots
(docs/studies.md explains what each measures):

  render2spike study lux FRAMES --out DIR ...
      reconstruction quality vs illuminance and noise model, over rendered frames
      (the frames are rescaled exactly: light is linear). The short form
      `render2spike study FRAMES ...` means `study lux FRAMES ...`.
  render2spike study motion SCENE --param KEY=v1,v2,... --out DIR ...
      PSNR, SSIM and blur width vs any numeric scene parameter (the bundled
      rotating_disk and translating_object expose speed_px_per_ms).
  render2spike study generalisation --data SPEC.yaml --out DIR ...
      networks trained on each noise model, tested on data of every model.

Run `render2spike study lux --help` (motion, generalisation) for each one's options.
"""
EXAMPLES = """\
examples:
  render2spike render scenes/translating_object.yaml --out out/trans --duration 0.05
  render2spike study lux out/trans --out out/lux --lux 0.5,5,50,500 --models elssim,isi --seeds 0,1,2
  render2spike study motion translating_object --param speed_px_per_ms=0.1,0.3,1 --out out/motion \\
      --duration 0.03 --set render.spp=16
  render2spike study generalisation --data spec.yaml --train-models ideal,isi,elssim:crossing --out out/gen
"""
STUDIES = ("lux", "motion", "generalisation")


def _floats(text):
    return [float(x) for x in text.split(",") if x.strip()]


def _words(text):
    return [x.strip() for x in text.split(",") if x.strip()]


def _ints(text):
    return [int(x) for x in text.split(",") if x.strip()]


def register(sub) -> None:
    p = sub.add_parser("study", help=HELP, description=DESCRIPTION, epilog=EXAMPLES,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("which", metavar="lux|motion|generalisation", help="the study (or a frames folder: `study lux`)")
    p.add_argument("rest", nargs=argparse.REMAINDER, help="the study's arguments (see `study STUDY --help`)")
    p.set_defaults(func=run)


def _common(p, window=320):
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--overwrite", action="store_true", help="write into an existing, non-empty output folder")
    p.add_argument("--methods", default="tfp,tfp-dt,tfp-dt-denoised", metavar="M1,M2",
                   help="reconstructions (recon's registry: tfp, tfp:N, tfi, tfp-dt, rsir:CKPT, ...; default "
                        "tfp,tfp-dt,tfp-dt-denoised: the strongest classic estimate is always in the table); the "
                        "noise-free window average is always added")
    p.add_argument("--seeds", type=_seed_list, default=[0, 1, 2], metavar="S1,S2",
                   help="simulation seeds; error bars are the spread of the per-seed means (default 0,1,2)")
    p.add_argument("--window", type=int, default=window, help=f"reconstruction window [intervals] (default {window})")
    p.add_argument("--preroll", type=int, default=2000,
                   help="intervals simulated and dropped before the clip so the sensor starts in its stationary "
                        "state (default 2000 = 0.1 s)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def lux_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="render2spike study lux", formatter_class=argparse.RawDescriptionHelpFormatter,
                                description="""\
Reconstruction quality vs illuminance and noise model, over a frames folder.

The frames are rescaled exactly from the illuminance they were rendered at
(frames.json: illuminance_lux) to each --lux. Each (lux, model, seed) job
pre-rolls the sensor (--preroll), simulates the spikes and reconstructs the
window at each centre with every method, scored against the clean rate of the
centre interval. Writes rows.csv, summary.csv, summary.md (models x lux per
method, ± the spread over seeds, a noise-free row, warnings for cells with too
few light spikes), psnr_vs_lux.png, ssim_vs_lux.png (with a signal axis in e-
per interval) and study.json.""", epilog="""\
examples:
  render2spike study lux out/trans --out out/lux --lux 0.5,5,50,500 --models elssim,isi,ideal
  render2spike study lux out/trans --out out/lux --methods tfp,tfp-dt,rsir:runs/a/model.pt --dask local
""")
    p.add_argument("frames", metavar="FRAMES", help="frames folder (from render2spike render)")
    _common(p)
    p.add_argument("--lux", type=_floats, default=[0.5, 5.0, 50.0, 500.0], metavar="L1,L2,...",
                   help="scene illuminances [lux] (default 0.5,5,50,500)")
    p.add_argument("--models", type=_words, default=["elssim", "isi", "ideal"], metavar="M1,M2",
                   help="noise models: ideal, isi, elssim, MODEL:RESET (default elssim,isi,ideal)")
    p.add_argument("--profile", default="vidar-default", metavar="NAME|PATH",
                   help="sensor profile (centre-windowed to the frames; default vidar-default)")
    p.add_argument("--centers", type=int, default=3, help="window centres per stream (default 3)")
    p.add_argument("--reference-lux", type=float, default=None,
                   help="illuminance the frames were rendered at, if frames.json does not say")
    p.add_argument("--dask", default=None, metavar="local|ADDRESS", help="run the jobs on a Dask cluster")
    return p


def motion_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="render2spike study motion", formatter_class=argparse.RawDescriptionHelpFormatter,
                                description="""\
Reconstruction quality and blur width vs a scene parameter.

For each value of --param the scene is rendered (cached under OUT/renders by
content hash), then for each model and seed simulated (after --preroll),
reconstructed by every method and scored against the clean image of the centre
interval. Blur width is the 10-90 % edge spread [px] along the motion, for each
method and for the noise-free window average. Writes rows.csv, summary.csv,
summary.md, psnr_vs_P.png, ssim_vs_P.png, blur_vs_P.png, strip.png, study.json.""",
                                epilog="""\
examples:
  render2spike study motion translating_object --param speed_px_per_ms=0.1,0.3,1 --out out/motion \\
      --duration 0.03 --set render.spp=16
  render2spike study motion rotating_disk --param speed_px_per_ms=0.1,0.5 --out out/disk --duration 0.03
  render2spike study motion my_scene.yaml --param objects.ball.motion.parametric.0.translate.velocity_m_s.0=0.5,2 \\
      --blur-axis x --out out/ball
""")
    p.add_argument("scene", metavar="SCENE", help="scene file or bundled scene name")
    p.add_argument("--param", required=True, metavar="KEY=v1,v2,...",
                   help="the swept parameter: a named scene parameter (speed_px_per_ms) or a numeric dotted key")
    _common(p)
    p.add_argument("--models", type=_words, default=["elssim"], metavar="M1,M2", help="noise models (default elssim)")
    p.add_argument("--lux", type=float, default=None, help="scene illuminance [lux] (default: the scene's)")
    p.add_argument("--duration", type=float, default=None, help="clip length [s] (default: the scene's)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="scene override (repeatable)")
    p.add_argument("--profile", default=None, help="sensor profile for the simulation (default: the scene's)")
    p.add_argument("--centers", type=int, default=1, help="window centres per stream (default 1)")
    p.add_argument("--blur-axis", default="auto", choices=("auto", "x", "y", "polar"),
                   help="direction of the motion in the image (auto: from the scene parameter, else x)")
    p.add_argument("--edge-radius", type=int, default=20,
                   help="edge profiles span this many pixels either side; blur wider than it is not measurable "
                        "(default 20)")
    return p


def generalisation_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="render2spike study generalisation",
                                formatter_class=argparse.RawDescriptionHelpFormatter, description="""\
Cross-noise-model generalisation: one network per training model, each tested
on data simulated with every test model from the same scenes and seeds.

--data is a dataset spec (as for `render2spike dataset`); its scenes are
rendered into OUT/data and split by sample into train and test frames (the
last --test-fraction of the samples are test). Networks are trained (tiny by
default) into OUT/nets/MODEL and reused when already there (or given with
--reuse MODEL=CKPT). Writes matrix.csv, matrix.md (PSNR / SSIM ± sd over test
items; rows: training model, plus the classic baselines; columns: test model),
heatmap.png and study.json.""", epilog="""\
examples:
  render2spike study generalisation --data spec.yaml --out out/gen --train-models ideal,isi,elssim \\
      --test-models ideal,isi,elssim:interval,elssim:crossing --steps 200 --crop 32x32
  render2spike study generalisation --data spec.yaml --out out/gen --reuse elssim=runs/big/model.pt
""")
    p.add_argument("--data", required=True, metavar="SPEC.yaml", help="dataset spec (scenes, lux, parameters)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--overwrite", action="store_true", help="write into an existing, non-empty output folder")
    p.add_argument("--train-models", type=_words, default=["ideal", "isi", "elssim:interval", "elssim:crossing"],
                   metavar="M1,M2", help="one network per model (ideal, isi, elssim, MODEL:RESET; a bare elssim "
                   "follows the profile's reset; default ideal,isi,elssim:interval,elssim:crossing)")
    p.add_argument("--test-models", type=_words, default=None, metavar="M1,M2",
                   help="test data models (default: the training models)")
    p.add_argument("--baselines", default="tfp-dt,tfp-dt-denoised", metavar="M1,M2",
                   help="classic methods scored on the same test items (default tfp-dt,tfp-dt-denoised; '' for none)")
    p.add_argument("--reuse", action="append", default=[], metavar="MODEL=CKPT",
                   help="use this checkpoint for MODEL instead of training (repeatable)")
    p.add_argument("--steps", type=int, default=200, help="training steps per network (default 200)")
    p.add_argument("--batch-size", type=int, default=4, help="batch size (default 4)")
    p.add_argument("--size", choices=("tiny", "full"), default="tiny", help="network size (default tiny)")
    p.add_argument("--width", type=int, default=None, help="network width (overrides the size's)")
    p.add_argument("--crop", default=None, metavar="HxW", help="centre crop of the frames (smaller = faster)")
    p.add_argument("--test-fraction", type=float, default=0.25, help="fraction of the samples used for testing")
    p.add_argument("--profile", default="vidar-default", help="sensor profile (centre-windowed; default vidar-default)")
    p.add_argument("--seed", type=_seed_type, default=0, help="seed of training order and test noise (default 0)")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    p.add_argument("--workers", type=int, default=0, help="dataset workers (0: this process; see `dataset`)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    return p


def run(args) -> int:
    which, rest = args.which, list(args.rest)
    if which not in STUDIES:
        if which in ("-h", "--help"):
            print(DESCRIPTION)
            return 0
        if Path(which).exists() or not which.isidentifier():
            which, rest = "lux", [which] + rest  # the short form: study FRAMES ...
        else:
            from sensor.errors import UnknownMethodError
            raise UnknownMethodError("study", which, STUDIES)
    if which == "lux":
        return run_lux(lux_parser().parse_args(rest))
    if which == "motion":
        return run_motion(motion_parser().parse_args(rest))
    return run_generalisation(generalisation_parser().parse_args(rest))


def run_lux(a) -> int:
    from render2spike.commands._common import check_numbers, check_output
    from render2spike.studies.lux import make_client, plan_lux_sweep, run_jobs, write_study
    check_numbers(a, at_least=dict(window=1, preroll=0, centers=1), positive=("reference_lux",))
    check_output(a.out, inputs=[a.frames], overwrite=a.overwrite, folder=True)
    jobs = plan_lux_sweep(a.frames, a.lux, a.models, a.seeds, profile=a.profile, window=a.window,
                          n_centers=a.centers, methods=a.methods, reference_lux=a.reference_lux, preroll=a.preroll)
    client = make_client(a.dask)
    try:
        rows = run_jobs(jobs, client, progress=not a.quiet)
    finally:
        if client is not None:
            client.close()
    paths = write_study(a.out, rows, jobs, title="Reconstruction quality vs illuminance and noise model")
    print((Path(a.out) / "summary.md").read_text())
    print("wrote " + ", ".join(str(p) for p in paths))
    return 0


def run_motion(a) -> int:
    from render2spike.commands._common import check_numbers, check_output
    from render2spike.studies.motion import parse_param, run_motion_study
    check_numbers(a, at_least=dict(window=1, preroll=0, centers=1, edge_radius=1), positive=("lux", "duration"))
    check_output(a.out, overwrite=a.overwrite, folder=True)
    key, values = parse_param(a.param)
    res = run_motion_study(a.scene, key, values, a.out, methods=a.methods, models=a.models, seeds=a.seeds,
                           lux=a.lux, duration_s=a.duration, sets=a.set, profile=a.profile, window=a.window,
                           n_centers=a.centers, preroll=a.preroll, blur_axis=a.blur_axis,
                           edge_radius=a.edge_radius, progress=not a.quiet)
    print(Path(res["table"]).read_text())
    print("wrote " + ", ".join([res["table"], res["strip"]] + list(res["plots"].values())))
    return 0


def run_generalisation(a) -> int:
    from render2spike.commands._common import check_numbers, check_output
    from render2spike.studies.generalisation import run_generalisation_study
    check_numbers(a, at_least=dict(steps=1, batch_size=1, width=1, threads=1, workers=0), positive=("test_fraction",))
    if not a.test_fraction < 1:
        from sensor.errors import InputError
        raise InputError(f"must be in (0, 1); got {a.test_fraction}", field="--test-fraction")
    check_output(a.out, inputs=[a.data], overwrite=a.overwrite, folder=True)
    res = run_generalisation_study(a.data, a.out, train_models=a.train_models, test_models=a.test_models,
                                   baselines=a.baselines, reuse=a.reuse, steps=a.steps, batch_size=a.batch_size,
                                   size=a.size, width=a.width, crop=a.crop, test_fraction=a.test_fraction,
                                   profile=a.profile, seed=a.seed, threads=a.threads, workers=a.workers,
                                   overwrite=a.overwrite, progress=not a.quiet)
    print(Path(res["table"]).read_text())
    print("wrote " + ", ".join([res["table"], res["csv"], res["heatmap"]]))
    return 0
