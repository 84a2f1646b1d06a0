"""``render2spike render``: scene file -> irradiance frames (Phi [e-/(s m^2)], E [lux])."""

from __future__ import annotations

from render2spike.commands._common import seed as _seed_type

import argparse

HELP = "render a scene file to irradiance frames (OpenEXR, physical units)"
DESCRIPTION = """\
Render a moving 3-D scene with Mitsuba 3 (spectral) into a frames folder:
one float32 OpenEXR per keyframe with

  Phi  QE-weighted photon irradiance at the focal plane [e-/(s m^2)]
       (photoelectrons per second per m^2 of a 100 % fill-factor pixel)
  E    focal-plane illuminance [lux]

plus frames.json (the manifest). Scene light is scaled so that the illuminance
on the scene's reference surface is ILLUMINANCE_LUX (--lux); the lens turns
scene radiance L into focal-plane irradiance E_img = pi L T cos^4(theta)/(4 N^2).

SCENE is a YAML file or the name of a bundled scene (rotating_disk,
translating_object, room_pan, lambertian_plane); see docs/render.md.

Keyframes start at --keyframe-rate and are refined where the irradiance changes
by more than the scene's tolerance between neighbours. Samples per pixel are
chosen so render noise stays below photon shot noise (over a 64-interval
window) unless --spp is given. Rerunning the same command resumes (the result
is an uninterrupted render's, bit for bit with the default frozen launch on the CPU
and on a GPU; with --launch film only to float round-off: at high spp a pixel may
differ in its last bits run to run, rarely on the CPU, often on a GPU, whose film
sums are atomic); a changed scene or setting is
refused unless --overwrite. While it renders, the folder is locked: a second
render into it is refused, naming the first (pid, host, start time).
Frame files are named by time (frame_TTTTTTTT.exr, the tick on the finest
time grid), so they sort in time order.
"""
EXAMPLES = """\
examples:
  render2spike render scenes/rotating_disk.yaml --out out/disk
  render2spike render rotating_disk --out out/dim --lux 2 --duration 0.05
  render2spike render scenes/translating_object.yaml --out out/fast \\
      --set objects.cube.motion.parametric.0.translate.velocity_m_s=[1,0,0] --spp 64
  render2spike render room_pan --out out/room --keyframe-rate 2000 --render-seed 3 --overwrite
  render2spike render rotating_disk --out out/cpu --variant llvm_ad_spectral   # on the CPU, GPU or not
"""


def add_scene_options(p) -> None:
    """Options shared by `render` and `run`. ``--render-seed`` seeds the render; ``--seed`` (run only) the spikes."""
    p.add_argument("scene", metavar="SCENE", help="scene YAML file or bundled scene name")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--lux", type=float, metavar="X", help="illuminance at the scene's reference [lux] (overrides the scene)")
    p.add_argument("--duration", type=float, metavar="S", help="clip length [s] (overrides the scene)")
    p.add_argument("--spp", type=int, metavar="N", help="samples per pixel per keyframe (default: noise budget)")
    p.add_argument("--keyframe-rate", type=float, metavar="HZ",
                   help="base keyframe rate [Hz] before adaptive refinement; also sets the adaptive maximum to 4x "
                        "this rate (use --set render.adaptive.max_rate_hz=... to choose it)")
    p.add_argument("--profile", metavar="NAME|PATH", help="sensor profile (sets resolution and pixel pitch)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override any scene key, dotted path; list items by index or name (repeatable)")
    p.add_argument("--render-seed", type=_seed_type, default=None, metavar="N",
                   help="render base seed: per-frame Monte Carlo seeds derive from it (default: the scene's "
                        "render.seed, 0 if unset)")
    from render2spike.render.backend import FALLBACK_VARIANT, GPU_VARIANT, PREFERRED_VARIANT
    p.add_argument("--variant", default=None, choices=("auto", GPU_VARIANT, PREFERRED_VARIANT, FALLBACK_VARIANT),
                   help=f"Mitsuba variant that renders: auto takes the GPU ({GPU_VARIANT}) when one works, else "
                        f"the CPU ({PREFERRED_VARIANT}), else {FALLBACK_VARIANT} (slow, same physics). Default: "
                        "$RENDER2SPIKE_VARIANT if set, else auto; this option wins over the variable. The variant's "
                        "back end (cuda, llvm, scalar) is part of the folder's scene hash: frames of two back ends "
                        "are never mixed in one folder, and a rerun must ask for the same back end to resume")
    from render2spike.render.launch import DEFAULT_LAUNCH, LAUNCHES
    p.add_argument("--launch", default=DEFAULT_LAUNCH, choices=LAUNCHES,
                   help="how each frame's render is launched. frozen: the launch is recorded once with "
                        "drjit.freeze and replayed (own camera rays, wavelength sampling and per-pixel sums around "
                        "the same integrator; LLVM or CUDA variants only), faster per frame. film: the path "
                        "integrator renders into Mitsuba's spectral film, traced anew every frame. The same "
                        "channels in the same units, two Monte Carlo estimates of them (docs/render.md, \"The "
                        "frozen launch\"). auto (default): frozen on LLVM and CUDA variants, film on a scalar one "
                        "and for a scene with a moving mesh that emits light or changes shape; resuming a folder, "
                        "the launch its frames were rendered with. Part of the folder's scene "
                        "hash, like the variant")
    p.add_argument("--overwrite", action="store_true", help="replace frames of a different scene/settings in --out")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def variant_of(args) -> str | None:
    """The ``--variant`` asked for, as :func:`render2spike.render.backend.mitsuba` takes it: None when not
    given ($RENDER2SPIKE_VARIANT, else the automatic choice), ``"auto"`` for the automatic choice whatever
    the variable says, else the variant's name."""
    return getattr(args, "variant", None)


