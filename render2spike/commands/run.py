"""``render2spike run``: render -> simulate -> TFP preview -> summary, in one command."""

from __future__ import annotations

from render2spike.commands._common import seed as _seed_type

HELP = "render a scene, simulate the spike camera, write a preview and a summary"
DESCRIPTION = """\
The whole pipeline in one command:

  1. render SCENE (irradiance keyframes: Phi [e-/(s m^2)]), held in memory
     (4 bytes per pixel per keyframe, the whole clip); with --keep-frames
     written to OUT/frames instead (Phi and E [lux], resumable, see
     `render2spike render --help`);
  2. simulate the spike camera over the frames (Phi -> photoelectrons per
     interval via pixel area x fill factor x T_r, interpolated linearly in time;
     T_r = 50 us) -> OUT/spikes.npz;
  3. TFP previews (mean spikes per interval over a window) -> OUT/preview.png,
     OUT/preview.gif;
  4. a summary (spike rate, lux, frames, timings) -> OUT/summary.json, summary.md.

With --dat the spikes are also written as OUT/spikes.dat (SpikeCV layout).
The sensor profile comes from the scene (camera.profile) unless --profile is given.
--seed seeds the spike simulation (default 0), --render-seed the render; the same
scene, options and seeds give the same frames (bit for bit with the default frozen
launch; with --launch film to float round-off: at high spp a pixel may differ in its
last bits run to run, rarely on the CPU, often on a GPU) and, from the
same frames, bitwise-identical spikes, in memory or through OUT/frames, also after a
resumed render. Only with --keep-frames (or when OUT/frames exists already, which is
then rendered into) does a rerun into OUT resume the render; without it a rerun renders
again. The rest is rewritten; an OUT made with another scene, model, seed or profile is
refused unless --overwrite.
SCENE is a YAML file or a bundled scene name (rotating_disk, translating_object,
room_pan, lambertian_plane).
"""
EXAMPLES = """\
examples:
  render2spike run scenes/rotating_disk.yaml --out out/demo          # the README demo (~50 s CPU)
  render2spike run rotating_disk --out out/dim --lux 5 --model elssim --seed 1 --dat
  render2spike run translating_object --out out/ideal --model ideal --duration 0.05 --render-seed 2
"""


def register(sub) -> None:
    from sensor.models.registry import MODELS

    from render2spike.commands._common import HelpFormatter
    from render2spike.commands.render import add_scene_options
    p = sub.add_parser("run", help=HELP, description=DESCRIPTION, epilog=EXAMPLES, formatter_class=HelpFormatter)
    add_scene_options(p)
    p.add_argument("--seed", type=_seed_type, default=0, metavar="N",
                   help="spike seed: seeds the spike simulation (default: 0); --render-seed seeds the render")
    p.add_argument("--model", default="elssim", choices=MODELS, help="spike noise model (default: elssim)")
    p.add_argument("--dat", action="store_true", help="also write OUT/spikes.dat (SpikeCV .dat layout)")
    p.add_argument("--keep-frames", action="store_true",
                   help="write the rendered frames to OUT/frames (OpenEXR, as `render2spike render` does): a rerun "
                        "then resumes the render; without it they are held in memory and not written")
    p.add_argument("--preview-window", type=int, default=200, metavar="INTERVALS",
                   help="TFP window of the previews in intervals (default 200 = 10 ms)")
    p.set_defaults(func=run)


def run(args) -> int:
    from render2spike.commands.render import scene_sets, variant_of
    from render2spike.commands._common import check_output
    check_output(args.out, overwrite=True, folder=True)  # a file, or a file above it; resuming and --overwrite: below
    from render2spike.commands._common import check_numbers
    from render2spike.pipeline import run_pipeline
    check_numbers(args, at_least=dict(preview_window=1))
    s = run_pipeline(args.scene, args.out, sets=scene_sets(args), lux=args.lux, duration_s=args.duration,
                     profile=args.profile, model=args.model, seed=args.seed, overwrite=args.overwrite,
                     progress=not args.quiet, preview_window=args.preview_window, dat=args.dat,
                     variant=variant_of(args), launch=args.launch, keep_frames=args.keep_frames)
    print(f"run: {s['scene']} at {s['illuminance_lux']:g} lux: {s['frames']} frames, {s['intervals']} intervals, "
          f"{s['spikes']} spikes ({s['spike_rate_hz']:.1f} Hz per pixel); {s['seconds']['total']:.1f} s -> {args.out}")
    print(f"run: preview {s['files']['png']}, {s['files']['gif']}; summary {args.out}/summary.md")
    return 0
