"""``render2spike scenegen``: procedural scene files, seeded (render2spike.scenegen)."""

from __future__ import annotations

HELP = "write procedural scene files: random rigid objects before a textured background, seeded"
DESCRIPTION = """\
Write COUNT scene files drawn by the procedural generator (render2spike/scenegen.py) into --out, as
procedural_SEED_IIII.yaml. Scene I of a seed is the same on every machine and run. Each holds:

  camera       the --profile sensor (default vidar-default) on a centred --window (default 64 96),
               f = 8 mm, f/2, facing a background plane --distance metres away (log-uniform, default 0.8 3)
  objects      --objects LOW HIGH of them (default 1 4): spheres, cubes, cylinders, disks, rectangles and
               the bundled meshes (torus, blob, cone, capsule), 10-40 % of the view wide, textured with
               scikit-image's photographs or procedural textures, or plain
  motion       a share --still-fraction of the scenes is still (default 0.2); in the others each object
               translates and turns at an image speed log-uniform in --speed LOW HIGH [px/ms] (default
               0.05 3), and the camera pans at such a speed with probability --camera-motion (default 0.5)
  light        a directional key light (3000-6500 K) from a random direction, a dim sky, at times a lamp;
               illuminance_lux log-uniform in --lux LOW HIGH (default 0.5 500)

A dataset spec takes the same scenes without files: scenes: [{procedural: {count: 100, seed: 0}}]
(docs/studies.md). Render one: render2spike render DIR/procedural_0_0000.yaml --out FRAMES.
"""
EXAMPLES = """\
examples:
  render2spike scenegen --count 20 --seed 0 --out scenes_gen
  render2spike scenegen --count 5 --seed 1 --speed 1 3 --objects 3 6 --window 128 192 --out fast
  render2spike scenegen --count 10 --seed 2 --still-fraction 1 --lux 0.5 5 --out dim_still
"""


def register(sub) -> None:
    from render2spike.commands._common import HelpFormatter, add_overwrite
    p = sub.add_parser("scenegen", help=HELP, description=DESCRIPTION, epilog=EXAMPLES, formatter_class=HelpFormatter)
    p.add_argument("--count", type=int, required=True, metavar="N", help="how many scenes")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="generator seed (default 0)")
    p.add_argument("--out", required=True, metavar="DIR", help="folder for the scene files")
    p.add_argument("--objects", type=int, nargs=2, metavar=("LOW", "HIGH"), help="objects per scene (default 1 4)")
    p.add_argument("--speed", type=float, nargs=2, metavar=("LOW", "HIGH"),
                   help="image speed of moving objects and camera [px/ms] (default 0.05 3)")
    p.add_argument("--still-fraction", type=float, metavar="P", help="share of still scenes (default 0.2)")
    p.add_argument("--camera-motion", type=float, metavar="P",
                   help="probability that the camera pans in a moving scene (default 0.5)")
    p.add_argument("--lux", type=float, nargs=2, metavar=("LOW", "HIGH"),
                   help="illuminance at the background's centre [lux] (default 0.5 500)")
    p.add_argument("--distance", type=float, nargs=2, metavar=("LOW", "HIGH"),
                   help="camera to background [m] (default 0.8 3)")
    p.add_argument("--window", type=int, nargs=2, metavar=("H", "W"), help="sensor window [px] (default 64 96)")
    p.add_argument("--profile", metavar="NAME|PATH", help="sensor profile (default vidar-default)")
    p.add_argument("--duration", type=float, metavar="S", help="clip length [s] (default 0.1)")
    add_overwrite(p)
    p.set_defaults(func=run)


def options_from(args) -> dict:
    """The generator options the arguments give (only those given; the generator fills the rest)."""
    pairs = {"objects": args.objects, "speed_px_per_ms": args.speed, "lux": args.lux, "distance_m": args.distance,
             "window": args.window}
    out = {k: list(v) for k, v in pairs.items() if v is not None}
    for key, v in (("still_fraction", args.still_fraction), ("camera_motion", args.camera_motion),
                   ("profile", args.profile), ("duration_s", args.duration)):
        if v is not None:
            out[key] = v
    return out


def run(args) -> int:
    from render2spike.commands._common import check_output
    from render2spike.scenegen import check_options, write_scenes
    from sensor.errors import InputError
    if args.count < 1:
        raise InputError(f"must be an integer >= 1; got {args.count}", field="--count")
    if args.seed < 0:
        raise InputError(f"must be an integer >= 0; got {args.seed}", field="--seed")
    flags = {"objects": "--objects", "speed_px_per_ms": "--speed", "lux": "--lux", "distance_m": "--distance",
             "window": "--window", "still_fraction": "--still-fraction", "camera_motion": "--camera-motion",
             "profile": "--profile", "duration_s": "--duration"}
    opts = options_from(args)
    try:
        check_options(opts)
    except InputError as exc:
        key = (exc.field or "").removeprefix("procedural.")
        raise InputError(str(exc).split(": ", 1)[1] if exc.field else str(exc), field=flags.get(key, key)) from None
    out = check_output(args.out, overwrite=args.overwrite, folder=True)
    paths = write_scenes(out, int(args.count), int(args.seed), opts)
    print(f"scenegen: {len(paths)} scene(s) of seed {args.seed} -> {out} ({paths[0].name} .. {paths[-1].name})")
    return 0
