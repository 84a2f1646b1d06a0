"""Strong classic baseline: dead-time-corrected TFP smoothed by a Gaussian whose width suits the light level.

``tfp_dt_denoised``: the TFP spike rate over the window, its excess over each
pixel's dark level smoothed by a Gaussian of standard deviation ``sigma``
pixels (``scipy.ndimage.gaussian_filter``, reflecting edges; hot pixels left
out, :func:`smooth_rate`), then dead-time corrected per pixel
(:func:`recon.classic.deadtime_correct`, the inversion of
:func:`recon.classic.tfp_deadtime`). Smoothing *before* the nonlinear
inversion matters in dim scenes: inverting a pixel's few spikes first clips
the dark-subtracted estimate at zero and biases every smoothed value upwards. The best ``sigma`` depends on how many spikes a pixel saw:
few spikes (dim scenes) want a wide filter, many a narrow one. The shipped
table ``recon/data/denoise_sigma.json`` gives the PSNR-optimal ``sigma`` as a
function of the **mean spike count per pixel over the window** (``mean(TFP) *
window``), chosen on *training* items only (``python -m recon.baselines
tune``); at run time the count of the item itself selects ``sigma`` (linear
interpolation in log count, clamped to the table's ends). No test item is
looked at when choosing the widths.

Method names in ``render2spike evaluate`` / studies: ``tfp-dt-denoised``
(table) and ``tfp-dt-denoised:SIGMA`` (a fixed width in pixels).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from sensor.errors import InputError
from sensor.io.fileio import provenance, write_json_atomic

from .classic import deadtime_correct, tfp, window_bounds
from .metrics import psnr_ssim

DATA_DIR = Path(__file__).with_name("data")
SIGMA_TABLE_FILE = DATA_DIR / "denoise_sigma.json"
TABLE_FORMAT = "render2spike-denoise-sigma"
#: widths tried by the tuner [pixels] (0 = no filter)
SIGMA_GRID = (0.0, 0.5, 0.75, 1.0, 1.25, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0, 11.0, 16.0)


def gaussian_denoise(img, sigma: float) -> np.ndarray:
    """Gaussian filter of ``sigma`` pixels (reflecting edges); ``sigma <= 0`` returns a copy. float32 (H, W)."""
    from scipy.ndimage import gaussian_filter
    a = np.asarray(img, np.float32)
    if sigma <= 0:
        return a.copy()
    return gaussian_filter(a, float(sigma), mode="reflect").astype(np.float32)


def mean_count(spikes, window: int | None = None, center: int | None = None) -> float:
    """Mean spike count per pixel over the centred window (the light-level key of the sigma table)."""
    s = np.asarray(spikes)
    start, stop = window_bounds(s.shape[0], window, center)
    return float(tfp(s, window, center).mean()) * (stop - start)


def load_sigma_table(path=None) -> dict:
    """The sigma table: dict with ``counts`` and ``sigmas`` (ascending counts) and how it was made."""
    path = Path(path) if path else SIGMA_TABLE_FILE
    if not path.is_file():
        raise InputError("denoising width table does not exist (make one with python -m recon.baselines tune)",
                         path=path)
    try:
        d = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise InputError(f"invalid JSON ({exc})", path=path) from exc
    if d.get("format") != TABLE_FORMAT or len(d.get("counts", [])) != len(d.get("sigmas", [])) \
            or not d.get("counts"):
        raise InputError(f"not a {TABLE_FORMAT} table with equal-length 'counts' and 'sigmas'", path=path)
    return d


def sigma_for_count(count: float, table: dict | None = None) -> float:
    """PSNR-optimal width [pixels] for a mean count per pixel: interpolated in log count, clamped."""
    t = table or load_sigma_table()
    c = np.log(np.maximum(np.asarray(t["counts"], np.float64), 1e-6))
    return float(np.interp(np.log(max(float(count), 1e-6)), c, np.asarray(t["sigmas"], np.float64)))


def smooth_rate(rate, profile, sigma: float) -> np.ndarray:
    """Smooth a TFP rate map for the dead-time correction: the dark excess, without hot pixels.

    ``x = rate - p_dark`` (each pixel's own expected dark spikes per
    interval) is smoothed by normalised convolution that leaves hot pixels out
    (``G*(x w) / G*w``, ``w = 0`` on hot pixels), and ``p_dark`` is added back.
    In dim light the dark spikes outnumber the signal and the dark rate varies
    from pixel to pixel: smoothing the excess keeps each pixel's dark level its
    own, and smoothing before the (nonlinear, zero-clipped) inversion avoids the
    upward bias of inverting a few spikes per pixel. ``sigma <= 0``: unchanged.
    """
    r = np.asarray(rate, np.float64)
    if sigma <= 0:
        return r
    p = profile.dark_spike_rate
    w = (~profile.hot_mask).astype(np.float64)
    num = gaussian_denoise(((r - p) * w).astype(np.float32), sigma).astype(np.float64)
    den = gaussian_denoise(w.astype(np.float32), sigma).astype(np.float64)
    return np.clip(num / np.maximum(den, 1e-6) + p, 0.0, 1.0)


def tfp_dt_denoised(spikes, profile, window: int | None = None, center: int | None = None,
                    sigma: float | None = None, table: dict | None = None) -> np.ndarray:
    """The strong classic baseline: ``rate_e`` [e-/interval], float32 (H, W).

    TFP over the window, :func:`smooth_rate` with ``sigma`` pixels, then
    :func:`recon.classic.deadtime_correct` per pixel. ``sigma`` fixed, or
    ``None``: chosen from the item's mean count with the tuned table
    (:func:`sigma_for_count`).
    """
    r = tfp(spikes, window, center)
    if sigma is None:
        sigma = sigma_for_count(mean_count(spikes, window, center), table)
    return _denoised_from_rate(r, profile, sigma)


def _denoised_from_rate(r, profile, sigma: float) -> np.ndarray:
    return deadtime_correct(smooth_rate(r, profile, sigma), profile, correct_hot_pixels=sigma <= 0)


# ----------------------------------------------------------------------------------------------- tuning
def tune_sigmas(samples, sigmas=SIGMA_GRID) -> tuple[float, dict]:
    """The width of ``sigmas`` with the best mean PSNR over ``samples`` (recon.datasets Samples with spikes).

    Returns (best sigma, {sigma: mean PSNR}). Uses the samples' own window (M).
    """
    scores = {float(s): [] for s in sigmas}
    for smp in samples:
        M = smp.windows.shape[0] * int(smp.meta.get("window", 32))
        r = tfp(smp.spikes, M, smp.center)
        th = np.float32(smp.profile.threshold_e)
        for s in scores:
            scores[s].append(psnr_ssim(_denoised_from_rate(r, smp.profile, s) / th, smp.target[0])[0])
    mean = {s: float(np.mean(v)) for s, v in scores.items()}
    return max(mean, key=mean.get), mean


def tune_table(spec_texts, lux_levels, *, items: int = 8, seed: int = 0, sigmas=SIGMA_GRID,
               progress: bool = True) -> dict:
    """Tune the width per light level on the *training* split of data specs (davis / rendered kinds).

    For each ``lux`` every spec is built with ``split=train`` and ``lux=LUX`` (then read like test items:
    centre crop, that light level), ``items`` items per spec are drawn (evenly spaced), the best width over
    all of them found and keyed by their mean count.
    """
    from tqdm import tqdm

    from .spec import build_dataset, parse_data_spec
    spec_texts = [spec_texts] if isinstance(spec_texts, str) else list(spec_texts)
    rows = []
    for lux in tqdm(list(lux_levels), desc="tune", unit="lux", disable=not progress):
        samples = []
        for text in spec_texts:
            spec = parse_data_spec(text)
            spec.options = dict(spec.options, lux=float(lux))
            ds = build_dataset(spec, split="train", seed=seed, include_spikes=True)
            ds.train = False  # fixed light level and centre crops; the items are still the training split's
            idx = np.unique(np.linspace(0, len(ds) - 1, min(items, len(ds))).round().astype(int))
            samples += [ds.sample(int(i)) for i in idx]
        best, scores = tune_sigmas(samples, sigmas)
        count = float(np.mean([mean_count(s.spikes, s.windows.shape[0] * int(s.meta.get("window", 32)), s.center)
                               for s in samples]))
        rows.append({"lux": float(lux), "mean_count": count, "sigma": best, "psnr_by_sigma": scores,
                     "items": len(samples)})
    rows.sort(key=lambda r: r["mean_count"])
    return {"format": TABLE_FORMAT, "version": 1, "counts": [r["mean_count"] for r in rows],
            "sigmas": [r["sigma"] for r in rows], "data": spec_texts, "split": "train", "seed": seed,
            "sigma_grid": [float(s) for s in sigmas], "levels": rows,
            "note": "sigma [pixels] of the Gaussian after dead-time-corrected TFP, by mean spike count per pixel "
                    "over the window; chosen by mean PSNR on training items only",
            "provenance": provenance()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m recon.baselines",
        description="Tune the Gaussian width of the tfp-dt-denoised baseline on a training split and write the "
                    "table (count -> sigma).",
        epilog="example:\n  python -m recon.baselines tune --data davis:data/dvsynth:res=96x128 "
               "--lux 0.5,1,2,5,10,20,50,100,200,500 --out recon/data/denoise_sigma.json",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("tune", help="choose widths on a training split")
    t.add_argument("--data", required=True, action="append",
                   help="data spec, davis or rendered (its training split is used); repeatable")
    t.add_argument("--lux", required=True, help="comma-separated light levels [lux]")
    t.add_argument("--items", type=int, default=8, help="training items per light level")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--out", default=str(SIGMA_TABLE_FILE))
    a = ap.parse_args(argv)
    table = tune_table(a.data, [float(v) for v in a.lux.split(",") if v.strip()], items=a.items, seed=a.seed)
    write_json_atomic(Path(a.out), table)
    for r in table["levels"]:
        print(f"lux {r['lux']:8.3g}  mean count {r['mean_count']:9.3f}  sigma {r['sigma']:.2f}")
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
