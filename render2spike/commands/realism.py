"""``render2spike realism``: hold a real spike recording against each spike model."""

from __future__ import annotations

from render2spike.commands._common import seed as _seed_type

import argparse

HELP = "compare a real spike recording with each spike model (statistics per mean ISI, figure, distances)"
DESCRIPTION = """\
Hold a real recording against the spike models.

1. RECORDING is read in any layout `render2spike convert --help` lists
   (Spike-Zoo/UHSR .npz, SpikingSIM .npz, RSIR .npz, Vidar .dat, containers, .h5).
2. Motion: a pixel enters the ISI and count statistics only if its 3x3
   neighbourhood's counts in --segments parts pass a chi-square dispersion test and
   its ISIs show no linear trend (both at --alpha); neighbours of failing pixels are
   left out too. The same tests select the simulated pixels.
3. Each pixel's light [e-/interval] is estimated from its spike rate: the exact
   renewal relation for elssim with the interval reset, otherwise the model's own
   rate-light curve measured by simulation.
4. Each model simulates that light for the same duration and H x W (seeded).
5. Statistics per mean-ISI bin (mean ISI = T / spikes): ISI coefficient of
   variation, lag-1 ISI correlation, Fano factor of counts in windows of several
   lengths; the spike-rate histogram; dark and hot pixels (local outliers) and the
   extreme rate quantiles. Standard errors over pixels.
6. Distance D per model: the mean over statistics of the mean over bins of
   |model - real| / combined standard error (~0.8 = indistinguishable).

With --fit, the global dark rate (a scale of the profile's dark-rate map, 0
included; with --fit-dark-mode current, or a profile with dark = current, a scale
of its dark-current map) and threshold theta of elssim (the profile's own reset)
are fitted to the recording: a grid search minimising D over the ISI CV, lag-1 correlation and
Fano factors on --fit-pixels random stationary pixels, repeated for --fit-seeds
pixel draws (their spread is the uncertainty). The fitted profile is written to
DIR/fitted_profile.npz (usable as `render2spike simulate --profile`) and the
elssim models are simulated again with it ("elssim:RESET (fitted)" rows).

Writes DIR/realism.csv (every statistic per bin per source), DIR/realism.png (one
panel per statistic), DIR/realism.json and DIR/realism.md (distances, what they
mean, how motion and light were treated).

Models are NAME[:RESET] with NAME in {models} and RESET 'interval' (Algorithm 2:
reset at the end of the interval) or 'crossing' (reset when the charge crosses
the threshold; needs a sensor model that has it).
"""
EXAMPLES = """\
examples:
  render2spike realism ../shared/data/real/uhsr.npz --out out/realism
  render2spike realism rec.dat --layout vidar-raw --out out/r --models elssim:interval,isi
  render2spike realism rec.npz --out out/r --profile mycam.npz --seed 3 --max-intervals 2000
  render2spike realism ../shared/data/real/uhsr.npz --out out/realism --fit
  render2spike realism big.dat --out out/r --crop 100,100 --models elssim,isi
"""


