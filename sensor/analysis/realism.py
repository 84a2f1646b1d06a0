"""Realism report: a real spike recording against each spike model, statistic by statistic.

What is compared (every statistic is computed the same way on the real and the
simulated streams; ``docs/sensor.md`` explains each):

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

from dataclasses import dataclass, field

import numpy as np

from sensor.errors import InputError
from sensor.io.fileio import provenance
from sensor.models.spec import ModelSpec, parse_models
from sensor.profile import SensorProfile

#: mean-ISI bin edges [intervals]
ISI_EDGES = (1.0, 2.0, 3.0, 4.5, 6.0, 8.0, 10.0, 15.0, 20.0, 30.0, 50.0, 80.0, 130.0, 200.0, 500.0, 1e3, 1e4, 1e6)
#: count windows [intervals] for the Fano factor (those with at least 4 windows in the recording are used; per
#: window, only pixels with mean ISI <= w, i.e. at least one spike per window on average)
FANO_WINDOWS = (10, 25, 50)
DEFAULT_MODELS = ("elssim:interval", "elssim:crossing", "isi", "ideal")
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


# ------------------------------------------------------------------- models and light
def profile_for(profile: SensorProfile, spec: ModelSpec) -> SensorProfile:
    """The profile with the spec's reset applied."""
    return spec.profile(profile)


def _reset_of(profile) -> str:
    return profile.reset


def _uses_gain(model: str) -> bool:
    # ``ideal`` ignores every fixed-pattern map (Algorithm 1); elssim and isi need ceil(theta / g) photoelectrons
    return model != "ideal"


def rate_light_curve(profile: SensorProfile, model: str, *, seed: int = 0, n_levels: int = 48, n_pixels: int = 16,
                     n_intervals: int = 8000):
    """The model's spike rate as a function of light, measured by simulation on a uniform sensor.

    A ``n_levels x n_pixels`` sensor with ``profile``'s threshold, reset,
    interval and median refractory time and dark rate, no PRNU and no hot
    pixels; row j receives ``lambda_j = theta * x_j`` photoelectrons per
    interval (``x`` = 0, then 1e-3 .. 4 log-spaced) for ``n_intervals``
    intervals. Returns (lambda [e-/interval] (n_levels,), rate [spikes/interval]
    (n_levels,), made non-decreasing).
    """
    from sensor.simulator import simulate
    kw = {"reset": profile.reset}
    uni = SensorProfile.synthetic(n_levels, n_pixels, threshold_e=profile.threshold_e,
                                  dark_rate=float(np.median(profile.dark_rate)),
                                  refractory_s=float(np.median(profile.refractory_s)), interval_s=profile.interval_s,
                                  clock_hz=profile.clock_hz, name="rate-light-curve", **kw)
    lam = profile.threshold_e * np.concatenate([[0.0], np.geomspace(1e-3, 4.0, n_levels - 1)])
    rate_e = np.broadcast_to(np.repeat(lam[:, None], n_pixels, axis=1).astype(np.float32)[None],
                             (n_intervals, n_levels, n_pixels))
    s = simulate(rate_e, uni, model, seed=seed)
    # stationary rate without the start-up transient (the stream starts with an empty integrator): per row,
    # (spikes - 1) / (last - first spike time) pooled over its pixels; the plain fraction where that is undefined
    T = s.shape[0]
    any_ = s.any(axis=0)
    first = np.where(any_, s.argmax(axis=0), 0)
    last = np.where(any_, T - 1 - s[::-1].argmax(axis=0), 0)
    n = s.sum(axis=0, dtype=np.int64)
    span = np.where(n >= 2, last - first, 0).sum(axis=1)
    r = np.where(span > 0, np.maximum(n - 1, 0).sum(axis=1) / np.maximum(span, 1), s.mean(axis=(0, 2)))
    return lam, np.maximum.accumulate(r)


