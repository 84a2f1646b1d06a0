"""Real-data score: reconstruction methods scored on a real recording that has no reference image.

``render2spike evaluate --data real:FILE[:key=value...]``.

The reference
-------------
Pixels whose light does not change have a reference of their own: their
long-window rate. :func:`sensor.analysis.statistics.stationary_pixels` (the
realism report's tests: the 3 x 3-neighbourhood chi-square dispersion test of
spike counts over ``segments`` equal parts of the whole recording, and the
ISI-trend t-test, both at level ``alpha``, failures dilated by 3 x 3) picks
them; hot pixels of the profile are left out too. On those pixels the
reference is the dead-time-corrected rate (:func:`recon.classic.deadtime_correct`
with the profile) of the *reference intervals*, divided by the threshold
(ideal spikes per interval, the unit of every method).

Which intervals: each method reconstructs the centre instant from a short
clip of ``clip`` intervals (default 64) at the centre. With
``reference=outside`` (the default) the reference uses only the intervals
**outside** the clip: its noise is then independent of the clip's, so a
method cannot score by copying the clip's own noise (a reference over the
whole recording would contain the clip's spikes: clip / T of them, 32 % for
64 of 200 intervals, and reward the noisiest estimate of the clip).
``reference=whole`` uses every interval (lower noise, shared spikes; for
comparison only).

The score
---------
Reference and reconstruction are divided by the reference's white level (its
99.5th percentile over the scored pixels); the reconstruction is multiplied
by its best-fit gain (least squares over the scored pixels: the recording's
absolute light is unknown and the methods' biases differ), both are clipped
to [0, 1] and PSNR = -10 log10(MSE) with data range 1 (capped at 120 dB), as
:mod:`recon.metrics` does on whole images. Also reported: the gain, the
relative RMSE (RMSE over the mean reference, before clipping) and the number
of pixels.

The reference's noise floor
---------------------------
The reference is itself noisy (a few spikes per pixel in dim light). Its
noise is measured by splitting its intervals into two halves, A and B, and
comparing the two halves' references on the scored pixels:
``MSE_h = mean((R_A - R_B)^2)``. With ``reference=outside`` the halves are the
pieces before and after the clip: they lie ``clip`` intervals apart, so their
errors are independent whatever the noise law (Poisson counts, or the
quantisation of a regular integrate-and-fire pixel, whose count error comes
from the window's edges), and the reference, their length-weighted mean, has
``MSE_ref = MSE_h / 2 * (n_A^2 + n_B^2) / (n_A + n_B)^2`` (``MSE_h / 4``, 6.02 dB
below, for a centred clip). With ``reference=whole`` (or a clip at an end of
the recording) the halves are adjacent and share an edge, which makes their
difference larger than independent errors would (for regular pixels): the
floor is then a conservative estimate. The **floor** ``10 log10(1 /
MSE_ref)`` is the PSNR an exact reconstruction would score against this
reference: a method near the floor is
limited by the reference, not by itself. With independent noise (``outside``)
a method's own error is estimated as ``MSE - MSE_ref``; its PSNR is reported
when ``MSE > 2 MSE_ref`` (else the method is marked as limited by the
reference).
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sensor.errors import InputError, UnknownMethodError
from sensor.io.fileio import write_json_atomic, write_text_atomic

from .classic import deadtime_correct, tfp_windows, window_bounds
from .metrics import PSNR_CAP_DB, WHITE_PERCENTILE

#: clip length [intervals] each method reconstructs from
DEFAULT_CLIP = 64
REFERENCE_MODES = ("outside", "whole")
#: a method whose MSE is below this many times the reference's own MSE is limited by the reference
LIMITED_FACTOR = 2.0


@dataclass
class RealData:
    """A real recording to score: spikes bool (T, H, W), its profile and the score's options."""

    path: str
    spikes: np.ndarray
    profile: object
    profile_source: str
    clip: int = DEFAULT_CLIP
    center: int | None = None
    reference: str = "outside"
    segments: int = 4
    alpha: float = 0.01
    options: dict = field(default_factory=dict)


