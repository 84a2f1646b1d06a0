"""``render2spike calibrate``: dark + flat-field spike recordings -> sensor profile and report."""

from __future__ import annotations

from pathlib import Path

HELP = "estimate a sensor profile from dark and flat-field spike recordings, or import RSIR calibration maps"
DESCRIPTION = """\
Estimate the fixed-pattern maps of your spike camera (paper Eqs. 2-5):

  dark current  mu_DC per pixel [expected dark events per interval], from the pooled
                dark spike fraction p of all --dark recordings: mu_DC = -ln(1 - p);
  hot pixels    pixels whose dark spike fraction exceeds the median by --hot-threshold
                spikes per interval; their hot charge mu_HP, sigma_HP [threshold units
                per interval] is fitted to their dark inter-spike intervals;
  reset         "interval" (Algorithm 2) or "crossing" (continuous time), decided from the
                lag-1 correlation of the flats' inter-spike intervals (0 for the interval
                reset, negative for the crossing reset), with a confidence; --reset imposes it;
  PRNU          per-pixel gain: the flat rates are inverted through the exact rate-vs-light
                law of the reset and fitted as gain x level light, each (level, pixel)
                weighted by the information it carries; levels on the interval reset's
                staircase (nearly deterministic read-out) get no weight; the report says
                which levels were used and why, and warns when they are not enough;
  threshold     theta [e-] by photon transfer: the shot-noise part of the ISI variance of a
                pixel is (mean crossing time)^2 / k; dark events, refractory time and the
                read-out quantisation are modelled exactly and separated; with a standard error;
  sensitivity   with --flat-lux (the illuminance you measured for each flat, in order):
                photoelectrons per lux per interval, per pixel and on average.

Refractory time, pixel pitch, fill factor and QE are copied from --base (the base threshold is
only a starting point, unless --keep-threshold).
Recordings are SpikeCV .dat files (give --height/--width; raw 416-wide captures: --raw)
or render2spike .npz spike containers. Writes PROFILE plus PROFILE-stem_report.{png,json}.

--from-rsir MAPS.npz imports RSIR calibration maps instead (keys Nd, Nl, D_light, each (H, W); mean
read-out ISI 1 + D_light (335 + Nd) / (lux + Nd) intervals, lux at the focal plane). With the base
profile's sensitivity s [e-/(interval lux)]: threshold theta = median of s q, q = (1 - f + D_light)
(335 + Nd), PRNU gain theta / (s q), dark current s Nd [e-/interval] as a charge (dark = current),
and RSIR's "+1" as a one-interval blind time (--plus-one dead-time) or folded
into the threshold at 335 lux (--plus-one threshold). The maps fix theta / s, not s: pitch, fill
factor, QE, the reset and hot-pixel statistics come from --base. Writes PROFILE only.
"""
EXAMPLES = """\
examples:
  render2spike calibrate --dark dark/*.dat --flat flat/*.dat --raw --out mycam.npz
  render2spike calibrate --dark d*.npz --flat f*.npz --base vidar-default --out mycam.npz
  render2spike calibrate --dark d*.dat --flat f1.dat f2.dat f3.dat --flat-lux 0.5 1.5 3 --raw --out mycam.npz
  render2spike calibrate --from-rsir rsir_maps.npz --base vidar-default --out rsir-vidar.npz
"""