def estimate_light(rate, profile: SensorProfile, model: str, *, seed: int = 0, curve_intervals: int = 8000):
    """Per-pixel light [e-/interval] that makes ``model`` fire at ``rate`` [spikes/interval]; and how.

    * ``elssim`` with the interval reset: the exact renewal relation, inverted
      per pixel with its own k = ceil(theta / g), refractory fraction and dark
      probability (:func:`sensor.analysis.theory.invert_renewal_rate`).
    * any other model / reset: the model's rate-light curve measured by
      simulation on a uniform sensor (:func:`rate_light_curve`), inverted by
      linear interpolation; for models that use the PRNU gain the light is then
      divided by the pixel's gain (it needs ~theta/g photoelectrons). Per-pixel
      dark-rate differences are not removed (the curve has the median dark rate).

    Returns (lambda (H, W) float32, description str).
    """
    from sensor.models.effects import count_threshold, dark_event_probability
    from sensor.analysis.theory import invert_renewal_rate
    rate = np.asarray(rate, np.float64)
    if model == "elssim" and _reset_of(profile) == "interval":
        k = count_threshold(profile.threshold_e, profile.prnu_gain)
        lam = invert_renewal_rate(rate, k, profile.refractory_fraction, dark_event_probability(profile.dark_rate))
        return lam.astype(np.float32), ("exact renewal inversion per pixel (k = ceil(theta/g), refractory, dark "
                                        "probability; sensor.analysis.theory.invert_renewal_rate)")
    lam_c, r_c = rate_light_curve(profile, model, seed=seed, n_intervals=curve_intervals)
    # strictly increasing support for the interpolation (plateaus: take the first light level of each rate)
    r_u, first = np.unique(r_c, return_index=True)
    lam = np.interp(rate, r_u, lam_c[first])
    lam = np.where(rate <= r_u[0], 0.0, lam)
    if _uses_gain(model):
        lam = lam / np.asarray(profile.prnu_gain, np.float64)
    return lam.astype(np.float32), (f"rate-light curve of the model measured by simulation ({lam_c.size} levels x 16 "
                                    f"pixels x {curve_intervals} intervals, median dark and refractory, no PRNU), "
                                    "inverted by interpolation" + (", divided by the pixel's PRNU gain"
                                                                   if _uses_gain(model) else ""))


def _simulate_after_warmup(lam, T: int, warmup: int, profile, model: str, seed: int, chunk: int = 1024):
    """bool (T, H, W): ``model`` under constant light ``lam`` (H, W) after ``warmup`` discarded intervals.

    Streamed, so memory holds the kept T intervals plus one chunk.
    """
    from sensor.simulator import SpikeSimulator
    sim = SpikeSimulator(profile, model, seed, per_interval=True)
    lam = np.asarray(lam, np.float32)
    total = warmup + T
    kept: list[np.ndarray] = []
    n_kept = produced = fed = 0

    def take(block):
        nonlocal n_kept, produced
        kept.append(block)
        n_kept += block.shape[0]
        produced += block.shape[0]
        # the first block is not needed when the rest plus what is still to come covers the last T intervals
        while kept and n_kept - kept[0].shape[0] + (total - produced) >= T:
            n_kept -= kept.pop(0).shape[0]

    while fed < total:
        n = min(chunk, total - fed)
        for block in sim.iter_feed(np.broadcast_to(lam[None], (n,) + lam.shape)):
            take(block)
        fed += n
    take(sim.finish())
    s = np.concatenate(kept)
    return np.ascontiguousarray(s[s.shape[0] - T:])


# ------------------------------------------------------------------- the report
@dataclass
class RealismResult:
    rows: list
    distances: dict
    notes: dict = field(default_factory=dict)

    def summary(self) -> dict:
        return {"distance_meaning": DISTANCE_MEANING, "distances": self.distances, **self.notes}


def _distance(rows, real="real", model="model", min_groups: int = 1):
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