def scene_sets(args) -> list[str]:
    """The scene overrides the options give (``--set`` plus --spp and --keyframe-rate, checked here so that
    their errors name the option, not the scene key they set)."""
    import math

    from sensor.errors import InputError
    if args.spp is not None and args.spp < 1:
        raise InputError(f"must be an integer >= 1 (samples per pixel per keyframe); got {args.spp}", field="--spp")
    if args.keyframe_rate is not None and not (math.isfinite(args.keyframe_rate) and args.keyframe_rate > 0):
        raise InputError(f"must be a finite rate in Hz above 0; got {args.keyframe_rate}", field="--keyframe-rate")
    sets = list(args.set or [])
    if args.spp is not None:
        sets.append(f"render.spp={int(args.spp)}")
    if args.keyframe_rate is not None:
        sets.append(f"render.keyframe_rate_hz={float(args.keyframe_rate)}")
        sets.append(f"render.adaptive.max_rate_hz={max(float(args.keyframe_rate), 0.0) * 4}")
    if getattr(args, "render_seed", None) is not None:
        sets.append(f"render.seed={int(args.render_seed)}")
    return sets


def register(sub) -> None:
    from render2spike.commands._common import HelpFormatter
    p = sub.add_parser("render", help=HELP, description=DESCRIPTION, epilog=EXAMPLES, formatter_class=HelpFormatter)
    add_scene_options(p)
    p.add_argument("--seed", type=int, default=None, help=argparse.SUPPRESS)  # only to say what to use instead
    p.set_defaults(func=run)


def run(args) -> int:
    from render2spike.render.job import render_scene
    from render2spike.commands._common import check_output
    check_output(args.out, overwrite=True, folder=True)  # a file, or a file above it; resuming and --overwrite: below
    from render2spike.render.scene import load_scene
    from sensor.errors import InputError
    if args.seed is not None:
        raise InputError("`render` makes no spikes, and --seed is the spike seed in every command; use "
                         "--render-seed N to seed the render", field="--seed")
    sc = load_scene(args.scene, scene_sets(args), lux=args.lux, duration_s=args.duration, profile=args.profile)
    res = render_scene(sc, args.out, overwrite=args.overwrite, progress=not args.quiet, variant=variant_of(args),
                       launch=args.launch)
    m = res.manifest
    ts = m.get("temporal_sampling", {})
    from render2spike.render.job import spp_text
    print(f"render: {res.n_frames} frames ({res.n_rendered} rendered now) -> {res.out}; {m.get('variant')}, "
          f"{m.get('launch')} launch; {spp_text(m, res.spp)}; "
          f"{ts.get('n_refined', 0)} added by adaptive refinement; render/shot noise "
          f"{(m.get('render_noise_ratio') or {}).get('mean', float('nan')):.3f}; {res.seconds:.1f} s")
    return 0