def register(sub) -> None:
    from sensor.calibration.estimate import DEFAULT_HOT_THRESHOLD
    from render2spike.commands._common import HelpFormatter, add_overwrite
    p = sub.add_parser("calibrate", help=HELP, description=DESCRIPTION, epilog=EXAMPLES, formatter_class=HelpFormatter)
    p.add_argument("--dark", nargs="+", metavar="FILE", help="dark recordings (the paper uses 20)")
    p.add_argument("--flat", nargs="+", metavar="FILE",
                   help="flat-field recordings, one per brightness level (>= 2 levels)")
    p.add_argument("--from-rsir", default=None, metavar="MAPS.npz",
                   help="import RSIR calibration maps (keys Nd, Nl, D_light) instead of --dark/--flat")
    p.add_argument("--kelvin", type=float, default=None, metavar="K",
                   help="--from-rsir: colour temperature of the flats' light, for lux -> photoelectrons "
                        "(default 5000)")
    p.add_argument("--plus-one", choices=["dead-time", "threshold"], default=None,
                   help="--from-rsir: where RSIR's '+1' goes: a one-interval blind time after each firing "
                        "(RSIR's law at every illuminance; default) or the threshold at 335 lux (the base's "
                        "blind time kept)")
    p.add_argument("--out", required=True, metavar="PROFILE", help="output profile (.npz)")
    p.add_argument("--base", default="vidar-default", metavar="NAME|PATH",
                   help="profile supplying threshold, refractory time, pitch, fill factor, QE (default: vidar-default)")
    p.add_argument("--name", default=None, help="name stored in the profile (default: calibrated-<base>; with --from-rsir: rsir-<maps stem>)")
    p.add_argument("--hot-threshold", type=float, default=None, metavar="SPIKES",
                   help=f"theta_HT in spikes per interval above the median dark rate (default {DEFAULT_HOT_THRESHOLD})")
    p.add_argument("--height", type=int, default=None, help=".dat frame height (default: the base profile's)")
    p.add_argument("--width", type=int, default=None, help=".dat frame width (default: the base profile's)")
    p.add_argument("--raw", action="store_true", help=".dat files are raw 416-wide captures: drop 16 columns")
    p.add_argument("--flat-lux", nargs="+", type=float, default=None, metavar="LUX",
                   help="illuminance [lux] of each flat field, in the order of --flat: adds the sensitivity "
                        "(photoelectrons per lux per interval)")
    p.add_argument("--reset", choices=["interval", "crossing"], default=None,
                   help="impose the pixel's reset instead of deciding it from the flats")
    p.add_argument("--keep-threshold", action="store_true",
                   help="store the base profile's threshold (the photon-transfer estimate is still reported)")
    p.add_argument("--dark-mode", choices=["events", "current"], default=None,
                   help="how the profile models dark current (default: as the --base profile does; vidar-default: "
                        "current): 'events' (Algorithm 2: dark events that fire the pixel, dark_rate) or 'current' (a "
                        "charge integrated with the light, dark_current_e [e-/interval], from each pixel's dark ISI "
                        "rate through the exact rate law)")
    add_overwrite(p, "replace an existing PROFILE (and its report)")
    p.set_defaults(func=run)


def _profile_out(out) -> Path:
    """The file --out names: a profile is an .npz; a name without a suffix gets ".npz" (as
    :meth:`sensor.SensorProfile.save` adds it), any other suffix is refused."""
    from sensor.errors import InputError
    out = Path(out)
    if out.suffix == "":
        return out.with_name(out.name + ".npz")
    if out.suffix != ".npz":
        raise InputError(f"a profile is written as an .npz file; got the suffix '{out.suffix}' (give a name "
                         "ending in .npz)", path=out, field="--out")
    return out