def realism(spikes, profile: SensorProfile, models=DEFAULT_MODELS, *, seed: int = 0, segments: int = 4,
            alpha: float = 0.01, curve_intervals: int = 8000, max_warmup: int = 4000, progress=None,
            **stat_kw) -> RealismResult:
    """Compare a real recording with each model: statistics rows, distances and notes on what was done.

    Parameters
    ----------
    spikes : bool (T, H, W)
        The real recording (image orientation).
    profile : SensorProfile
        Sensor of the same H x W (use ``profile.window`` for a crop).
    models : sequence of str or ModelSpec
        ``name[:reset]`` (see :func:`parse_models`). Each model is simulated for
        the same T, H, W with light estimated per pixel from the recording.
    seed : int
        Seed of every simulation (child seeds per model and for the curves).
    segments, alpha : stationarity test (:func:`stationary_pixels`).
    curve_intervals : intervals of the rate-light curve simulation (:func:`rate_light_curve`).
    max_warmup : most intervals simulated and dropped before the compared stream (the recording starts with
        every pixel at a random phase, a simulation with empty integrators).
    """
    say = progress or (lambda msg: None)
    s, (T, H, W) = _checked_recording(spikes, profile)
    specs = parse_models(",".join(m.label if isinstance(m, ModelSpec) else m for m in models))
    keep, st = stationary_pixels(s, segments, alpha)
    say(f"stationarity: {st['stationary']} of {H * W} pixels pass (neighbourhood counts in {segments} segments: "
        f"{st['fail_counts']} fail; ISI trend: {st['fail_isi_trend']} fail; alpha {alpha})")
    rows = spike_statistics(s, keep, source="real", **stat_kw)
    rate = s.sum(axis=0, dtype=np.int64) / T
    notes = {"recording": {"intervals": T, "height": H, "width": W, "mean_rate_per_interval": float(rate.mean())},
             "profile": profile.name, "seed": seed,
             "motion": (f"A pixel enters the ISI and Fano statistics only if (1) the spike counts of its 3x3 "
                        f"neighbourhood in {segments} equal segments pass a chi-square dispersion test and (2) its "
                        f"ISIs show no linear trend (t-test on the slope), both at alpha = {alpha}, and no pixel of "
                        f"its 3x3 neighbourhood fails either test (motion is spatially coherent): "
                        f"{st['stationary']} of {H * W} real pixels pass ({st['fail_counts']} fail the count test, "
                        f"{st['fail_isi_trend']} the trend test). Each simulated stream uses the real stationary "
                        "pixels that also pass the same tests on their own simulated spikes, so the selection acts "
                        "alike on both. The rate histogram and the dark/hot-pixel statistics use all pixels (the "
                        "simulation reproduces each pixel's mean rate). The tests miss changes that average out "
                        "within a segment and have little power for pixels with 1-3 spikes."),
             "stationarity": st,
             "mean_isi": "T / n_spikes of the pixel [intervals]", "models": {}}
    # the camera was running before the recording began, a simulation starts with empty integrators: simulate a
    # warm-up of several ISIs of the slowest firing pixel (at least T, at most max_warmup) and drop it
    n_min = int(rate[rate > 0].min() * T) if np.any(rate > 0) else 1
    warmup = int(min(max_warmup, max(T, 4 * int(np.ceil(T / max(n_min, 1))))))
    notes["warmup_intervals"] = warmup
    distances = {}
    for i, spec in enumerate(specs):
        prof = profile_for(profile, spec)
        child = np.random.SeedSequence(int(seed), spawn_key=(i,))  # one child seed per model
        sim_seed, curve_seed = (int(x) for x in child.generate_state(2))
        say(f"{spec.label}: estimating each pixel's light")
        lam, how = estimate_light(rate, prof, spec.name, seed=curve_seed, curve_intervals=curve_intervals)
        say(f"{spec.label}: simulating {warmup} + {T} intervals of {H} x {W}")
        sim = _simulate_after_warmup(lam, T, warmup, prof, spec.name, sim_seed)
        keep_m = keep & stationary_pixels(sim, segments, alpha)[0]
        rows.extend(spike_statistics(sim, keep_m, source=spec.label, **stat_kw))
        distances[spec.label] = _distance(rows, model=spec.label)
        notes["models"][spec.label] = {"model": spec.name, "reset": _reset_of(prof), "light_estimate": how,
                                       "simulation_seed": sim_seed, "stationary_pixels": int(keep_m.sum()),
                                       "mean_rate_per_interval": float(sim.mean())}
    return RealismResult(rows, distances, notes)