def load_real(path, *, clip: int = DEFAULT_CLIP, center: int | None = None, reference: str = "outside",
              profile: str | None = None, segments: int = 4, alpha: float = 0.01, layout: str | None = None,
              height: int | None = None, width: int | None = None, drop_columns: int = 0) -> RealData:
    """Read a recording (any layout ``sensor`` reads) and check the options (see the module docstring).

    ``profile``: a bundled name or file (centre-windowed to the recording), or
    ``None``: :func:`recon.profiles.recording_profile` (uniform vidar-like
    sensor with the recording's own hot pixels).
    """
    from .profiles import recording_profile, resolve_profile
    from .reconstruct import read_recording
    spikes, _ = read_recording(path, layout=layout, height=height, width=width, drop_columns=drop_columns)
    T, H, W = spikes.shape
    if reference not in REFERENCE_MODES:
        raise UnknownMethodError("real-data reference", reference, REFERENCE_MODES)
    clip = int(clip)
    if clip < 1:
        raise InputError(f"clip must be >= 1 interval, got {clip}", field="--data")
    spare = T - clip if reference == "outside" else T
    if spare < 4:
        raise InputError(f"the recording has {T} intervals: a clip of {clip} leaves {spare} for the reference "
                         f"(need >= 4; use a shorter clip)", path=path)
    if center is not None and not 0 <= int(center) < T:
        raise InputError(f"center {center} is outside the recording (0..{T - 1})", field="--data")
    if profile:
        prof, source = resolve_profile(profile, H, W), str(profile)
    else:
        prof, source = recording_profile(spikes, source=str(path), warn=False), "recording (uniform vidar-like)"
    return RealData(str(path), spikes, prof, source, clip, None if center is None else int(center), reference,
                    int(segments), float(alpha))


def clip_bounds(T: int, clip: int, center: int | None = None) -> tuple[int, int]:
    """Interval range ``[start, stop)`` of the clip: ``clip`` intervals centred on ``center`` (default T // 2)."""
    return window_bounds(T, clip, center)


def reference_intervals(T: int, start: int, stop: int, mode: str = "outside") -> np.ndarray:
    """Indices of the reference intervals: all of ``[0, T)`` outside ``[start, stop)``, or all (``whole``)."""
    idx = np.arange(T)
    if mode == "whole":
        return idx
    if mode != "outside":
        raise UnknownMethodError("real-data reference", mode, REFERENCE_MODES)
    return idx[(idx < start) | (idx >= stop)]


def reference_image(spikes, idx, profile) -> np.ndarray:
    """Dead-time-corrected rate over intervals ``idx`` / threshold: float64 (H, W), ideal spikes per interval."""
    s = np.asarray(spikes)
    rate = s[np.asarray(idx)].mean(axis=0, dtype=np.float64)
    return np.asarray(deadtime_correct(rate, profile), np.float64) / float(profile.threshold_e)


def _psnr(mse: float) -> float:
    return PSNR_CAP_DB if mse <= 10 ** (-PSNR_CAP_DB / 10) else min(float(-10 * np.log10(mse)), PSNR_CAP_DB)


def score_on_pixels(pred, ref, keep, white: float) -> dict:
    """PSNR at the best-fit gain on the pixels ``keep`` (see the module docstring).

    Returns {psnr_db, mse, gain, rel_rmse}; ``mse`` on the white-normalised, clipped values.
    """
    p = np.asarray(pred, np.float64)[keep] / white
    r = np.asarray(ref, np.float64)[keep] / white
    pp = float(np.dot(p, p))
    gain = float(np.dot(p, r) / pp) if pp > 0 else 1.0
    mse = float(np.mean((np.clip(gain * p, 0, 1) - np.clip(r, 0, 1)) ** 2))
    rel = float(np.sqrt(np.mean((gain * p - r) ** 2)) / max(float(r.mean()), 1e-12))
    return {"psnr_db": _psnr(mse), "mse": mse, "gain": gain, "rel_rmse": rel}