def run(args) -> int:
    from render2spike.commands._common import check_output
    from sensor import SensorProfile
    from sensor.errors import InputError
    if args.from_rsir is not None:
        return run_rsir(args)
    for flag in ("kelvin", "plus_one"):
        if getattr(args, flag) is not None:
            raise InputError("applies only with --from-rsir", field="--" + flag.replace("_", "-"))
    if not args.dark or not args.flat:
        raise InputError("calibrate needs --dark and --flat recordings, or --from-rsir MAPS.npz",
                         field="--flat" if args.dark else "--dark")
    from sensor.calibration.estimate import DEFAULT_HOT_THRESHOLD, calibrate, write_report
    from sensor.io.dat import check_frame_dims
    check_frame_dims(args.height, args.width)
    base_path = args.base if Path(args.base).exists() else None
    out = check_output(_profile_out(args.out), inputs=[*args.dark, *args.flat, base_path],
                       overwrite=args.overwrite)
    for suffix in (".png", ".json"):  # the report beside the profile is an output too
        check_output(out.with_name(out.stem + "_report" + suffix), overwrite=args.overwrite)
    base = SensorProfile.load(args.base)
    drop = 16 if args.raw else 0
    width = args.width or ((base.raw_width or base.width + 16) if args.raw else base.width)
    prof, report = calibrate([Path(f) for f in args.dark], [Path(f) for f in args.flat], base,
                             hot_threshold=DEFAULT_HOT_THRESHOLD if args.hot_threshold is None else args.hot_threshold,
                             name=args.name, height=args.height or base.height,
                             width=width, drop_columns=drop, reset=args.reset, flat_lux=args.flat_lux,
                             estimate_threshold=not args.keep_threshold, dark_mode=args.dark_mode,
                             progress=print,
                             progress_bar=True)
    out = prof.save(out)
    files = write_report(report, prof, out.with_name(out.stem + "_report"))
    n = report.numbers
    print(f"wrote {out}: mean dark rate {n['mean_dark_rate_hz']:.1f} Hz, {n['hot_pixels']} hot pixels, "
          f"PRNU std {n['prnu_std']:.4f} (median SE {n['prnu_se_median']:.4f}), reset {n['reset']}")
    if n.get("dark_current_e_median") is not None:
        print(f"dark current (charge): median {n['dark_current_e_median']:.3g} e-/interval, 1st-99th percentile "
              f"{n['dark_current_e_p01']:.3g}-{n['dark_current_e_p99']:.3g}, median SE "
              f"{n['dark_current_se_median']:.3g}")
    if n.get("threshold_e") is not None:
        print(f"threshold {n['threshold_e']:.0f} +- {n['threshold_se']:.0f} e-"
              + (" (not stored: --keep-threshold)" if args.keep_threshold else ""))
    if n.get("sensitivity_e_per_lux") is not None:
        print(f"sensitivity {n['sensitivity_e_per_lux']:.2f} +- {n['sensitivity_se']:.2f} photoelectrons per lux "
              "per interval")
    print("report: " + ", ".join(str(f) for f in files))
    import sys
    for w in n.get("warnings") or []:  # repeated after the summary, on stderr, so that they are not missed
        print(f"render2spike: warning: {w}", file=sys.stderr)
    return 0


def run_rsir(args) -> int:
    """``calibrate --from-rsir``: RSIR maps -> profile (nothing is written unless every check passes)."""
    from render2spike.commands._common import check_output
    from sensor import SensorProfile
    from sensor.calibration.rsir import DEFAULT_KELVIN, import_rsir, load_rsir_maps, rsir_profile
    from sensor.errors import InputError
    given = [f for f, v in (("--dark", args.dark), ("--flat", args.flat), ("--flat-lux", args.flat_lux),
                            ("--reset", args.reset), ("--keep-threshold", args.keep_threshold), ("--raw", args.raw),
                            ("--height", args.height), ("--width", args.width), ("--dark-mode", args.dark_mode),
                            ("--hot-threshold", args.hot_threshold is not None)) if v]
    if given:
        raise InputError(f"--from-rsir imports maps; {', '.join(given)} appl{'ies' if len(given) == 1 else 'y'} "
                         "only to calibration from recordings", field=given[0])
    base_path = args.base if Path(args.base).exists() else None
    out = check_output(_profile_out(args.out), inputs=[args.from_rsir, base_path], overwrite=args.overwrite)
    base = SensorProfile.load(args.base)
    maps = load_rsir_maps(args.from_rsir)
    imp = import_rsir(maps, base, plus_one=args.plus_one or "dead-time",
                      kelvin=DEFAULT_KELVIN if args.kelvin is None else args.kelvin, source=str(args.from_rsir))
    prof = rsir_profile(imp, base, name=args.name or f"rsir-{Path(args.from_rsir).stem}")
    out = prof.save(out)
    n = imp.summary()
    print(f"wrote {out}: {n['resolution']}, threshold {n['threshold_e']:.0f} e- (s = "
          f"{n['sensitivity_e_per_lux']:.2f} e-/(interval lux) from '{base.name}'), PRNU sd/mean "
          f"{n['prnu_sd_over_mean']:.4f}, dark current median {n['dark_current_e_median']:.1f} e-/interval, "
          f"'+1' as {n['plus_one']}")
    return 0