# ------------------------------------------------------------------- fitting the profile to a recording
#: statistics the fit matches (the rate histogram and the outliers are reproduced by the per-pixel light estimate
#: whatever the parameters, so they carry no information on them)
FIT_STATISTICS = ("isi_cv", "isi_lag1", "fano")
#: grids of the fit: multipliers of the profile's dark-rate map (0 = no dark events) and of its threshold theta
DARK_SCALES = (0.0, 0.05, 0.1, 0.2, 0.35, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0)
THRESHOLD_SCALES = (0.125, 0.18, 0.25, 0.35, 0.5, 0.7, 1.0, 1.4, 2.0, 2.8, 4.0, 5.6, 8.0)


@dataclass
class FitResult:
    """Result of :func:`fit_profile`: scales of the dark-rate map and the threshold, their spread and the profile."""

    profile: SensorProfile
    dark_scale: float
    dark_scale_sd: float
    threshold_scale: float
    threshold_scale_sd: float
    per_seed: list
    notes: dict = field(default_factory=dict)

    def summary(self) -> dict:
        hm = self.profile.hot_mask
        return {"dark_scale": self.dark_scale, "dark_scale_sd": self.dark_scale_sd,
                "threshold_scale": self.threshold_scale, "threshold_scale_sd": self.threshold_scale_sd,
                "threshold_e": float(self.profile.threshold_e),
                "dark_rate_mean_per_interval": float(self.profile.dark_rate[~hm].mean()) if (~hm).any() else 0.0,
                "per_seed": self.per_seed, **self.notes}


def scaled_profile(profile: SensorProfile, dark_scale: float, threshold_scale: float,
                   name: str | None = None) -> SensorProfile:
    """``profile`` with its dark-rate map multiplied by ``dark_scale`` and its threshold [e-] by ``threshold_scale``.

    The hot-pixel charge (``hot_mu``, ``hot_sigma``) is stored in threshold units, so it scales with theta.
    """
    return profile.replace(dark_rate=(profile.dark_rate * float(dark_scale)).astype(profile.dark_rate.dtype),
                           threshold_e=float(profile.threshold_e) * float(threshold_scale),
                           name=name or profile.name)


def _pixel_profile(profile: SensorProfile, idx) -> SensorProfile:
    """A 1 x N profile of the pixels ``idx`` (flat indices) of ``profile``."""
    from dataclasses import replace as _replace
    from sensor.profile import MAP_NAMES
    maps = {nm: getattr(profile, nm).reshape(-1)[idx][None, :].copy() for nm in MAP_NAMES}
    return _replace(profile, name=f"{profile.name}[{len(idx)} pixels]", height=1, width=len(idx), raw_width=None,
                    **maps)


def _parabola_min(xs, ds, i):
    """Abscissa of the vertex of the parabola through the grid point ``i`` and its two neighbours (clipped)."""
    if i == 0 or i == len(xs) - 1:
        return float(xs[i])
    x, y = np.asarray(xs[i - 1:i + 2], float), np.asarray(ds[i - 1:i + 2], float)
    a = np.polyfit(x, y, 2)
    if a[0] <= 0:
        return float(xs[i])
    return float(np.clip(-a[1] / (2 * a[0]), x[0], x[2]))