def register(sub) -> None:
    from sensor.models.registry import MODELS
    from sensor.analysis.realism import DEFAULT_MODELS
    from sensor.io.spikefile import LAYOUTS
    p = sub.add_parser("realism", help=HELP, description=DESCRIPTION.format(models=", ".join(MODELS)),
                       epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("recording", metavar="RECORDING", help="real spike recording (.npz, .dat, .h5)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    p.add_argument("--profile", default="vidar-default", metavar="NAME|PATH",
                   help="sensor profile of the models; its centred window is used for a smaller recording "
                        "(default: vidar-default)")
    p.add_argument("--models", default=",".join(DEFAULT_MODELS), metavar="LIST",
                   help=f"comma-separated NAME[:RESET] (default: {','.join(DEFAULT_MODELS)})")
    p.add_argument("--layout", choices=sorted(LAYOUTS), help="layout of RECORDING (default: detected)")
    p.add_argument("--height", type=int, help="frame height of a headerless .dat RECORDING")
    p.add_argument("--width", type=int, help="frame width of a headerless .dat RECORDING")
    p.add_argument("--crop", metavar="H,W", help="use the centred H x W window of RECORDING (faster; default: all)")
    p.add_argument("--seed", type=_seed_type, default=0, help="seed of every simulation (default: 0)")
    p.add_argument("--max-intervals", type=int, default=2000, metavar="N",
                   help="use the first N intervals of RECORDING (memory and time grow with N x H x W; default 2000)")
    p.add_argument("--segments", type=int, default=4, help="segments of the stationarity count test (default 4)")
    p.add_argument("--alpha", type=float, default=0.01, help="level of the stationarity tests (default 0.01)")
    p.add_argument("--fit", action="store_true",
                   help="fit the profile's dark rate and threshold to RECORDING (writes DIR/fitted_profile.npz and "
                        "adds the fitted elssim models to the report)")
    p.add_argument("--fit-dark-mode", choices=["events", "current"], default=None,
                   help="fit the dark term as dark events (a scale of the dark-rate map) or as a dark current (a "
                        "scale of the dark-current map; a profile with dark events is first converted at the same "
                        "dark firing rate, d = mu_DC theta / g). Default: the profile's own dark mode")
    p.add_argument("--fit-seeds", type=int, default=3, metavar="N",
                   help="independent pixel draws of the fit; their spread is its uncertainty (default 3)")
    p.add_argument("--fit-pixels", type=int, default=1500, metavar="N",
                   help="random stationary pixels per fit draw (default 1500)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing report in DIR")
    p.add_argument("--quiet", action="store_true", help="no progress messages")
    p.set_defaults(func=run)


def run(args) -> int:
    import time

    import numpy as np

    from sensor.io.stream import profile_for_input as fit_profile
    from sensor.errors import InputError
    from sensor.profile import SensorProfile
    from sensor.analysis.realism import parse_models, realism, write_report
    from sensor.io.spikefile import read_spikes_with_meta

    t0 = time.perf_counter()
    say = (lambda m: None) if args.quiet else (lambda m: print(m, flush=True))
    from render2spike.commands._common import check_output
    out = check_output(args.out, inputs=[args.recording], overwrite=True,
                       folder=True)  # a file, or a file above it; an existing report: below
    if args.fit_dark_mode is not None and not args.fit:
        raise InputError("applies only with --fit (the fitted profile's dark mode)", field="--fit-dark-mode")
    if (out / "realism.json").exists() and not args.overwrite:
        raise InputError("already holds a realism report; pass --overwrite to replace it", path=out)
    from render2spike.commands._common import check_numbers
    check_numbers(args, at_least=dict(segments=2, fit_seeds=1, fit_pixels=1))
    if not 0 < args.alpha < 1:
        raise InputError(f"must be in (0, 1); got {args.alpha}", field="--alpha")
    specs = parse_models(args.models)
    if args.max_intervals < 8:
        raise InputError(f"must be >= 8; got {args.max_intervals}", field="--max-intervals")
    spikes, meta = read_spikes_with_meta(args.recording, layout=args.layout, height=args.height, width=args.width)
    T, H, W = spikes.shape
    say(f"read {args.recording} (layout '{meta['layout']}'): {T} intervals of {H} x {W}, mean "
        f"{float(spikes.mean()) if spikes.size else 0.0:.4f} spikes per pixel per interval")
    if args.crop:
        try:
            ch, cw = (int(v) for v in args.crop.split(","))
        except ValueError as exc:
            raise InputError(f"must be H,W (two integers); got '{args.crop}'", field="--crop") from exc
        if not (0 < ch <= H and 0 < cw <= W):
            raise InputError(f"{ch} x {cw} does not fit in the {H} x {W} recording", field="--crop")
        top, left = (H - ch) // 2, (W - cw) // 2
        spikes = spikes[:, top:top + ch, left:left + cw]
        H, W = ch, cw
        say(f"note: using the centred {H} x {W} window (rows {top}:{top + H}, cols {left}:{left + W}; --crop)")
    if T > args.max_intervals:
        say(f"note: using the first {args.max_intervals} of {T} intervals (--max-intervals)")
        spikes = spikes[:args.max_intervals]
    if spikes.shape[0] < 4 * args.segments:
        raise InputError(f"has {spikes.shape[0]} intervals; the report needs at least {4 * args.segments}",
                         path=args.recording)
    used = f"{'the centred window' if args.crop else 'the recording'}" + (
        f" (first {args.max_intervals} intervals, --max-intervals)" if T > args.max_intervals else "")
    if not spikes.any():
        raise InputError(f"{used} holds no spike at all ({spikes.shape[0]} intervals of {H} x {W}): a recording "
                         "with no spike cannot be told from any model; check the file (or its --layout)",
                         path=args.recording)
    if spikes.all():
        raise InputError(f"{used} fires at every pixel in every interval ({spikes.shape[0]} intervals of {H} x {W}): "
                         "a saturated recording cannot be told from any model; check the file (or its --layout)",
                         path=args.recording)
    if args.fit and (args.fit_seeds < 2 or args.fit_pixels < 20):
        raise InputError(f"--fit needs --fit-seeds >= 2 (for its uncertainty) and --fit-pixels >= 20; got "
                         f"{args.fit_seeds} and {args.fit_pixels}", field="--fit-seeds")
    base = SensorProfile.load(args.profile)
    profile = fit_profile(base, (H, W), say)
    result = realism(np.ascontiguousarray(spikes), profile, specs, seed=args.seed, segments=args.segments,
                     alpha=args.alpha, progress=say)
    if args.fit:
        add_fit(result, np.ascontiguousarray(spikes), base, profile, specs, out, args, say)
    result.notes["layout"] = meta["layout"]
    paths = write_report(result, out, recording=str(args.recording))
    say("distance D per model (mean |model - real| in standard errors; ~0.8 = indistinguishable):")
    for m, d in result.distances.items():
        say(f"  {m:<18} D = {d['D']:7.2f}   " + "  ".join(f"{g} {v:.1f}" for g, v in d["per_statistic"].items()))
    say(f"wrote {', '.join(str(p) for p in paths.values())} in {time.perf_counter() - t0:.1f} s")
    return 0


def add_fit(result, spikes, base, profile, specs, out, args, say) -> None:
    """Fit dark rate and threshold, write DIR/fitted_profile.npz, add the fitted elssim models to ``result``."""
    from sensor.analysis.fit import as_dark_mode
    from sensor.analysis.realism import add_fitted_models, fit_profile as fit, scaled_profile
    mode = getattr(args, "fit_dark_mode", None) or profile.dark
    say(f"fitting dark {'current' if mode == 'current' else 'rate'} and threshold of elssim (reset {profile.reset}) "
        "to the recording")
    f = fit(spikes, profile, seed=args.seed, n_seeds=args.fit_seeds, n_pixels=args.fit_pixels,
            segments=args.segments, alpha=args.alpha, dark_mode=mode, progress=say)
    base = as_dark_mode(base, mode)
    say(f"fit: dark {'current' if mode == 'current' else 'rate'} x{f.dark_scale:.3g} +- {f.dark_scale_sd:.2g}, threshold x{f.threshold_scale:.3g} +- "
        f"{f.threshold_scale_sd:.2g} (sd over {args.fit_seeds} draws) in {f.notes['seconds']:.1f} s")
    full = scaled_profile(base, f.dark_scale, f.threshold_scale, name=f"{base.name}-fitted")
    full = full.replace(provenance={**(base.provenance or {}), "fitted": {
        "by": "render2spike realism --fit", "recording": str(args.recording), "from_profile": base.name,
        "dark_mode": mode, "dark_scale": f.dark_scale, "dark_scale_sd": f.dark_scale_sd,
        "threshold_scale": f.threshold_scale,
        "threshold_scale_sd": f.threshold_scale_sd, "method": f.notes["method"]}})
    path = full.save(out / "fitted_profile.npz")
    add_fitted_models(result, spikes, profile, f, specs, seed=args.seed, segments=args.segments, alpha=args.alpha,
                      progress=say)
    result.notes["fit"]["fitted_profile_file"] = str(path)
