"""Spike-train statistics of the realism report, computed the same way on real and simulated streams.

What is compared (``docs/sensor.md`` explains each):

* **pixel selection (motion)**: a pixel counts as stationary when its 3 x 3
  neighbourhood's spike counts in ``segments`` equal parts of the recording
  pass a chi-square dispersion test and its ISIs show no linear trend
  (:func:`stationary_pixels`); the ISI and count statistics use stationary
  pixels only. The same tests are applied to every simulated stream (a
  simulated pixel is used when the real pixel is stationary *and* its own
  spikes pass), so the selection acts alike on both.
* **mean ISI** of a pixel: ``T / n_spikes`` [intervals] (its reciprocal rate);
  pixels are pooled in mean-ISI bins.
* **ISI coefficient of variation** of each pixel (sample standard deviation of
  its ISIs over their mean), averaged over the pixels of a bin.
* **lag-1 ISI serial correlation** of each pixel, ``sum d_j d_{j+1} / sum
  d_j^2`` with ``d`` its ISIs minus their mean (pixels with at least 3 ISIs,
  not all equal), averaged over the pixels of a bin.
* **Fano factor** of each pixel's spike counts in non-overlapping windows of
  ``w`` intervals (variance over mean), averaged over the pixels of a bin
  whose mean ISI is at most ``w`` (below one spike per window the value is
  fixed by the spike count alone).
* **spike-rate histogram** over all pixels (fraction of pixels per rate bin).
* **dark and hot pixels**: pixels whose count is below / above the median of
  their 8 neighbours by more than ``z_outlier`` Poisson standard deviations
  (fractions), and the 0.1 % / 99.9 % quantiles of the per-pixel rate.

Each pixel weighs the same in a bin's average, so a few pixels with residual
motion (large, drifting ISIs) cannot dominate it. Standard errors: the standard
deviation over the bin's pixels divided by sqrt(pixels), so they include the
pixel-to-pixel variation; fractions use the binomial error (at least that of one
pixel) and quantiles the order-statistic interval.

Every estimate is biased on short recordings (e.g. the lag-1 correlation of
independent ISIs is about ``-1/n`` with ``n`` ISIs per pixel). The simulation
has the same duration, shape and per-pixel light as the recording, so the bias
is the same for real and simulated data: compare sources with each other, not
with long-recording theory.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sensor.errors import InputError

#: mean-ISI bin edges [intervals]
ISI_EDGES = (1.0, 2.0, 3.0, 4.5, 6.0, 8.0, 10.0, 15.0, 20.0, 30.0, 50.0, 80.0, 130.0, 200.0, 500.0, 1e3, 1e4, 1e6)
#: count windows [intervals] for the Fano factor (those with at least 4 windows in the recording are used; per
#: window, only pixels with mean ISI <= w, i.e. at least one spike per window on average)
FANO_WINDOWS = (10, 25, 50)
STATISTICS = {
    "isi_cv": "ISI coefficient of variation",
    "isi_lag1": "lag-1 ISI serial correlation",
    "rate_hist": "fraction of pixels per spike-rate bin",
    "outliers": "dark / hot pixels (local outliers) and rate quantiles",
}
DISTANCE_MEANING = (
    "D = mean over statistics (each weighted equally) of the mean over bins of |model - real| / "
    "sqrt(SE_real^2 + SE_model^2): the typical difference in units of the combined standard error. A model "
    "that reproduced the camera would give D ~ 0.8 (the mean of |N(0,1)|); D = 10 means that a typical bin is "
    "ten standard errors off. D grows with the recording's length for any fixed imperfection, so compare "
    "models on the same recording, not distances across recordings.")


# ------------------------------------------------------------------- per-pixel data
@dataclass
class _Trains:
    """Spike trains of P pixels: ISIs grouped by pixel (sorted by pixel, then time)."""

    T: int
    counts: np.ndarray  # (P,) spikes per pixel
    isi: np.ndarray  # all ISIs [intervals]
    isi_pix: np.ndarray  # pixel of each ISI
    pair: np.ndarray  # index j of ISIs whose successor j+1 is of the same pixel


def _trains(spikes) -> _Trains:
    T = spikes.shape[0]
    flat = np.ascontiguousarray(spikes.reshape(T, -1).T)  # (P, T)
    pix, t = np.nonzero(flat)
    same = pix[1:] == pix[:-1]
    isi = np.diff(t)[same].astype(np.float64)
    isi_pix = pix[1:][same]
    pair = np.flatnonzero(isi_pix[1:] == isi_pix[:-1])
    return _Trains(T, flat.sum(axis=1).astype(np.int64), isi, isi_pix, pair)


def stationary_pixels(spikes, segments: int = 4, alpha: float = 0.01, dilate: bool = True,
                      trains: _Trains | None = None):
    """Which pixels see constant light: two tests, both at level ``alpha``; returns (bool (H, W), details dict).

    1. **Counts** (rate changes): the spike counts of the pixel's 3 x 3
       neighbourhood (9 pixels pooled, for power; edges reflected) in
       ``segments`` equal parts of the recording pass a chi-square dispersion
       test, ``X2 = sum_k (c_k - cbar)^2 / cbar`` with ``segments - 1``
       degrees of freedom (Poisson reference: a renewal process more regular
       than Poisson passes more easily, so drift and motion are what fail it).
       A moving edge changes the neighbourhood's count even where one pixel
       has too few spikes to show it.
    2. **ISI trend** (pixels with >= 4 ISIs): the slope of the pixel's ISIs
       against their order is zero by a t-test (``n - 2`` degrees of freedom).
       Spike-camera pixels are so regular (ISIs jitter by about one interval)
       that a drift of the light shows up here first.

    Motion is spatially coherent (a moving edge is a line of pixels) while the
    tests have little power for a pixel with a few spikes, so with ``dilate``
    every neighbour (3 x 3) of a failing pixel is left out as well.

    The tests cannot see fast changes that average out within a segment, and
    have little power for pixels with 1-3 spikes.
    """
    from scipy.ndimage import uniform_filter
    from scipy.stats import chi2
    from scipy.stats import t as student_t
    s = np.asarray(spikes)
    T, H, W = s.shape
    L = T // segments
    if L < 1 or segments < 2:
        raise InputError(f"the recording has {T} intervals; the stationarity test needs at least {segments}")
    c = s[:L * segments].reshape(segments, L, H, W).sum(axis=1, dtype=np.int64).astype(np.float64)
    c = uniform_filter(c, size=(1, 3, 3), mode="reflect") * 9.0
    mean = c.mean(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        x2 = np.where(mean > 0, ((c - mean) ** 2).sum(axis=0) / np.where(mean > 0, mean, 1.0), 0.0)
    count_ok = chi2.sf(x2, segments - 1) >= alpha
    tr = trains if trains is not None else _trains(s)
    P = H * W
    n = np.bincount(tr.isi_pix, None, P)
    start = np.concatenate([[0], np.cumsum(n)[:-1]])
    j = np.arange(tr.isi.size, dtype=np.float64) - start[tr.isi_pix]
    nn = np.maximum(n, 1)
    dj = j - (np.bincount(tr.isi_pix, j, P) / nn)[tr.isi_pix]
    dx = tr.isi - (np.bincount(tr.isi_pix, tr.isi, P) / nn)[tr.isi_pix]
    sjj, sxx, sjx = (np.bincount(tr.isi_pix, a * b, P) for a, b in ((dj, dj), (dx, dx), (dj, dx)))
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where((sjj > 0) & (sxx > 0), sjx / np.sqrt(sjj * sxx), 0.0)
        tstat = r * np.sqrt(np.maximum(n - 2, 1) / np.maximum(1.0 - r * r, 1e-12))
    trend_ok = ((n < 4) | (2 * student_t.sf(np.abs(tstat), np.maximum(n - 2, 1)) >= alpha)).reshape(H, W)
    fail = ~(count_ok & trend_ok)
    if dilate:
        from scipy.ndimage import binary_dilation
        fail = binary_dilation(fail, structure=np.ones((3, 3), bool))
    keep = ~fail
    return keep, {"pixels": P, "fail_counts": int((~count_ok).sum()), "fail_isi_trend": int((~trend_ok).sum()),
                  "stationary": int(keep.sum()), "dilated": bool(dilate)}


def _pixel_mean(values, groups, n_groups):
    """Mean of a per-pixel value over the pixels of each group, its standard error (sd / sqrt(n)) and n."""
    n = np.bincount(groups, None, n_groups)
    s1 = np.bincount(groups, values, n_groups)
    s2 = np.bincount(groups, values * values, n_groups)
    with np.errstate(divide="ignore", invalid="ignore"):
        mean = s1 / n
        var = np.maximum(s2 - n * mean * mean, 0.0) / (n - 1)
        se = np.sqrt(var / n)
    return mean, se, n


def _rows(source, stat, lo, hi, labels, value, se, npix, nsamp):
    return [{"source": source, "statistic": stat, "bin_lo": float(a), "bin_hi": float(b), "bin": lab,
             "value": float(v), "se": float(e), "n_pixels": int(k), "n_samples": int(m)}
            for a, b, lab, v, e, k, m in zip(lo, hi, labels, value, se, npix, nsamp)]


def spike_statistics(spikes, keep=None, *, source: str = "real", isi_edges=ISI_EDGES, fano_windows=FANO_WINDOWS,
                     min_pixels: int = 10, z_outlier: float = 5.0) -> list[dict]:
    """Every statistic of one spike stream as rows (``source``, ``statistic``, bin, ``value``, ``se``, ...).

    Parameters
    ----------
    spikes : bool (T, H, W)
    keep : bool (H, W), optional
        Pixels used for the ISI and count statistics (default: all).
    isi_edges : sequence
        Mean-ISI bin edges [intervals].
    fano_windows : sequence of int
        Count windows [intervals]; windows with fewer than 4 repeats in T are skipped.
    min_pixels : int
        Bins with fewer pixels are dropped.
    z_outlier : float
        Local-outlier threshold for dark / hot pixels [Poisson standard deviations].
    """
    s = np.asarray(spikes, bool)
    if s.ndim != 3 or s.shape[0] < 8:
        raise InputError(f"spikes must be (T >= 8, H, W); got shape {s.shape}")
    T, H, W = s.shape
    tr = _trains(s)
    P = H * W
    keep = np.ones(P, bool) if keep is None else np.asarray(keep, bool).reshape(-1)
    edges = np.asarray(isi_edges, np.float64)
    nb = edges.size - 1
    with np.errstate(divide="ignore"):
        mean_isi = np.where(tr.counts > 0, T / np.maximum(tr.counts, 1), np.inf)
    pbin = np.digitize(mean_isi, edges) - 1  # -1 / nb: outside
    use = keep & (pbin >= 0) & (pbin < nb)
    lo, hi = edges[:-1], edges[1:]
    labels = [f"{a:g}-{b:g}" for a, b in zip(lo, hi)]
    rows: list[dict] = []

    def emit(stat, R, se, npix, nsamp):
        ok = (npix >= min_pixels) & np.isfinite(R) & np.isfinite(se)
        sel = np.flatnonzero(ok)
        rows.extend(_rows(source, stat, lo[sel], hi[sel], [labels[i] for i in sel], R[sel], se[sel], npix[sel],
                          nsamp[sel]))

    # ISI CV and lag-1 correlation of each pixel, averaged over the pixels of a bin
    n_isi = np.bincount(tr.isi_pix, None, P)
    m = np.bincount(tr.isi_pix, tr.isi, P) / np.maximum(n_isi, 1)
    d = (tr.isi - m[tr.isi_pix]) / np.where(m[tr.isi_pix] > 0, m[tr.isi_pix], 1.0)
    ss = np.bincount(tr.isi_pix, d * d, P)
    pix_cv = np.flatnonzero(use & (n_isi >= 2))
    cv_pix = np.sqrt(ss[pix_cv] / (n_isi[pix_cv] - 1))
    emit("isi_cv", *_pixel_mean(cv_pix, pbin[pix_cv], nb), np.bincount(pbin[pix_cv], n_isi[pix_cv], nb))
    lag = np.bincount(tr.isi_pix[tr.pair], d[tr.pair] * d[tr.pair + 1], P)
    pix_l = np.flatnonzero(use & (n_isi >= 3) & (ss > 0))  # undefined when all of a pixel's ISIs are equal
    emit("isi_lag1", *_pixel_mean(lag[pix_l] / ss[pix_l], pbin[pix_l], nb),
         np.bincount(pbin[pix_l], n_isi[pix_l] - 1, nb))

    # Fano factor of each pixel's counts in windows of w intervals, averaged over the pixels of a bin
    flat = s.reshape(T, P)
    for w in fano_windows:
        K = T // w
        if K < 4:
            continue
        pix_f = np.flatnonzero(use & (mean_isi <= w))  # >= 1 spike per window on average: else F is set by n alone
        c = flat[:K * w, pix_f].reshape(K, w, pix_f.size).sum(axis=1, dtype=np.int64).astype(np.float64)
        cbar = c.mean(axis=0)
        fano = ((c - cbar) ** 2).sum(axis=0) / ((K - 1) * cbar)
        mean, se, npix = _pixel_mean(fano, pbin[pix_f], nb)
        emit(f"fano_w{w}", mean, se, npix, npix * K)

    # spike-rate histogram over all pixels
    rate = tr.counts / T
    redges = np.concatenate([[0.0], np.geomspace(0.5 / T, 1.0 + 1e-9, 17)])
    rb = np.clip(np.digitize(rate, redges) - 1, 0, redges.size - 2)
    frac = np.bincount(rb, None, redges.size - 1) / P
    rows.extend(_rows(source, "rate_hist", redges[:-1], redges[1:],
                      ["0 spikes"] + [f"{a:.3g}-{b:.3g}" for a, b in zip(redges[1:-1], redges[2:])], frac,
                      np.sqrt(np.maximum(frac * (1 - frac), 1.0 / P) / P), np.bincount(rb, None, redges.size - 1), np.full(frac.size, P)))

    # dark / hot pixels: local outliers against the 8-neighbour median, and extreme rate quantiles
    from scipy.ndimage import median_filter
    counts = tr.counts.reshape(H, W).astype(np.float64)
    ring = np.ones((3, 3), bool)
    ring[1, 1] = False
    med = median_filter(counts, footprint=ring, mode="reflect")
    tol = z_outlier * np.sqrt(np.maximum(med, 1.0))
    hot = counts > med + tol
    dark = counts < med - tol
    sr = np.sort(rate)
    qs, qv, qe = (0.001, 0.999), [], []
    for q in qs:
        half = np.sqrt(P * q * (1 - q))
        i0, i1 = int(np.clip(np.floor(P * q - half), 0, P - 1)), int(np.clip(np.ceil(P * q + half), 0, P - 1))
        qv.append(float(np.quantile(rate, q)))
        qe.append(max((sr[i1] - sr[i0]) / 2, 0.5 / T))
    fr = np.array([dark.mean(), hot.mean()])
    rows.extend(_rows(source, "outliers", [np.nan] * 4, [np.nan] * 4,
                      ["dark_fraction", "hot_fraction", "rate_q0.001", "rate_q0.999"],
                      np.concatenate([fr, qv]),
                      np.concatenate([np.sqrt(np.maximum(fr * (1 - fr), 1.0 / P) / P), qe]),
                      [int(dark.sum()), int(hot.sum()), P, P], [P] * 4))
    return rows


def distance(rows, real="real", model="model", min_groups: int = 1) -> dict:
    """Per-statistic and overall distance D of ``model`` rows from ``real`` rows (see DISTANCE_MEANING)."""
    ref = {(r["statistic"], r["bin"]): r for r in rows if r["source"] == real}
    per: dict[str, list] = {}
    for r in rows:
        if r["source"] != model:
            continue
        q = ref.get((r["statistic"], r["bin"]))
        if q is None:
            continue
        den = np.hypot(q["se"], r["se"])
        if not np.isfinite(den) or den <= 0:
            continue
        group = "fano" if r["statistic"].startswith("fano_w") else r["statistic"]
        per.setdefault(group, []).append(abs(r["value"] - q["value"]) / den)
    by_stat = {g: float(np.mean(v)) for g, v in sorted(per.items())}
    overall = float(np.mean(list(by_stat.values()))) if len(by_stat) >= min_groups else float("nan")
    real_groups = {("fano" if r["statistic"].startswith("fano_w") else r["statistic"]) for r in rows
                   if r["source"] == real}
    return {"D": overall, "per_statistic": by_stat, "bins_compared": int(sum(len(v) for v in per.values())),
            "statistics_undefined": sorted(real_groups - set(by_stat))}


def checked_recording(spikes, profile):
    """``spikes`` as bool (T, H, W) and its shape, checked against the profile's (H, W)."""
    s = np.asarray(spikes, bool)
    if s.ndim != 3:
        raise InputError(f"spikes must be (T, H, W); got shape {s.shape}")
    T, H, W = s.shape
    if profile.shape != (H, W):
        raise InputError(f"profile '{profile.name}' is {profile.height} x {profile.width} but the recording is "
                         f"{H} x {W}; pass a profile (or window) of the recording's size", field="profile")
    return s, (T, H, W)