def fit_profile(spikes, profile: SensorProfile, *, seed: int = 0, n_seeds: int = 3, n_pixels: int = 1500,
                dark_scales=DARK_SCALES, threshold_scales=THRESHOLD_SCALES, segments: int = 4, alpha: float = 0.01,
                max_warmup: int = 4000, progress=None, **stat_kw) -> FitResult:
    """Fit the global dark rate and threshold of ``profile`` (elssim, its own reset) to a real recording.

    The recording fixes each pixel's light only through its rate, so what it can
    identify is the *shape* of the spike trains: the ISI coefficient of
    variation, lag-1 ISI correlation and Fano factors per mean-ISI bin
    (:data:`FIT_STATISTICS`). Dark events (a Poisson process at ``dark_rate``
    per interval) cut ISIs short and raise the CV; the threshold sets how many
    photoelectrons make a spike (CV ~ 1/sqrt(k) from photon noise).

    Method: ``n_pixels`` stationary, non-hot real pixels with >= 3 spikes are
    drawn at random (seeded; the draws are disjoint while the candidates last).
    At each grid point the pixels' light is the exact inversion of their rate
    for that profile (:func:`sensor.calibration.vidar.light_for_rate`), elssim simulates
    them (same T, a warm-up dropped, one fixed seed for every grid point: common
    random numbers) and the objective is the distance D (:func:`_distance`)
    restricted to :data:`FIT_STATISTICS`. The whole grid of both scales is
    searched (they trade off: more dark events and a higher threshold can give
    a similar CV); the grid minimum is refined along each axis by a parabola
    through its neighbours. This is repeated for ``n_seeds`` independent pixel
    draws and simulation seeds; the estimate is the mean over draws and its
    uncertainty their standard deviation (the spread of one draw's estimate,
    which includes the choice of pixels).

    Returns a :class:`FitResult` whose ``profile`` is ``profile`` scaled
    (:func:`scaled_profile`) by the mean scales.
    """
    import time

    from sensor.calibration.vidar import light_for_rate
    say = progress or (lambda msg: None)
    t0 = time.perf_counter()
    s, (T, H, W) = _checked_recording(spikes, profile)
    if n_seeds < 1:
        raise InputError(f"n_seeds must be >= 1; got {n_seeds}", field="n_seeds")
    keep, _ = stationary_pixels(s, segments, alpha)
    counts = s.sum(axis=0, dtype=np.int64)
    cand = np.flatnonzero((keep & ~profile.hot_mask & (counts >= 3)).reshape(-1))
    if cand.size < 20:
        raise InputError(f"only {cand.size} stationary pixels with >= 3 spikes; the fit needs at least 20")
    flat = s.reshape(T, -1)
    dsc, tsc = [float(x) for x in dark_scales], [float(x) for x in threshold_scales]
    per_seed = []
    # disjoint pixel draws while the candidates last (then they wrap round and share pixels)
    order = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(999,))).permutation(cand)
    n_pix = min(n_pixels, cand.size)
    disjoint = n_pix * n_seeds <= cand.size
    for r in range(n_seeds):
        sim_seed = int(np.random.SeedSequence(int(seed), spawn_key=(1000 + r,)).generate_state(1)[0])
        idx = np.sort(np.take(order, np.arange(r * n_pix, (r + 1) * n_pix), mode="wrap"))
        real = np.ascontiguousarray(flat[:, idx])[:, None, :]
        rate = counts.reshape(-1)[idx][None, :] / T
        base = _pixel_profile(profile, idx)
        n_min = max(int(counts.reshape(-1)[idx].min()), 1)
        warmup = int(min(max_warmup, max(T, 4 * int(np.ceil(T / n_min)))))
        real_rows = [q for q in spike_statistics(real, None, source="real", **stat_kw)
                     if q["statistic"].split("_w")[0] in FIT_STATISTICS]
        cache: dict = {}

        def objective(d, t):
            key = (d, t)
            if key not in cache:
                prof = scaled_profile(base, d, t)
                lam = light_for_rate(rate, prof).astype(np.float32)
                sim = _simulate_after_warmup(lam, T, warmup, prof, "elssim", sim_seed)
                rows = real_rows + [q for q in spike_statistics(sim, None, source="model", **stat_kw)
                                    if q["statistic"].split("_w")[0] in FIT_STATISTICS]
                cache[key] = _distance(rows)["D"]
            return cache[key]

        grid = np.array([[objective(d, t) for t in tsc] for d in dsc])  # (dark, threshold)
        i, j = np.unravel_index(int(np.nanargmin(grid)), grid.shape)
        d_grid, t_grid = dsc[i], tsc[j]
        d_best = _parabola_min(dsc, grid[:, j], i)
        t_best = float(np.exp(_parabola_min(np.log(tsc), grid[i, :], j)))
        d_fit = objective(d_grid, t_grid)
        d_start = objective(1.0, 1.0) if (1.0 in dsc and 1.0 in tsc) else float("nan")
        per_seed.append({"seed": r, "pixels": int(idx.size), "warmup_intervals": warmup, "dark_scale": d_best,
                         "threshold_scale": t_best, "D_fit_statistics_at_start": float(d_start),
                         "D_fit_statistics_at_grid_min": float(d_fit), "evaluations": len(cache),
                         "at_grid_edge": bool(i in (0, len(dsc) - 1) and dsc[i] > 0 or j in (0, len(tsc) - 1)),
                         "grid_D": grid.round(3).tolist()})
        say(f"fit seed {r}: dark x{d_best:.3g}, threshold x{t_best:.3g} (D on {'/'.join(FIT_STATISTICS)}: "
            f"{d_start:.2f} at x1, x1 -> {d_fit:.2f})")
    dv = np.array([p["dark_scale"] for p in per_seed])
    tv = np.log([p["threshold_scale"] for p in per_seed])
    d_mean, t_mean = float(dv.mean()), float(np.exp(tv.mean()))
    d_sd = float(dv.std(ddof=1)) if dv.size > 1 else float("nan")
    t_sd = float(t_mean * tv.std(ddof=1)) if tv.size > 1 else float("nan")
    fitted = scaled_profile(profile, d_mean, t_mean, name=f"{profile.name}-fitted")
    notes = {"method": ("grid search of the dark-rate scale (grid " + ", ".join(f"{x:g}" for x in dsc)
                        + ") and threshold scale (grid " + ", ".join(f"{x:g}" for x in tsc) + ", geometric) "
                        f"minimising D over {', '.join(FIT_STATISTICS)} of elssim (reset {_reset_of(profile)}) "
                        f"on {min(n_pixels, cand.size)} random stationary pixels, refined by a parabola; mean "
                        f"over {n_seeds} pixel draws / simulation seeds, uncertainty = their standard deviation "
                        "(threshold: geometric mean, sd of the log times the mean)"),
             "reset": _reset_of(profile), "candidate_pixels": int(cand.size), "disjoint_draws": bool(disjoint),
             "seconds": time.perf_counter() - t0,
             "base_threshold_e": float(profile.threshold_e)}
    return FitResult(fitted, d_mean, d_sd, t_mean, t_sd, per_seed, notes)


