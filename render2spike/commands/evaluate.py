"""``render2spike evaluate``: PSNR / SSIM of reconstruction methods on test data, as a Table-1-style table."""

from __future__ import annotations

from render2spike.commands._common import seed as _seed_type



EXAMPLES = """\
examples:
  render2spike evaluate --data davis:data/dvsynth:res=96x128 --methods tfp,tfp:4000,tfi,tfp-dt --out runs/eval
  render2spike evaluate --data rendered:out/demo/frames --methods tfp,rsir:runs/x/model.pt=RSIR --out runs/eval2
  render2spike evaluate --data real:rec.npz:clip=64 --methods tfp,tfp-dt,tfp-dt-denoised --out runs/eval-real
"""


def register(subparsers) -> None:
    from render2spike.commands._common import HelpFormatter, add_overwrite
    p = subparsers.add_parser(
        "evaluate", help="compare reconstruction methods (PSNR/SSIM table and example grid)",
        description="Reconstruct every test item with each method and score it against the ground truth. "
                    "Metrics: reference and reconstruction divided by the reference's 99.5th percentile, clipped "
                    "to [0, 1], PSNR and SSIM (scikit-image) with data range 1. Writes table.md, table.csv "
                    "(Methods | PSNR | SSIM, the layout of the ELSSim paper's Table 1), per_item.csv, grid.png "
                    "and summary.json.",
        epilog=EXAMPLES, formatter_class=HelpFormatter)
    p.add_argument("--data", required=True,
                   help="data spec KIND:PATH[,PATH...][:key=value...] (split=test by default; see docs/recon.md); "
                        "real:FILE[:clip=64][:reference=outside|whole][:profile=P]: the real-data score of a "
                        "recording without a reference image (stationary pixels against their long-window rate)")
    p.add_argument("--methods", default="tfp,tfi,tfp-dt,tfp-dt-denoised",
                   help="comma-separated: tfp, tfp:N, tfi, tfp-dt, tfp-dt-denoised (the strong classic baseline: "
                        "window and width tuned per light level and measured speed on training data), tfp-dt-denoised:SIGMA, rsir:CKPT[=LABEL]")
    p.add_argument("--noise-model", default="elssim", choices=["elssim", "ideal", "isi"],
                   help="spike model for simulated test data (a model= spec option wins)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (table.md, table.csv, grid.png, ...)")
    p.add_argument("--examples", type=int, default=4, help="rows of the example grid")
    p.add_argument("--device", default="auto", help="auto (CUDA if present, else CPU), cpu or cuda")
    p.add_argument("--seed", type=_seed_type, default=0, help="spike seed: seeds the simulated test spikes")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_overwrite(p, "write into an existing, non-empty output folder")
    p.set_defaults(func=run)


def run(args) -> int:
    from recon.evaluate import evaluate, load_models, parse_methods
    from recon.spec import build_dataset, parse_data_spec

    from render2spike.commands._common import check_numbers, check_output
    check_numbers(args, at_least=dict(examples=0))
    check_output(args.out, overwrite=args.overwrite, folder=True)
    methods = parse_methods(args.methods)
    spec = parse_data_spec(args.data)
    if spec.kind == "real":
        from recon.realscore import evaluate_real, load_real_spec, print_real_summary
        data = load_real_spec(spec)
        if any(m.kind == "rsir" for m in methods):
            load_models(methods, args.device)
        print_real_summary(evaluate_real(data, methods, args.out, data_label=args.data), args.out)
        return 0
    ds = build_dataset(spec, split="test", model=args.noise_model, seed=args.seed, include_spikes=True)
    if any(m.kind == "rsir" for m in methods):
        load_models(methods, args.device)
    summary = evaluate(ds, methods, args.out, n_examples=args.examples, progress=not args.quiet,
                       data_label=args.data)
    w = max(len(r["method"]) for r in summary["rows"])
    print(f"{'Methods':<{w}}  PSNR    SSIM")
    for r in summary["rows"]:
        print(f"{r['method']:<{w}}  {r['psnr_db']:6.2f}  {r['ssim']:.3f}")
    print(f"({summary['items']} items; table, grid and per-item scores in {args.out})")
    return 0