def reference_floor(spikes, idx, profile, keep, white: float) -> dict:
    """The reference's own noise from its two halves (see the module docstring).

    Returns {split_half_psnr_db, mse_half, halves, mse_ref, floor_psnr_db}.
    """
    idx = np.asarray(idx)
    pieces = np.split(idx, np.flatnonzero(np.diff(idx) != 1) + 1)
    if len(pieces) == 2:  # 'outside': the pieces before and after the clip, apart in time
        a, b = pieces
    else:  # one contiguous piece ('whole', or a clip at an end): its two halves, which share an edge
        a, b = idx[:idx.size // 2], idx[idx.size // 2:]
    if min(a.size, b.size) < 2:
        raise InputError(f"the reference's halves hold {a.size} and {b.size} intervals: no split-half noise "
                         "estimate (choose a shorter clip or another center)", field="--data")
    ra = np.clip(reference_image(spikes, a, profile)[keep] / white, 0, 1)
    rb = np.clip(reference_image(spikes, b, profile)[keep] / white, 0, 1)
    mse_h = float(np.mean((ra - rb) ** 2))
    mse_ref = mse_h / 2.0 * (a.size ** 2 + b.size ** 2) / float(a.size + b.size) ** 2
    return {"split_half_psnr_db": _psnr(mse_h), "mse_half": mse_h, "halves": [int(a.size), int(b.size)],
            "mse_ref": mse_ref, "floor_psnr_db": _psnr(mse_ref)}


def _clip_samples(clip_spikes, profile):
    """The clip as a classic-method sample (M = the whole clip) and a factory of network samples."""
    from .datasets import Sample
    from .profiles import sensor_maps
    L, H, W = clip_spikes.shape
    maps = sensor_maps(profile)
    classic = Sample(windows=np.zeros((1, H, W), np.float32), target=np.zeros((1, H, W), np.float32), maps=maps,
                     spikes=clip_spikes, center=L // 2, profile=profile, name="clip", meta={"window": L})

    def network(model) -> Sample:
        from .reconstruct import fit_windows
        N, Lw = fit_windows(L, None, None, model.config.input_layout)
        return Sample(windows=tfp_windows(clip_spikes, N, Lw), target=classic.target, maps=maps,
                      spikes=clip_spikes, center=L // 2, profile=profile, name="clip",
                      meta={"window": Lw, "windows": f"{N}x{Lw}"})
    return classic, network


def real_score(spikes, profile, methods, *, clip: int = DEFAULT_CLIP, center: int | None = None,
               reference: str = "outside", segments: int = 4, alpha: float = 0.01) -> dict:
    """Score ``methods`` on a real recording (see the module docstring).

    ``methods``: :class:`recon.evaluate.Method` objects (``rsir`` loaded), or
    ``(label, fn)`` with ``fn(sample) -> (H, W)`` ideal spikes per interval
    (the clip as a :class:`recon.datasets.Sample`). Returns a dict: ``rows``
    (one per method: method, psnr_db, gain, rel_rmse, mse, psnr_own_db,
    limited_by_reference, windows), ``floor`` (:func:`reference_floor`),
    ``pixels``, ``stationarity``, the interval ranges, and ``images``
    (reference, stationary mask, each reconstruction).
    """
    from sensor.analysis.statistics import stationary_pixels

    from .evaluate import Method, apply_method
    s = np.asarray(spikes).astype(bool, copy=False)
    T, H, W = s.shape
    start, stop = clip_bounds(T, clip, center)
    idx = reference_intervals(T, start, stop, reference)
    stationary, st = stationary_pixels(s, segments, alpha)
    keep = stationary & ~np.asarray(profile.hot_mask, bool)
    if keep.sum() < 2:
        raise InputError(f"only {int(keep.sum())} pixel(s) pass the stationarity tests: nothing to score",
                         field="--data")
    ref = reference_image(s, idx, profile)
    white = float(np.percentile(ref[keep], WHITE_PERCENTILE))
    if white <= 0:
        raise InputError("the reference is black on every stationary pixel: nothing to score", field="--data")
    floor = reference_floor(s, idx, profile, keep, white)
    classic, network = _clip_samples(s[start:stop], profile)
    rows, images = [], {}
    for m in methods:
        if isinstance(m, Method):
            if m.kind == "tfp" and m.arg is None:  # plain tfp: the whole clip
                m.label = f"TFP (M={stop - start})"
            label = m.label
            smp = network(m.model) if m.kind == "rsir" else classic
            img = apply_method(m, smp)
            windows = smp.meta.get("windows", f"1x{stop - start}")
        else:
            label, fn = m
            img, windows = fn(classic), ""
        sc = score_on_pixels(img, ref, keep, white)
        own = sc["mse"] - floor["mse_ref"]
        limited = sc["mse"] < LIMITED_FACTOR * floor["mse_ref"]
        rows.append({"method": label, **sc, "windows": windows, "limited_by_reference": bool(limited),
                     "psnr_own_db": None if (reference != "outside" or limited) else _psnr(own)})
        images[label] = np.asarray(img, np.float32)
    return {"rows": rows, "floor": floor, "pixels": int(keep.sum()), "pixels_total": H * W,
            "stationarity": st, "hot_pixels_left_out": int((stationary & ~keep).sum()),
            "intervals": T, "clip": [int(start), int(stop)], "reference": reference,
            "reference_intervals": int(idx.size), "overlap_clip_reference": int(np.sum((idx >= start) & (idx < stop))),
            "white": white, "segments": segments, "alpha": alpha,
            "images": {"reference": ref.astype(np.float32), "stationary": keep, **images}}


def evaluate_real(data: RealData, methods, out_dir, *, data_label: str = "") -> dict:
    """:func:`real_score` on ``data``; writes table.md, table.csv, summary.json, grid.png, reference.npy."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    res = real_score(data.spikes, data.profile, methods, clip=data.clip, center=data.center,
                     reference=data.reference, segments=data.segments, alpha=data.alpha)
    images = res.pop("images")
    summary = {"data": data_label or data.path, "kind": "real", "profile": data.profile_source, **res,
               "method": "real-data score (recon.realscore): reference = dead-time-corrected rate of the "
                         f"reference intervals ({data.reference}) on the stationary pixels; best-fit gain; "
                         f"pred and reference / reference {WHITE_PERCENTILE}th percentile, clipped to [0, 1]"}
    write_real_tables(out_dir, summary)
    write_json_atomic(out_dir / "summary.json", summary)
    from sensor.io.fileio import atomic_path
    with atomic_path(out_dir / "reference.npy") as tmp, open(tmp, "wb") as f:
        np.save(f, np.where(images["stationary"], images["reference"], np.nan).astype(np.float32))
    from .evaluate import write_grid
    ref = images["reference"]
    labels = [r["method"] for r in res["rows"]]
    masked = {k: np.where(images["stationary"], v, 0.0) for k, v in images.items() if k in labels}
    write_grid(out_dir / "grid.png", [("stationary pixels", np.where(images["stationary"], ref, 0.0), masked)],
               labels)
    return summary


def write_real_tables(out_dir: Path, summary: dict) -> None:
    """table.md and table.csv of a real-data score, atomically."""
    f = summary["floor"]
    lines = ["| Methods | PSNR | gain | rel. RMSE | own PSNR |", "|---|---|---|---|---|"]
    for r in summary["rows"]:
        own = "limited by ref." if r["limited_by_reference"] else (
            "-" if r["psnr_own_db"] is None else f"{r['psnr_own_db']:.2f}")
        lines.append(f"| {r['method']} | {r['psnr_db']:.2f} | {r['gain']:.3f} | {r['rel_rmse']:.3f} | {own} |")
    lines.append(f"| reference floor | {f['floor_psnr_db']:.2f} | | | |")
    a, b = summary["clip"]
    caption = (f"\nTable: real-data score on {summary['data']}: PSNR (dB) of each method's reconstruction from "
               f"intervals {a}-{b - 1} ({b - a} of {summary['intervals']}) against the dead-time-corrected rate of "
               f"{summary['reference_intervals']} reference intervals ({summary['reference']}; "
               f"{summary['overlap_clip_reference']} shared with the clip), on the {summary['pixels']} of "
               f"{summary['pixels_total']} pixels that pass the stationarity tests, at each method's best-fit gain. "
               f"Reference floor: the PSNR an exact reconstruction would score against this noisy reference "
               f"(the halves' references, {f['halves'][0]} and {f['halves'][1]} intervals, agree to "
               f"{f['split_half_psnr_db']:.2f} dB). Own PSNR: the "
               "method's error with the reference's noise taken off.\n")
    write_text_atomic(out_dir / "table.md", "\n".join(lines) + "\n" + caption)
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["Methods", "PSNR", "gain", "rel_RMSE", "own_PSNR", "limited_by_reference", "pixels", "floor_PSNR"])
    for r in summary["rows"]:
        w.writerow([r["method"], f"{r['psnr_db']:.4f}", f"{r['gain']:.5f}", f"{r['rel_rmse']:.5f}",
                    "" if r["psnr_own_db"] is None else f"{r['psnr_own_db']:.4f}", int(r["limited_by_reference"]),
                    summary["pixels"], f"{f['floor_psnr_db']:.4f}"])
    write_text_atomic(out_dir / "table.csv", buf.getvalue())


def load_real_spec(spec) -> RealData:
    """:func:`load_real` of a parsed ``real:FILE[:key=value...]`` data spec (:func:`recon.spec.parse_data_spec`)."""
    if len(spec.paths) != 1:
        raise InputError(f"real data take one spike file, got {len(spec.paths)} paths", field="--data")
    return load_real(spec.paths[0], **spec.options)


def print_real_summary(summary: dict, out_dir) -> None:
    """The command's console table of a real-data score."""
    rows = summary["rows"]
    w = max([len(r["method"]) for r in rows] + [len("reference floor")])
    print(f"{'Methods':<{w}}  PSNR    gain   own PSNR")
    for r in rows:
        own = "limited by ref." if r["limited_by_reference"] else (
            "-" if r["psnr_own_db"] is None else f"{r['psnr_own_db']:.2f}")
        print(f"{r['method']:<{w}}  {r['psnr_db']:6.2f}  {r['gain']:5.3f}  {own}")
    print(f"{'reference floor':<{w}}  {summary['floor']['floor_psnr_db']:6.2f}")
    a, b = summary["clip"]
    print(f"({summary['pixels']} of {summary['pixels_total']} pixels pass the stationarity tests; clip {a}-{b - 1}, "
          f"reference {summary['reference_intervals']} intervals ({summary['reference']}); tables in {out_dir})")