def add_fitted_models(result: RealismResult, spikes, profile: SensorProfile, fit: FitResult, models, *,
                      seed: int = 0, segments: int = 4, alpha: float = 0.01, progress=None, **kw) -> dict:
    """Simulate the ``elssim`` models of ``models`` again with ``fit``'s scales; add them to ``result``.

    ``profile`` is the one ``result`` was made with (same H x W as ``spikes``).
    Rows and distances are added as ``"LABEL (fitted)"``; ``result.notes["fit"]``
    gets the fit's summary and the distance D of each elssim model before and
    after, which is also returned ({"before_D": {...}, "after_D": {...}}).
    """
    specs = parse_models(",".join(m.label if isinstance(m, ModelSpec) else m for m in models))
    elssim = [s for s in specs if s.name == "elssim"]
    fitted = scaled_profile(profile, fit.dark_scale, fit.threshold_scale, name=f"{profile.name}-fitted")
    label = {s.label: f"{s.label} (fitted)" for s in elssim}
    if elssim:
        again = realism(spikes, fitted, elssim, seed=seed, segments=segments, alpha=alpha, progress=progress, **kw)
        result.rows.extend(dict(r, source=label[r["source"]]) for r in again.rows if r["source"] in label)
        for m, d in again.distances.items():
            result.distances[label[m]] = d
        result.notes.setdefault("models", {}).update({label[m]: v for m, v in again.notes["models"].items()})
    change = {"before_D": {s.label: result.distances[s.label]["D"] for s in elssim if s.label in result.distances},
              "after_D": {s.label: result.distances[label[s.label]]["D"] for s in elssim}}
    result.notes["fit"] = {**fit.summary(), **change}
    return change


# ------------------------------------------------------------------- output
CSV_COLUMNS = ("source", "statistic", "bin", "bin_lo", "bin_hi", "value", "se", "n_pixels", "n_samples")


