"""Strong classic baseline: dead-time-corrected TFP over a window and smoothed by a Gaussian, both suiting the light.

``tfp_dt_denoised``: the TFP spike rate over a window of ``window``
intervals, its excess over each pixel's dark level smoothed by a Gaussian of
standard deviation ``sigma`` pixels (``scipy.ndimage.gaussian_filter``,
reflecting edges; hot pixels left out, :func:`smooth_rate`), then dead-time
corrected per pixel (:func:`recon.classic.deadtime_correct`, the inversion of
:func:`recon.classic.tfp_deadtime`). Smoothing *before* the nonlinear
inversion matters in dim scenes: inverting a pixel's few spikes first clips
the dark-subtracted estimate at zero and biases every smoothed value upwards.

The best ``window`` and ``sigma`` depend on how much light a pixel saw and on
how fast the scene moves: few spikes (dim scenes) want a long window and a
wide filter, many spikes a short window (less motion blur) and a narrow
filter. The shipped table ``recon/data/denoise_sigma.json`` gives the
PSNR-optimal pair (window, sigma) per light level and motion group, chosen
jointly on a grid (:data:`WINDOW_GRID` x :data:`SIGMA_GRID`) on *training*
items only (``python -m recon.baselines tune``). Its light key is the **mean
spike count per pixel over ``count_window`` intervals** (320; the mean TFP
rate over the intervals the item offers, at most 320, times 320), so the key
does not depend on the window chosen.

Speed is measured from the spikes: :func:`motion_score` is the mean over
pixels of the squared z-score of the TFP over the central
:data:`MOTION_SHORT_WINDOW` intervals against the TFP over the whole offered
window, both pooled over a few pixels (the difference in units of its shot
noise; about 1 or below on a still scene, larger the faster the scene moves,
and smaller in dim light, where the noise hides the motion). A table of format version 3 holds one sub-table per
*motion group* (training data of one range of speeds, ``--group`` of the
tuner), each with its light levels and their mean motion scores. At run time
the item's light key and motion score select the pair: the group of
:func:`motion_group` (the first, slowest group unless a faster group's
score stands out of it at this light level and is nearer the item's in log);
within it, the window of the level nearest in log count,
and the width interpolated linearly in log count among the levels with that
window (clamped to the table's ends). The window is capped at the intervals
the caller offers (``window`` argument). No test item is looked at when
choosing. The top-level ``counts``, ``windows`` and ``sigmas`` of a version 3
table are the pairs tuned on all groups pooled (used when ``motion`` is
off); a table without groups (version 2) has those alone, and a table
without ``windows`` (version 1) means window 320 at every level.

Method names in ``render2spike evaluate`` / studies: ``tfp-dt-denoised``
(table: tuned window and width) and ``tfp-dt-denoised:SIGMA`` (a fixed width
in pixels over the full window the data offer, 320 intervals by default).
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
#: TFP windows tried by the tuner [intervals]
WINDOW_GRID = (16, 32, 64, 128, 320)
#: window [intervals] of a table that names none (format version 1), and the span of the light key
DEFAULT_WINDOW = 320
COUNT_WINDOW = 320
#: short window of :func:`motion_score` [intervals]
MOTION_SHORT_WINDOW = 64
#: width of the Gaussian that pools :func:`motion_score`'s differences and variances [pixels]
MOTION_SIGMA_PX = 1.5
#: floor of motion scores before their logarithm is taken
MOTION_FLOOR = 1e-3
#: a motion group is told apart from the first (slowest) one where its score is at least this factor higher
MOTION_GROUP_RATIO = 1.5
#: largest Gaussian width [pixels] accepted for denoising: wider than any frame the project reads, where the
#: filter is a plain mean; larger widths only cost memory
MAX_SIGMA_PX = 1000.0


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


def light_count(spikes, window: int | None = None, center: int | None = None,
                count_window: int = COUNT_WINDOW) -> float:
    """The table's light key: mean TFP rate per pixel over the centred ``window`` times ``count_window``.

    The mean spike count per pixel a window of ``count_window`` intervals would
    see at the rate measured over the offered window; equal to
    :func:`mean_count` when ``window == count_window``.
    """
    return float(tfp(spikes, window, center).mean()) * float(count_window)


def motion_score(spikes, window: int | None = None, center: int | None = None,
                 short: int = MOTION_SHORT_WINDOW, sigma: float = MOTION_SIGMA_PX) -> float:
    """How fast the scene changes, from the spikes alone: a mean squared z-score (dimensionless).

    ``r_s`` the TFP over the central ``short`` intervals, ``r`` over the centred
    ``window`` (default all, ``M``); their difference ``d = r_s - r`` and its
    variance for a still scene, ``v = r (1 - r) (1/short - 1/M)`` (nested
    Bernoulli means), are both smoothed by a Gaussian of ``sigma`` pixels (the
    variance of the smoothed noise is ``G * v / (4 pi sigma^2)``; ``sigma`` 0: per
    pixel), and the score is the mean over pixels of ``d^2 / v`` (pixels with
    ``v`` 0 give 0). Pooling a few pixels lets edges that move by a pixel or two
    in ``short`` intervals stand out of the shot noise of a few spikes. Still
    scenes score about 1 or below (integrate-and-fire spikes are more regular
    than Bernoulli, the more so the brighter), faster motion higher; compare
    scores at the same light level. ``short >= M``: 0.
    """
    s = np.asarray(spikes)
    start, stop = window_bounds(s.shape[0], window, center)
    M = stop - start
    short = int(short)
    if short >= M:
        return 0.0
    c = (start + stop) // 2
    r = tfp(s, M, c).astype(np.float64)
    d = tfp(s, short, c).astype(np.float64) - r
    v = r * (1.0 - r) * (1.0 / short - 1.0 / M)
    if sigma > 0:
        from scipy.ndimage import gaussian_filter
        d = gaussian_filter(d, float(sigma), mode="reflect")
        v = gaussian_filter(v, float(sigma), mode="reflect") / (4.0 * np.pi * float(sigma) ** 2)
    z2 = np.where(v > 1e-12, d ** 2 / np.maximum(v, 1e-12), 0.0)
    return float(z2.mean())


def load_sigma_table(path=None) -> dict:
    """The table: dict with ``counts``, ``sigmas``, ``windows`` (ascending counts) and how it was made.

    A table without ``windows`` (version 1) gets :data:`DEFAULT_WINDOW` at every
    level; without ``count_window``, :data:`COUNT_WINDOW`.
    """
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
    if "windows" in d:
        w = d["windows"]
        if not isinstance(w, list) or len(w) != len(d["counts"]) \
                or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in w):
            raise InputError("'windows' must list one integer window >= 1 [intervals] per count", path=path)
    else:
        d["windows"] = [DEFAULT_WINDOW] * len(d["counts"])
    cw = d.setdefault("count_window", COUNT_WINDOW)
    if not isinstance(cw, int) or isinstance(cw, bool) or cw < 1:
        raise InputError(f"'count_window' must be an integer >= 1 [intervals], got {cw!r}", path=path)
    groups = d.get("groups")
    if groups is not None:
        if not isinstance(groups, list) or not groups:
            raise InputError("'groups' must list one or more motion groups", path=path)
        for i, g in enumerate(groups):
            keys = ("counts", "windows", "sigmas", "motions")
            if not isinstance(g, dict) or any(not isinstance(g.get(k), list) for k in keys) \
                    or len({len(g[k]) for k in keys}) != 1 or not g["counts"] \
                    or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in g["windows"]):
                raise InputError(f"group {i} needs equal-length lists 'counts', 'windows' (integers >= 1), "
                                 f"'sigmas' and 'motions'", path=path, field="groups")
    return d


def window_sigma_for_count(count: float, table: dict | None = None) -> tuple[int, float]:
    """PSNR-optimal (window [intervals], width [pixels]) for a light key (:func:`light_count`).

    The window of the level nearest in log count; the width interpolated in log
    count among the levels with that window, clamped to their ends. A table
    without ``windows`` uses :data:`DEFAULT_WINDOW` everywhere (the width is then
    interpolated over all levels).
    """
    t = table or load_sigma_table()
    c = np.log(np.maximum(np.asarray(t["counts"], np.float64), 1e-6))
    wins = np.asarray(t.get("windows") or [DEFAULT_WINDOW] * c.size, np.int64)
    x = np.log(max(float(count), 1e-6))
    win = int(wins[int(np.argmin(np.abs(c - x)))])
    same = wins == win
    return win, float(np.interp(x, c[same], np.asarray(t["sigmas"], np.float64)[same]))


def motion_group(count: float, motion: float, table: dict) -> dict:
    """The motion group of a version 3 table for an item of light key ``count`` and :func:`motion_score` ``motion``.

    Each group's motion score at ``count`` is interpolated in log count
    (clamped to its levels). The first group (the slowest training data) is
    the default; a later group is a candidate only where its score exceeds the
    first group's by :data:`MOTION_GROUP_RATIO` or more (where the groups score
    alike, the motion cannot be told from the noise, or from the scenes'
    content, at this light level). Of the first group and the candidates, the
    one nearest ``motion`` in log (both floored at :data:`MOTION_FLOOR`) is
    returned. A table without groups is its own single group.
    """
    groups = table.get("groups")
    if not groups:
        return table
    x = np.log(max(float(count), 1e-6))
    lm = np.log(max(float(motion), MOTION_FLOOR))

    def expected(g):
        c = np.log(np.maximum(np.asarray(g["counts"], np.float64), 1e-6))
        m = np.log(np.maximum(np.asarray(g["motions"], np.float64), MOTION_FLOOR))
        o = np.argsort(c)
        return float(np.interp(x, c[o], m[o]))

    ex = [expected(g) for g in groups]
    cands = [0] + [i for i in range(1, len(groups)) if ex[i] >= ex[0] + np.log(MOTION_GROUP_RATIO)]
    return groups[min(cands, key=lambda i: abs(ex[i] - lm))]


def window_sigma_for_item(spikes, window: int | None = None, center: int | None = None,
                          table: dict | None = None, *, motion: bool = True) -> tuple[int, float]:
    """(window [intervals], width [pixels]) of the tuned table for an item, by its light and, if ``motion``, speed.

    The light key is :func:`light_count` over the offered ``window`` (default
    all intervals) around ``center``; with ``motion`` and a table with groups,
    :func:`motion_score` picks the group (:func:`motion_group`). The window is
    not yet capped at the offered one.
    """
    t = table or load_sigma_table()
    count = light_count(spikes, window, center, int(t.get("count_window", COUNT_WINDOW)))
    sub = motion_group(count, motion_score(spikes, window, center), t) if motion and t.get("groups") else t
    return window_sigma_for_count(count, sub)


def sigma_for_count(count: float, table: dict | None = None) -> float:
    """PSNR-optimal width [pixels] for a light key: the width of :func:`window_sigma_for_count`."""
    return window_sigma_for_count(count, table)[1]


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
                    sigma: float | None = None, table: dict | None = None, motion: bool = True) -> np.ndarray:
    """The strong classic baseline: ``rate_e`` [e-/interval], float32 (H, W).

    TFP over a centred window, :func:`smooth_rate` with ``sigma`` pixels, then
    :func:`recon.classic.deadtime_correct` per pixel. ``window``: the intervals
    offered around ``center`` (default all). ``sigma`` fixed: TFP over all of
    them. ``sigma=None``: window and width from the tuned table
    (:func:`window_sigma_for_item`: the item's light key and, with ``motion``,
    its :func:`motion_score`, over the offered window), the window capped at
    the offered one.
    """
    if sigma is None:
        win, sigma = window_sigma_for_item(spikes, window, center, table, motion=motion)
        start, stop = window_bounds(np.asarray(spikes).shape[0], window, center)
        window = min(win, stop - start)
    return _denoised_from_rate(tfp(spikes, window, center), profile, sigma)


def _denoised_from_rate(r, profile, sigma: float) -> np.ndarray:
    return deadtime_correct(smooth_rate(r, profile, sigma), profile, correct_hot_pixels=sigma <= 0)


# ----------------------------------------------------------------------------------------------- tuning
def _span(smp) -> int:
    """The network-input length M of a sample [intervals] (the window the evaluation offers)."""
    return smp.windows.shape[0] * int(smp.meta.get("window", 32))


def tune_sigmas(samples, sigmas=SIGMA_GRID) -> tuple[float, dict]:
    """The width of ``sigmas`` with the best mean PSNR over ``samples`` (recon.datasets Samples with spikes).

    Returns (best sigma, {sigma: mean PSNR}). Uses the samples' own window (M).
    """
    (_, best), scores = tune_window_sigma(samples, None, sigmas)
    return best, {s: v for (_, s), v in scores.items()}


def _item_scores(samples, windows=WINDOW_GRID, sigmas=SIGMA_GRID) -> dict:
    """{(window, sigma): [PSNR per sample]} over the grid (windows up to the shortest span; None: each own M)."""
    spans = [_span(smp) for smp in samples]
    if windows is None:
        wins = [0]
    else:
        wins = sorted({int(w) for w in windows if int(w) <= min(spans)} or {min(spans)})
    scores = {(w, float(s)): [] for w in wins for s in sigmas}
    for smp, M in zip(samples, spans):
        th = np.float32(smp.profile.threshold_e)
        for w in wins:
            r = tfp(smp.spikes, w or M, smp.center)
            for s in sigmas:
                scores[(w, float(s))].append(psnr_ssim(_denoised_from_rate(r, smp.profile, float(s)) / th,
                                                       smp.target[0])[0])
    return scores


def _best(scores: dict) -> tuple[tuple[int, float], dict]:
    mean = {k: float(np.mean(v)) for k, v in scores.items()}
    return max(sorted(mean, reverse=True), key=mean.get), mean


def tune_window_sigma(samples, windows=WINDOW_GRID, sigmas=SIGMA_GRID) -> tuple[tuple[int, float], dict]:
    """The (window, width) pair with the best mean PSNR over ``samples`` (Samples with spikes and a target).

    ``windows`` [intervals]: those no longer than the shortest sample's span M
    are tried (at least M itself); ``None``: each sample's own M only (reported
    as window 0). Returns ((window, sigma), {(window, sigma): mean PSNR}); ties
    go to the longer window and then the wider filter (the lower-variance choice).
    """
    return _best(_item_scores(samples, windows, sigmas))


def _level_row(lux, samples, scores) -> dict:
    (win, best), mean = _best(scores)
    by = {}
    for (w, s), v in mean.items():
        by.setdefault(str(w), {})[str(s)] = v
    return {"lux": float(lux), "window": win, "sigma": best,
            "mean_count": float(np.mean([light_count(s.spikes, _span(s), s.center) for s in samples])),
            "mean_motion": float(np.mean([motion_score(s.spikes, _span(s), s.center) for s in samples])),
            "psnr_by_window_sigma": by, "items": len(samples)}


def _rows_table(rows) -> dict:
    rows = sorted(rows, key=lambda r: r["mean_count"])
    return {"counts": [r["mean_count"] for r in rows], "windows": [r["window"] for r in rows],
            "sigmas": [r["sigma"] for r in rows], "motions": [r["mean_motion"] for r in rows], "levels": rows}


def tune_table(spec_texts, lux_levels, *, items: int = 8, seed: int = 0, sigmas=SIGMA_GRID,
               windows=WINDOW_GRID, groups=None, progress: bool = True) -> dict:
    """Tune the window and width per light level (and motion group) on the *training* split of data specs.

    ``spec_texts``: data specs (davis / rendered kinds), pooled. ``groups``:
    optional list of lists of specs, one list per motion group (e.g. still,
    slow, fast training scenes); each group gets its own table, keyed by light
    and by its mean :func:`motion_score`, and the top level is tuned on all
    groups pooled (``spec_texts`` is then ignored). For each ``lux`` every spec
    is built with ``split=train`` and ``lux=LUX`` (then read like test items:
    centre crop, that light level), ``items`` items per spec are drawn (evenly
    spaced), the best (window, width) pair over them found
    (:func:`tune_window_sigma`) and keyed by their mean :func:`light_count`
    over their span M.
    """
    from tqdm import tqdm

    from .spec import build_dataset, parse_data_spec
    spec_texts = [spec_texts] if isinstance(spec_texts, str) else list(spec_texts)
    group_specs = [list(g) for g in groups] if groups else [spec_texts]
    all_specs = [t for g in group_specs for t in g]
    pooled_rows, group_rows = [], [[] for _ in group_specs]
    for lux in tqdm(list(lux_levels), desc="tune", unit="lux", disable=not progress):
        pooled_samples, pooled_scores = [], {}
        for gi, specs in enumerate(group_specs):
            samples = []
            for text in specs:
                spec = parse_data_spec(text)
                spec.options = dict(spec.options, lux=float(lux))
                ds = build_dataset(spec, split="train", seed=seed, include_spikes=True)
                ds.train = False  # fixed light level and centre crops; the items are still the training split's
                idx = np.unique(np.linspace(0, len(ds) - 1, min(items, len(ds))).round().astype(int))
                samples += [ds.sample(int(i)) for i in idx]
            scores = _item_scores(samples, windows, sigmas)
            if groups:
                group_rows[gi].append(_level_row(lux, samples, scores))
            pooled_samples += samples
            for k, v in scores.items():
                pooled_scores.setdefault(k, []).extend(v)
        if len({_span(s) for s in pooled_samples}) > 1:  # the pooled grid must be the one every group tried
            pooled_scores = _item_scores(pooled_samples, windows, sigmas)
        pooled_rows.append(_level_row(lux, pooled_samples, pooled_scores))
    top = _rows_table(pooled_rows)
    out = {"format": TABLE_FORMAT, "version": 3 if groups else 2, "counts": top["counts"],
           "windows": top["windows"], "sigmas": top["sigmas"], "count_window": COUNT_WINDOW,
           "motion_short_window": MOTION_SHORT_WINDOW, "motion_sigma_px": MOTION_SIGMA_PX, "data": all_specs, "split": "train", "seed": seed,
           "sigma_grid": [float(s) for s in sigmas], "window_grid": [int(w) for w in windows],
           "levels": top["levels"]}
    if groups:
        out["groups"] = [{"data": specs, **_rows_table(rows)} for specs, rows in zip(group_specs, group_rows)]
    out["note"] = (f"window [intervals] of the TFP and sigma [pixels] of the Gaussian before the dead-time "
                   f"correction, by mean spike count per pixel over {COUNT_WINDOW} intervals (at the rate seen over "
                   f"the item's span){' and by motion group (mean motion score, recon.baselines.motion_score)' if groups else ''}; "
                   f"chosen jointly by mean PSNR on training items only")
    out["provenance"] = provenance()
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m recon.baselines",
        description="Tune the TFP window and Gaussian width of the tfp-dt-denoised baseline on a training split "
                    "and write the table (count -> window, sigma).",
        epilog="example:\n  python -m recon.baselines tune --data davis:data/dvsynth:res=96x128 "
               "--lux 0.5,1,2,5,10,20,50,100,200,500 --out recon/data/denoise_sigma.json",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("tune", help="choose windows and widths on a training split")
    t.add_argument("--data", action="append", default=[],
                   help="data spec, davis or rendered (its training split is used); repeatable; pooled")
    t.add_argument("--group", action="append", default=[], metavar="SPEC[;SPEC...]",
                   help="one motion group: data specs separated by ';' (e.g. the still scenes, then the fast ones); "
                        "repeatable; each group gets its own table keyed by its motion score (format version 3), "
                        "instead of --data")
    t.add_argument("--lux", required=True, help="comma-separated light levels [lux]")
    t.add_argument("--items", type=int, default=8, help="training items per light level")
    t.add_argument("--windows", default=",".join(str(w) for w in WINDOW_GRID),
                   help="comma-separated TFP windows to try [intervals] (those up to the data's span M)")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--out", default=str(SIGMA_TABLE_FILE))
    a = ap.parse_args(argv)
    try:
        windows = [int(v) for v in a.windows.split(",") if v.strip()]
    except ValueError:
        ap.error(f"--windows: expected comma-separated integers, got '{a.windows}'")
    if not windows or min(windows) < 1:
        ap.error(f"--windows: expected integers >= 1, got '{a.windows}'")
    if bool(a.data) == bool(a.group):
        ap.error("give either --data (pooled) or --group (motion groups)")
    groups = [[t for t in g.split(";") if t.strip()] for g in a.group] or None
    table = tune_table(a.data, [float(v) for v in a.lux.split(",") if v.strip()], items=a.items, seed=a.seed,
                       windows=windows, groups=groups)
    write_json_atomic(Path(a.out), table)
    for gi, g in enumerate(table.get("groups") or [table]):
        for r in g["levels"]:
            print(f"group {gi}  lux {r['lux']:8.3g}  mean count {r['mean_count']:9.3f}  motion "
                  f"{r['mean_motion']:8.3f}  window {r['window']:4d}  sigma {r['sigma']:.2f}")
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