def write_csv(path, rows):
    import csv
    import io

    from sensor.io.fileio import write_text_atomic
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=CSV_COLUMNS, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: (f"{r[k]:.6g}" if isinstance(r[k], float) else r[k]) for k in CSV_COLUMNS})
    return write_text_atomic(path, buf.getvalue())


def plot(result: RealismResult, path, title: str = ""):
    """One PNG: a panel per statistic, real (black) against each model."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sensor.io.fileio import atomic_path
    rows = result.rows
    sources = list(dict.fromkeys(r["source"] for r in rows))
    real_stats = {r["statistic"] for r in rows if r["source"] == "real"}
    fano = sorted((st for st in real_stats if st.startswith("fano_w")), key=lambda st: int(st[6:]))
    panels = [st for st in ("isi_cv", "isi_lag1") if st in real_stats] + fano + ["rate_hist", "outliers"]
    ncol = 3
    nrow = int(np.ceil(len(panels) / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.2 * ncol, 3.0 * nrow))
    axes = np.atleast_1d(axes).ravel()
    colors = {src: ("k" if src == "real" else f"C{i}") for i, src in enumerate(sources)}
    names = {"isi_cv": "ISI CV", "isi_lag1": "lag-1 ISI correlation", "rate_hist": "pixels per rate bin",
             "outliers": "dark / hot pixels"}
    for ax, st in zip(axes, panels):
        if st == "outliers":
            labels = ["dark_fraction", "hot_fraction", "rate_q0.001", "rate_q0.999"]
            width = 0.8 / max(len(sources), 1)
            for j, src in enumerate(sources):
                v = {r["bin"]: r for r in rows if r["source"] == src and r["statistic"] == st}
                x = np.arange(len(labels)) + (j - (len(sources) - 1) / 2) * width
                ax.bar(x, [v[b]["value"] if b in v else np.nan for b in labels], width,
                       yerr=[v[b]["se"] if b in v else 0 for b in labels], color=colors[src], label=src)
            ax.set_xticks(np.arange(len(labels)), ["dark frac", "hot frac", "rate q0.1%", "rate q99.9%"], fontsize=7)
            ax.set_yscale("log")
            ax.set_ylim(bottom=1e-5)
        else:
            for src in sources:
                rr = [r for r in rows if r["source"] == src and r["statistic"] == st]
                if not rr:
                    continue
                lo = np.array([r["bin_lo"] for r in rr])
                hi = np.array([r["bin_hi"] for r in rr])
                x = np.where(lo > 0, np.sqrt(np.maximum(lo, 1e-12) * hi), hi / 2)
                v = np.array([r["value"] for r in rr])
                e = np.array([r["se"] for r in rr])
                if st == "rate_hist":  # log axis: leave out empty bins, keep error bars above zero
                    v = np.where(v > 0, v, np.nan)
                    e = np.vstack([np.minimum(e, 0.9 * np.nan_to_num(v)), e])
                ax.errorbar(x, v, yerr=e, color=colors[src],
                            marker="o" if src == "real" else ".", ms=4, lw=1.6 if src == "real" else 1.0,
                            capsize=2, label=src)
            ax.set_xscale("log")
            ax.set_xlabel("spikes per interval" if st == "rate_hist" else "mean ISI [intervals]")
            if st == "rate_hist":
                ax.set_yscale("log")
        ax.set_title(names.get(st, st.replace("fano_w", "Fano factor, window ") + (" intervals"
                                                                                 if st.startswith("fano") else "")),
                     fontsize=9)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    for ax in axes[len(panels):]:
        ax.axis("off")
    leg = [f"{s} (D = {result.distances[s]['D']:.1f})" if s in result.distances else s for s in sources]
    handles = [plt.Line2D([], [], color=colors[s], marker="o", lw=1.5) for s in sources]
    fig.legend(handles, leg, loc="lower center", ncol=len(sources), fontsize=8, frameon=False)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0.05, 1, 0.97 if title else 1))
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=72)
    plt.close(fig)
    return path


def markdown(result: RealismResult, recording: str = "") -> str:
    lines = [f"# Realism report{': ' + recording if recording else ''}", ""]
    rec = result.notes.get("recording", {})
    if rec:
        lines += [f"{rec['intervals']} intervals of {rec['height']} x {rec['width']} pixels, mean "
                  f"{rec['mean_rate_per_interval']:.4f} spikes per pixel per interval; profile "
                  f"`{result.notes.get('profile')}`, seed {result.notes.get('seed')}.", ""]
    stats = sorted({g for d in result.distances.values() for g in d["per_statistic"]})
    lines += ["| model | D | " + " | ".join(stats) + " |", "|---|---|" + "---|" * len(stats)]
    for m, d in result.distances.items():
        lines.append(f"| {m} | {d['D']:.2f} | " + " | ".join(f"{d['per_statistic'][g]:.2f}" if g in
                                                            d["per_statistic"] else "undefined" for g in stats)
                     + " |")
    undefined = {m: d["statistics_undefined"] for m, d in result.distances.items() if d["statistics_undefined"]}
    if undefined:
        lines += ["", "A statistic is *undefined* for a model when no bin of it can be computed (e.g. the lag-1 "
                  "correlation when every ISI of a pixel is the same, as in the deterministic `ideal` model); "
                  "D is then the mean over the remaining statistics: "
                  + "; ".join(f"`{m}`: {', '.join(v)}" for m, v in undefined.items()) + "."]
    fit = result.notes.get("fit")
    if fit:
        lines += ["", f"**Fit.** dark-rate map x{fit['dark_scale']:.3g} +- {fit['dark_scale_sd']:.2g} (mean "
                  f"{fit['dark_rate_mean_per_interval']:.3g} dark events per interval), threshold "
                  f"x{fit['threshold_scale']:.3g} +- {fit['threshold_scale_sd']:.2g} (theta = {fit['threshold_e']:.4g} "
                  f"e-); +- = standard deviation over {len(fit['per_seed'])} pixel draws. " + fit["method"] + ". "
                  "Distance before -> after: " + "; ".join(f"`{m}` {fit['before_D'][m]:.2f} -> {fit['after_D'][m]:.2f}"
                                                          for m in fit.get("before_D", {})) + "."]
    lines += ["", "**What D means.** " + DISTANCE_MEANING, "", "**Motion.** " + result.notes.get("motion", ""), "",
              "**Light per pixel.**"]
    for m, info in result.notes.get("models", {}).items():
        reset = f" (reset {info['reset']})" if info["model"] == "elssim" else ""
        lines.append(f"- `{m}`{reset}: {info['light_estimate']}.")
    return "\n".join(lines) + "\n"


def write_report(result: RealismResult, out_dir, recording: str = "") -> dict:
    """Write ``realism.csv``, ``realism.png``, ``realism.json`` and ``realism.md`` into ``out_dir``."""
    from pathlib import Path

    from sensor.io.fileio import write_json_atomic, write_text_atomic
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"csv": out / "realism.csv", "png": out / "realism.png", "json": out / "realism.json",
             "md": out / "realism.md"}
    write_csv(paths["csv"], result.rows)
    plot(result, paths["png"], title=f"{Path(recording).name}: real vs models" if recording else "")
    write_json_atomic(paths["json"], {**result.summary(), "recording_file": str(recording),
                                      "provenance": provenance()})
    write_text_atomic(paths["md"], markdown(result, str(recording)))
    return paths


__all__ = ["realism", "spike_statistics", "stationary_pixels", "estimate_light", "rate_light_curve",
           "parse_models", "write_report", "fit_profile", "add_fitted_models", "scaled_profile", "FitResult", "RealismResult", "ModelSpec",
           "DEFAULT_MODELS", "DISTANCE_MEANING", "FIT_STATISTICS"]


def _checked_recording(spikes, profile):
    """``spikes`` as bool (T, H, W) and its shape, checked against the profile's (H, W)."""
    s = np.asarray(spikes, bool)
    if s.ndim != 3:
        raise InputError(f"spikes must be (T, H, W); got shape {s.shape}")
    T, H, W = s.shape
    if profile.shape != (H, W):
        raise InputError(f"profile '{profile.name}' is {profile.height} x {profile.width} but the recording is "
                         f"{H} x {W}; pass a profile (or window) of the recording's size", field="profile")
    return s, (T, H, W)
