"""Calibrate a sensor profile from dark and flat-field spike recordings (paper Eqs. 2-5).

Estimators (see ``docs/sensor.md`` for the derivations and departures):

* **Dark current** (Eq. 2): pooled over all dark recordings, the per-pixel
  spike fraction ``p`` estimates the per-interval dark-event probability, so
  ``mu_DC = -ln(1 - p)`` (the exact inverse of ``p = 1 - exp(-mu_DC)``; the
  paper uses ``p`` itself, equal to first order).
* **Dark current as charge** (``dark_mode="current"``, ``--dark-mode current``): each pixel's
  dark read-out rate is its mean dark ISI inverted (``1 / mean``; the mean ISI is the span from
  the first to the last spike of each recording over the ISIs in between, pooled), and the
  dark current ``d`` [e-/interval] is the light whose read-out rate under the calibrated reset,
  threshold, gain and refractory time is that rate (the exact laws of
  :mod:`sensor.calibration.flatfield` with no dark events: ``d = k x``, ``x`` the inverted rate
  in thresholds per interval, ``k = theta / g``). Its standard error combines the mean ISI's
  (``Var(sum of N ISIs) = N Var(U)`` with ``Var(U)`` of the model at the estimate, plus the
  read-out's bounded 1/6 per recording under the crossing reset) with the gain's and the
  threshold's. Flats are inverted at ``lambda + d``: the PRNU fit uses the light alone.
* **Hot pixels** (Eqs. 3-4): a pixel is hot when its pooled dark spike fraction
  exceeds the population median by ``hot_threshold`` spikes per interval
  (theta_HT; the paper thresholds the first recording only). A hot pixel's
  ordinary dark events get the population median mu_DC; its hot charge
  (``mu_HP``, ``sigma_HP`` in threshold units per interval) is fitted to the mean
  and variance of its dark inter-spike intervals with the exact numerical
  first-passage model of the decided reset (:func:`sensor.analysis.theory.fit_hot_pixel`
  with :func:`sensor.analysis.theory.hot_pixel_isi_moments` or
  :func:`sensor.calibration.theory.crossing_hot_pixel_isi_moments`), with
  delta-method standard errors (:func:`hot_pixel_se`).
* **Reset, PRNU (Eq. 5), threshold, sensitivity** from the flats
  (:mod:`sensor.calibration.flatfield`): the reset from the lag-1 ISI correlation; each
  level's per-pixel rate inverted through the exact rate-vs-light law of that
  reset; gains from a rank-1 fit weighted by the information each (level,
  pixel) carries (levels on the interval reset's staircase get none); the
  threshold in electrons by photon transfer (maximum likelihood on the ISI law
  for the interval reset, the variance-time slope of read-out ISI sums for the
  crossing reset); with the flats' illuminance, the sensitivity in
  photoelectrons per lux per interval. Because the model multiplies
  photoelectron *counts* by the gain, the identifiable quantities are the
  effective gain ``theta / ceil(theta / g)`` and ``theta = 1 / mean(1 / k)``.

Pixel pitch, fill factor, QE, clock and refractory time cannot be identified
from dark and flat recordings; they are taken from a base profile.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sensor.errors import CalibrationError, InputError
from sensor.io.fileio import provenance, write_json_atomic
from sensor.profile import SensorProfile
from sensor.io.spikefile import read_spikes
from sensor.calibration.flatfield import fit_flats, flat_level_stats
from sensor.calibration.theory import crossing_hot_pixel_isi_moments
from sensor.analysis.theory import fit_hot_pixel, hot_pixel_isi_moments
from sensor.units import per_interval_to_hz

#: default theta_HT [spikes per interval above the median dark rate] (= 400 Hz at 20 kHz)
DEFAULT_HOT_THRESHOLD = 0.02


@dataclass
class CalibrationReport:
    """Numbers and maps describing a calibration, for the PNG/JSON report."""

    n_dark: int
    n_flat: int
    dark_intervals: int
    flat_intervals: list
    hot_threshold: float
    numbers: dict = field(default_factory=dict)
    dark_fraction: np.ndarray | None = None
    flat_levels_e: list = field(default_factory=list)
    prnu_se: np.ndarray | None = None
    sensitivity: np.ndarray | None = None
    sensitivity_se: np.ndarray | None = None
    #: standard error of ``dark_current_e`` [e-/interval] per pixel (``dark_mode="current"``; NaN on hot pixels)
    dark_current_se: np.ndarray | None = None

    def to_dict(self) -> dict:
        return {"n_dark_recordings": self.n_dark, "n_flat_recordings": self.n_flat,
                "dark_intervals_total": self.dark_intervals, "flat_intervals": self.flat_intervals,
                "hot_threshold_spikes_per_interval": self.hot_threshold,
                "flat_levels_e_per_interval": self.flat_levels_e, **self.numbers}


def _as_recording(x, height, width, drop_columns, what, i):
    if isinstance(x, np.ndarray):
        s = x
    else:
        s = read_spikes(x, height=height, width=width, drop_columns=drop_columns)
    s = np.asarray(s)
    if s.ndim != 3 or s.shape[0] < 2:
        raise CalibrationError(f"{what} recording {i} must be (T >= 2, H, W) spikes; got shape {s.shape}",
                               path=None if isinstance(x, np.ndarray) else x)
    return s.astype(bool, copy=False)


def _name(x, what, i):
    """How a message names recording ``i`` of ``what`` ("dark" / "flat"): its file, or its index."""
    return f"{what} recording {i}" if isinstance(x, np.ndarray) else f"{what} recording {i} ({x})"


def _check_not_repeated(dark, flat):
    """Refuse a file given twice (to --dark, to --flat, or to both): each recording counts once."""
    seen = {}
    for what, recs in (("dark", dark), ("flat", flat)):
        for i, x in enumerate(recs):
            if isinstance(x, np.ndarray):
                continue
            try:
                key = Path(x).resolve()
            except OSError:
                key = Path(x)
            if key in seen:
                w0, i0 = seen[key]
                why = ("each flat must be a different brightness level" if what == w0 == "flat"
                       else "each recording counts once")
                raise CalibrationError(f"given twice ({w0} recording {i0} and {what} recording {i}); {why}",
                                       path=x, field=f"--{what}")
            seen[key] = (what, i)


def _digest(s: np.ndarray) -> str:
    """A content hash of a bool (T, H, W) recording (its shape and packed bits)."""
    import hashlib
    h = hashlib.blake2b(str(s.shape).encode(), digest_size=16)
    h.update(np.packbits(np.ascontiguousarray(s)).tobytes())
    return h.hexdigest()


def _check_unique_data(digests: dict, s, x, what, i):
    """Refuse recording ``i`` of ``what`` when it holds the same spikes as one read before (a copy of a file)."""
    d = _digest(s)
    if d in digests:
        w0, i0, x0 = digests[d]
        why = ("a duplicated brightness level: each flat must be a different level" if what == w0 == "flat"
               else "each recording counts once")
        raise CalibrationError(f"holds the same spikes as {_name(x0, w0, i0)}: {why}",
                               path=None if isinstance(x, np.ndarray) else x,
                               field=f"--{what}" + ("" if not isinstance(x, np.ndarray) else f" recording {i}"))
    digests[d] = (what, i, x)


#: a recording whose mean spike fraction reaches this fires at (nearly) every interval: saturated
SATURATED_FRACTION = 0.9


def _f(x):
    """A float for JSON (None for NaN)."""
    return None if not np.isfinite(x) else float(x)


def hot_pixel_se(isis, mu, sigma, p_dark, moments):
    """Delta-method standard errors of (mu_HP, sigma_HP) fitted to a hot pixel's dark ISIs.

    The sampling covariance of the ISIs' (mean, sd) (empirical second and
    fourth moments) is mapped through the inverse Jacobian of the exact moment
    model ``moments(mu, sigma, p_dark) -> (mean, var)`` (central differences).
    ISIs are treated as independent (exact for the interval reset; the crossing
    reset's carried-over charge correlates them weakly).
    """
    isis = np.asarray(isis, np.float64)
    n = isis.size
    m2 = isis.var()
    m4 = np.mean((isis - isis.mean()) ** 4)
    cov = np.diag([m2 / n, max(m4 - m2 ** 2, 1e-12) / (4 * m2 * n)])

    def ms(a, b):
        mm, vv = moments(a, b, p_dark)
        return np.array([mm, np.sqrt(max(vv, 0.0))])
    sg = max(sigma, 1e-3)
    J = np.column_stack([(ms(mu * 1.02, sg) - ms(mu * 0.98, sg)) / (0.04 * mu),
                         (ms(mu, sg * 1.05) - ms(mu, sg * 0.95)) / (0.10 * sg)])
    try:
        Ji = np.linalg.inv(J)
    except np.linalg.LinAlgError:
        return np.nan, np.nan
    c = Ji @ cov @ Ji.T
    return float(np.sqrt(c[0, 0])), float(np.sqrt(c[1, 1]))


def dark_isi_spans(recordings):
    """Per pixel: (ISIs N, summed span [intervals] from first to last spike, recordings with an ISI) over recordings.

    ``recordings``: iterable of bool (T, H, W) arrays. The mean dark ISI is ``span / N``.
    """
    n_isi = span = n_rec = None
    for s in recordings:
        T = s.shape[0]
        cnt = s.sum(axis=0)
        first = np.argmax(s, axis=0)
        last = T - 1 - np.argmax(s[::-1], axis=0)
        has = cnt >= 2
        if n_isi is None:
            n_isi, span, n_rec = (np.zeros(s.shape[1:], np.int64) for _ in range(3))
        n_isi += np.where(has, cnt - 1, 0)
        span += np.where(has, last - first, 0)
        n_rec += has
    return n_isi, span, n_rec


def dark_current_from_isis(n_isi, span, n_rec, k, f, reset):
    """Dark current [e-/interval] from the dark ISIs of each pixel at ``k`` electrons to fire, and its
    standard error from the ISIs alone: ``(d, se)``, float64 arrays (NaN / inf where a pixel has no ISI).

    The read-out rate is ``N / span``; ``d = k x`` with ``x`` the light [thresholds per interval] that gives
    this rate under ``reset`` (no dark events). The sum of N read-out ISIs has variance ``N Var(U)`` (the
    model's, at the estimate) plus, under the crossing reset, the read-out's quantisation (at most 1/4, about
    1/6, per recording); the delta method carries it to ``d``.
    """
    from sensor.calibration import theory as ct
    from sensor.calibration.flatfield import invert_rate
    n = n_isi.astype(np.float64)
    ok = n > 0
    rate = np.where(ok, n / np.where(span > 0, span, 1), 0.0)
    kk = np.broadcast_to(np.asarray(k, np.float64), rate.shape)
    ff = np.broadcast_to(np.asarray(f, np.float64), rate.shape)
    zero = np.zeros(rate.shape)
    x = invert_rate(reset, rate, kk, zero, ff)
    d = x * kk
    lam = np.maximum(d, 1e-12)
    if reset == "crossing":
        var_u = ct.crossing_readout_unit(lam, kk, zero, ff)[1]
        extra = n_rec / 6.0
    else:
        var_u = ct.interval_isi_moments(lam, kk, zero, ff)[1]
        extra = 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        var_span = n * var_u + extra
        var_rate = np.where(ok, var_span * rate ** 4 / np.where(ok, n, 1) ** 2, np.inf)  # rate = N / span
        e = np.maximum(1e-3 * rate, 1e-9)
        dd = (invert_rate(reset, rate + e, kk, zero, ff) - invert_rate(reset, np.maximum(rate - e, 0), kk, zero, ff)) \
            * kk / (2 * e)
    se = np.where(ok, np.abs(dd) * np.sqrt(var_rate), np.inf)
    return np.where(ok, d, np.nan), se, rate, var_rate, dd


def _isi_stats(trains: list[np.ndarray]):
    """Pooled ISIs (differences of consecutive spike indices) from several spike-index arrays."""
    d = [np.diff(t) for t in trains if t.size >= 2]
    return np.concatenate(d) if d else np.zeros(0)


def calibrate(dark, flat, base: SensorProfile | str = "vidar-default", *, hot_threshold: float = DEFAULT_HOT_THRESHOLD,
              name: str | None = None, height: int | None = None, width: int | None = None, drop_columns: int = 0,
              min_hot_isis: int = 20, reset: str | None = None, flat_lux=None, estimate_threshold: bool = True,
              dark_mode: str | None = None, progress=None, progress_bar: bool = False):
    """Estimate a :class:`SensorProfile` from dark and flat-field recordings.

    Parameters
    ----------
    dark : list of (array (T, H, W) bool | path)
        Dark recordings (the paper uses 20). Paths: .dat or spike containers.
    flat : list of (array | path)
        Flat-field recordings (no lens, uniform light), one per brightness level;
        at least two recordings, of which at least one must have a usable signal
        (mean spike rate above twice the dark rate and below 0.9). Each (level,
        pixel) is weighted by the information it carries; the report says which
        levels were used and why. Under the interval reset, levels where the
        read-out is nearly deterministic (the staircase, typically above ~0.1
        spikes/interval at theta = 2000 e-) carry none: record dim flats too.
    base : SensorProfile or str
        Supplies what spike recordings cannot identify (refractory time, pitch,
        fill factor, QE, clock, interval) and the starting threshold.
    hot_threshold : float
        theta_HT: spikes per interval above the median dark rate that make a pixel hot.
    height, width, drop_columns : int
        Layout of .dat inputs (default: the base profile's).
    min_hot_isis : int
        Hot pixels with fewer dark ISIs than this get their mean ISI only (sigma_HP = 0).
    reset : None, "interval" or "crossing"
        None (default): decide the pixel's reset from the flats' lag-1 ISI
        correlation; a name imposes it.
    flat_lux : list of float, optional
        Illuminance [lux] of each flat field as measured by the user: gives the
        sensitivity [photoelectrons per lux per interval], per pixel and on average.
    estimate_threshold : bool
        Store the photon-transfer threshold in the profile (default); False keeps
        the base profile's threshold (the estimate is still reported).
    dark_mode : None, "events" or "current"
        How the written profile models dark current (its ``dark``); None (default):
        as the base profile does. ``"events"`` estimates ``dark_rate`` (mu_DC of
        dark events); ``"current"``
        estimates ``dark_current_e`` [e-/interval], a charge integrated with the
        light, by inverting each pixel's dark ISI rate through the exact rate law of
        the calibrated reset and threshold (numbers ``dark_current_e_median``,
        ``dark_current_se_median``; map ``dark_current_se``).
    progress : callable, optional
        ``progress(message)`` called as work advances.
    progress_bar : bool
        Show a progress bar over the hot-pixel fits (the slow step).

    Returns
    -------
    (SensorProfile, CalibrationReport)
        The report's ``numbers`` hold, among others: ``reset``, ``reset_z``,
        ``reset_confidence``, ``reset_levels``; ``threshold_e``,
        ``threshold_se``, ``threshold_note``; ``sensitivity_e_per_lux``,
        ``sensitivity_se`` (with ``flat_lux``); per level ``level_light_e``,
        ``level_information_share``, ``level_used``, ``level_reason``;
        ``prnu_se_median``, ``prnu_enough``; ``hot_mu_sigma`` (row, col, mu,
        its SE, sigma, its SE, ISIs). Maps: ``prnu_se``, ``sensitivity``,
        ``sensitivity_se``.
    """
    say = progress or (lambda msg: None)
    base = base if isinstance(base, SensorProfile) else SensorProfile.load(base)
    dark_mode = base.dark if dark_mode is None else dark_mode
    if dark_mode not in ("events", "current"):
        raise CalibrationError(f"unknown dark mode '{dark_mode}'; valid choices: events, current", field="--dark-mode")
    current = dark_mode == "current"
    if not dark:
        raise CalibrationError("no dark recordings given (need at least 1; the paper uses 20)", field="--dark")
    if len(flat) < 2:
        raise CalibrationError(f"need flat-field recordings at >= 2 brightness levels for the PRNU regression; got "
                               f"{len(flat)}", field="--flat")
    if not (np.isfinite(hot_threshold) and hot_threshold > 0):
        raise CalibrationError(f"theta_HT must be a finite number of spikes per interval above 0; got {hot_threshold}",
                               field="--hot-threshold")
    if flat_lux is not None:
        lux = np.asarray(flat_lux, np.float64).reshape(-1)
        bad = [i for i, v in enumerate(lux) if not (np.isfinite(v) and v > 0)]
        if bad:
            raise CalibrationError(f"illuminance {lux[bad[0]]:g} (value {bad[0] + 1}, for flat recording {bad[0]}) "
                                   "must be a finite number of lux above 0", field="--flat-lux")
        if len(flat_lux) != len(flat):
            raise CalibrationError(f"--flat-lux gives {len(flat_lux)} values for {len(flat)} flat recordings; give "
                                   "one illuminance per flat", field="--flat-lux")
    _check_not_repeated(dark, flat)
    digests = {}
    warn = []
    H = height or base.height
    Wd = (width or (base.raw_width if drop_columns else base.width))

    # ---- dark: pooled counts and per-pixel spike-index trains (for hot-pixel ISIs)
    counts = None
    n_int = 0
    dark_recs = []
    for i, x in enumerate(dark):
        s = _as_recording(x, H, Wd, drop_columns, "dark", i)
        if counts is None:
            counts = np.zeros(s.shape[1:], np.int64)
            shape = s.shape[1:]
        elif s.shape[1:] != shape:
            raise CalibrationError(f"dark recording {i} is {s.shape[1:]}, the first one is {shape}")
        _check_unique_data(digests, s, x, "dark", i)
        c = s.sum(axis=0)
        frac = float(c.sum()) / max(c.size * s.shape[0], 1)
        if frac >= SATURATED_FRACTION:
            raise CalibrationError(f"dark recording {i} fires at {100 * frac:.0f} % of pixel-intervals "
                                   "(saturated): a dark recording is taken with no light on the sensor",
                                   path=None if isinstance(x, np.ndarray) else x, field="--dark")
        counts += c
        n_int += s.shape[0]
        dark_recs.append(x if not isinstance(x, np.ndarray) else s)
        say(f"dark {i + 1}/{len(dark)}: {s.shape[0]} intervals")
    if shape != base.shape:
        raise CalibrationError(f"recordings are {shape[0]}x{shape[1]} but the base profile '{base.name}' is "
                               f"{base.height}x{base.width}; pass a base profile of the same size")
    if not counts.any():
        files = ", ".join(str(x) for x in dark if not isinstance(x, np.ndarray))
        raise CalibrationError(f"the dark recordings{' (' + files + ')' if files else ''} hold no spike at all "
                               f"({n_int} intervals): the dark rate would be exactly 0 and every dark event of the "
                               "flats taken for light; record longer darks, or check that the files are spike "
                               "recordings of this sensor", field="--dark")
    p_dark = counts / n_int
    median_p = float(np.median(p_dark))
    hot = (p_dark - median_p) >= hot_threshold
    p_normal = np.where(hot, median_p, p_dark)
    mu_dc = -np.log1p(-np.clip(p_normal, 0.0, 1.0 - 1e-12))
    if current:  # dark ISIs per pixel: the mean ISI pins the dark current
        n_isi, span, n_rec = dark_isi_spans(
            x if isinstance(x, np.ndarray) else _as_recording(x, H, Wd, drop_columns, "dark", i)
            for i, x in enumerate(dark_recs))
        f_pilot = base.refractory_fraction.astype(np.float64)
        # pilot rate variance (base threshold, gain 1) for the PRNU fit's error budget
        _, _, rate_dark, var_rate_dark, _ = dark_current_from_isis(n_isi, span, n_rec, base.threshold_e, f_pilot,
                                                                reset or base.reset)
        med_rate = float(np.median(rate_dark[~hot])) if (~hot).any() else 0.0
        rate_dark = np.where(hot, med_rate, rate_dark)
        mu_dc = np.zeros(shape)

    # ---- flat fields: reset, effective light per pixel, PRNU, threshold, sensitivity
    normal = ~hot
    levels = []
    for i, x in enumerate(flat):
        s = _as_recording(x, H, Wd, drop_columns, "flat", i)
        if s.shape[1:] != shape:
            raise CalibrationError(f"flat recording {i} is {s.shape[1:]}, the dark recordings are {shape}")
        _check_unique_data(digests, s, x, "flat", i)
        path = None if isinstance(x, np.ndarray) else x
        if s.all():
            raise CalibrationError(f"flat recording {i} fires at every pixel in every interval (saturated): it "
                                   "carries no information on the light; record it dimmer or leave it out",
                                   path=path, field="--flat")
        if not s.any():
            raise CalibrationError(f"flat recording {i} holds no spike at all: a flat field is taken with light "
                                   "on the sensor; check the file, or leave it out", path=path, field="--flat")
        levels.append(flat_level_stats(s))
        say(f"flat {i + 1}/{len(flat)}: mean spike rate {levels[-1].rate[normal].mean():.4f} per interval")
    flat_ints = [lv.T for lv in levels]
    # binomial variance of mu_DC = -ln(1 - p): Var(p) / (1 - p)^2
    var_mu = np.clip(p_normal, 1e-12, None) / (n_int * np.clip(1 - p_normal, 1e-12, None))
    if current:
        fit = fit_flats(levels, normal, mu_dc, base.refractory_fraction.astype(np.float64), base.threshold_e,
                        median_p, reset=reset, flat_lux=flat_lux, say=say, dark_current_rate=rate_dark,
                        dark_current_rate_var=np.where(np.isfinite(var_rate_dark), var_rate_dark, 0.0))
    else:
        fit = fit_flats(levels, normal, mu_dc, base.refractory_fraction.astype(np.float64), base.threshold_e,
                        median_p, var_mu=var_mu, reset=reset, flat_lux=flat_lux, say=say)
    for i, (x, why) in enumerate(zip(flat, fit["level_reason"])):  # levels the fit could not use at all
        if why == "no signal" or why.startswith("saturated"):
            what = "is saturated" if why.startswith("saturated") else "has no signal above the dark rate"
            warn.append(f"{_name(x, 'flat', i)} {what} (mean spike rate {fit['level_mean_rate'][i]:.3g} per "
                        "interval): not used for the PRNU, the reset decision or the threshold")
            say("warning: " + warn[-1])
    theta_cal = float(fit["threshold_e"]) if fit.get("threshold_e") is not None and estimate_threshold else \
        float(base.threshold_e)
    gain_fit = np.clip(np.where(hot, 1.0, fit["gain"]), 0.05, None)
    if current:
        k_cal = theta_cal / gain_fit
        d_e, _, _, var_r, dd_dr = dark_current_from_isis(n_isi, span, n_rec, k_cal, base.refractory_fraction,
                                                          fit["reset"])
        d_med = float(np.nanmedian(d_e[normal])) if normal.any() else 0.0
        d_e = np.where(hot, d_med, np.nan_to_num(d_e))
        # d = x_dark(rate) theta / g: the dark rate's error moves d directly and through the gain (the flats'
        # light is the total minus the dark share, so dg / d rate = gain_dark_coeff); the flats' own gain error
        # and, when estimated here, the threshold's (common to all pixels) add
        coeff = np.where(hot, 0.0, fit.get("gain_dark_coeff", np.zeros(shape)))
        se_flat = np.where(hot, 0.0, fit.get("gain_se_flat", fit["gain_se"]))
        var_d = var_r * (dd_dr - d_e * coeff / gain_fit) ** 2 + (d_e * se_flat / gain_fit) ** 2
        if fit.get("threshold_e") is not None and estimate_threshold and fit.get("threshold_se"):
            var_d = var_d + (d_e * float(fit["threshold_se"]) / theta_cal) ** 2
        d_se = np.sqrt(var_d)
        d_se = np.where(hot, np.nan, d_se)
        say(f"dark current: median {d_med:.3g} e-/interval ({fit['reset']} reset, theta {theta_cal:.0f} e-)")
    # ---- hot pixels: ISI moments from the dark recordings
    hot_idx = np.flatnonzero(hot)
    hot_mu = np.zeros(shape, np.float64)
    hot_sigma = np.zeros(shape, np.float64)
    hot_n_isi = np.zeros(shape, np.int64)
    hot_mu_se = np.full(shape, np.nan)
    hot_sigma_se = np.full(shape, np.nan)
    f_map = base.refractory_fraction.astype(np.float64)
    if fit["reset"] == "crossing":
        def moments(m_, s_, p_, f_):
            return crossing_hot_pixel_isi_moments(m_, s_, p_, f_, n_bins=200)
    else:
        def moments(m_, s_, p_, f_):
            return hot_pixel_isi_moments(m_, s_, p_)
    # events: a hot pixel's ordinary dark events come at the median rate. current: its dark current is the
    # median d, a charge of d / theta per interval (gain 1), fitted as part of the hot charge and taken off after
    # (its own shot noise is neglected beside the hot charge's spread)
    p_hot_dark, hot_shift = (0.0, d_med / theta_cal) if current else (median_p, 0.0)
    if hot_idx.size:
        trains = {j: [] for j in hot_idx}
        for i, x in enumerate(dark_recs):
            s = x if isinstance(x, np.ndarray) else _as_recording(x, H, Wd, drop_columns, "dark", i)
            flat_s = s.reshape(s.shape[0], -1)[:, hot_idx]
            for c, j in enumerate(hot_idx):
                trains[j].append(np.flatnonzero(flat_s[:, c]))
        from tqdm import tqdm
        for c, j in enumerate(tqdm(hot_idx, desc="hot-pixel fits", unit="pixel", disable=not progress_bar)):
            isi = _isi_stats(trains[j])
            r, cc = np.unravel_index(j, shape)
            hot_n_isi[r, cc] = isi.size
            mom = functools.partial(moments, f_=float(f_map[r, cc]))
            if isi.size >= 2:
                m, v = float(isi.mean()), float(isi.var(ddof=1))
                if isi.size >= min_hot_isis:
                    mu, sg = fit_hot_pixel(m, v, p_dark=p_hot_dark, moments=mom)
                    hot_mu_se[r, cc], hot_sigma_se[r, cc] = hot_pixel_se(isi, mu, sg, p_hot_dark, mom)
                else:
                    mu, sg = fit_hot_pixel(m, max(v, 1e-6), p_dark=p_hot_dark, moments=mom)[0], 0.0
            else:  # too few spikes for an ISI: use the excess rate
                mu, sg = float(p_dark.reshape(-1)[j] - median_p) + hot_shift, 0.0
            mu = max(mu - hot_shift, 0.0)
            hot_mu[r, cc], hot_sigma[r, cc] = mu, sg
        say(f"hot pixels: {hot_idx.size} ({fit['reset']} reset)")

    gain = gain_fit
    use = np.array(fit["level_used"])

    changes = dict(
        name=name or f"calibrated-{base.name}",
        dark_rate=mu_dc.astype(np.float32), hot_mask=hot, hot_mu=hot_mu.astype(np.float32),
        hot_sigma=hot_sigma.astype(np.float32), prnu_gain=gain.astype(np.float32),
        provenance=dict(base.provenance, **{
            "dark_rate": f"calibrated: -ln(1 - p) of the pooled dark spike fraction over {len(dark)} recordings "
                         f"({n_int} intervals)",
            "hot_mask/hot_mu/hot_sigma": f"calibrated: hot if dark fraction - median >= {hot_threshold}; "
                                         "mu/sigma fitted to dark ISI mean/variance (exact first-passage model)",
            "prnu_gain": "calibrated: information-weighted rank-1 fit of the exact-inverted flat rates "
                         f"({fit['reset']} reset), {int(use.sum())} of {len(flat)} levels carry information",
        }),
        meta=dict(base.meta, calibration=provenance(n_dark=len(dark), n_flat=len(flat))),
    )
    if fit.get("threshold_e") is not None and estimate_threshold:
        changes["threshold_e"] = float(fit["threshold_e"])
        changes["provenance"]["threshold_e"] = (f"calibrated: photon transfer from flat ISI variances "
                                                f"({fit['threshold_e']:.0f} +- {fit['threshold_se']:.0f} e-)")
    if current:
        changes.update(dark="current", dark_rate=np.zeros(shape, np.float32), dark_current_e=d_e.astype(np.float32))
        changes["provenance"].pop("dark_rate", None)
        changes["provenance"]["dark"] = "current: calibrated with --dark-mode current"
        changes["provenance"]["dark_current_e"] = (
            f"calibrated: each pixel's mean dark ISI over {len(dark)} recordings ({n_int} intervals) inverted "
            f"through the exact rate law ({fit['reset']} reset, threshold {theta_cal:.0f} e-, calibrated gain, no "
            "dark events); hot pixels get the median")
    else:
        changes.update(dark="events", dark_current_e=np.zeros(shape, np.float32))
    changes["reset"] = fit["reset"]
    changes["provenance"]["reset"] = (
        f"calibrated: lag-1 ISI correlation test, decision {fit['reset']} (confidence "
        f"{fit['reset_confidence']:.4f})" if reset is None else f"imposed by the user ({reset})")
    prof = base.replace(**changes)
    numbers = {
        "dark_mode": dark_mode,
        "median_dark_fraction": median_p,
        "mean_dark_rate_hz": float(per_interval_to_hz(mu_dc[normal].mean(), base.interval_s)),
        "hot_pixels": int(hot.sum()),
        "hot_mu_median": float(np.median(hot_mu[hot])) if hot.any() else 0.0,
        "hot_sigma_median": float(np.median(hot_sigma[hot])) if hot.any() else 0.0,
        "hot_mu_sigma_columns": ["row", "col", "mu_HP", "mu_HP_se", "sigma_HP", "sigma_HP_se", "dark_isis"],
        "hot_mu_sigma": [[int(r), int(c), float(hot_mu[r, c]), _f(hot_mu_se[r, c]), float(hot_sigma[r, c]),
                          _f(hot_sigma_se[r, c]), int(hot_n_isi[r, c])] for r, c in zip(*np.nonzero(hot))],
        "hot_min_isis": int(hot_n_isi[hot].min()) if hot.any() else 0,
        "prnu_std": float(gain[normal].std()),
        "prnu_se_median": float(np.median(fit["gain_se"][normal])),
        "prnu_levels_used": [bool(u) for u in use],
        "flat_mean_spike_rate": [float(lv.rate[normal].mean()) for lv in levels],
        "warnings": warn,
        **{k: v for k, v in fit.items() if k not in ("gain", "gain_se", "x", "sensitivity_map",
                                                       "sensitivity_se_map", "dark_x",
                                                       "gain_se_flat", "gain_dark_coeff")},
    }
    if current:
        numbers.update(dark_current_e_median=d_med,
                       dark_current_e_p01=float(np.percentile(d_e[normal], 1)) if normal.any() else 0.0,
                       dark_current_e_p99=float(np.percentile(d_e[normal], 99)) if normal.any() else 0.0,
                       dark_current_se_median=float(np.nanmedian(d_se[normal])) if normal.any() else 0.0)
    report = CalibrationReport(n_dark=len(dark), n_flat=len(flat), dark_intervals=n_int, flat_intervals=flat_ints,
                               hot_threshold=hot_threshold, numbers=numbers, dark_fraction=p_dark,
                               flat_levels_e=[float(v) for v in fit["level_light_e"]], prnu_se=fit["gain_se"],
                               sensitivity=fit.get("sensitivity_map"), sensitivity_se=fit.get("sensitivity_se_map"),
                               dark_current_se=d_se if current else None)
    return prof, report


def write_report(report: CalibrationReport, profile: SensorProfile, out_stem) -> list[Path]:
    """Write ``<stem>.json`` (numbers) and ``<stem>.png`` (maps, uncertainty maps and per-level diagnostics).

    Panels: dark-rate histogram; hot-pixel map (mu/sigma of each hot pixel are in
    the JSON, ``hot_mu_sigma``); PRNU map; its standard-error map; PRNU
    histogram; per-level information share (which levels were used and why);
    per-level threshold estimates with error bars and the combined fit; lag-1
    ISI correlation per level against the two resets' predictions; sensitivity
    map (with ``--flat-lux``) or its standard-error summary.
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sensor.io.fileio import atomic_path
    out_stem = Path(out_stem)
    jpath = out_stem.with_suffix(".json")
    write_json_atomic(jpath, {"profile": profile.name, **report.to_dict(), "provenance": provenance()})
    n = report.numbers
    fig, ax = plt.subplots(3, 3, figsize=(15, 12))
    if profile.dark == "current":  # the Hz-equivalent of the dark current (d g / theta firings per interval)
        hz = per_interval_to_hz(profile.dark_current_e * profile.prnu_gain / profile.threshold_e, profile.interval_s)
    else:
        hz = per_interval_to_hz(profile.dark_rate, profile.interval_s)
    normal = ~profile.hot_mask
    vals = hz[normal]
    bins = np.geomspace(max(vals[vals > 0].min() if (vals > 0).any() else 1e-1, 1e-1), max(vals.max(), 1.0), 60)
    ax[0, 0].hist(vals[vals > 0], bins=bins, color="0.3")
    ax[0, 0].set_xscale("log")
    ax[0, 0].set_xlabel("dark current d g / theta / T_r [Hz-equivalent]" if profile.dark == "current"
                        else "dark rate mu_DC / T_r [Hz]")
    ax[0, 0].set_ylabel("pixels")
    ax[0, 0].set_title(f"dark current (mean {vals.mean():.1f} Hz)")
    ax[0, 1].imshow(profile.hot_mask, cmap="gray_r", interpolation="nearest")
    ax[0, 1].set_title(f"hot pixels ({int(profile.hot_mask.sum())}): median mu_HP {n.get('hot_mu_median', 0):.3f}, "
                       f"sigma_HP {n.get('hot_sigma_median', 0):.3f}", fontsize=9)
    im = ax[0, 2].imshow(profile.prnu_gain, cmap="coolwarm", vmin=0.8, vmax=1.2)
    ax[0, 2].set_title("PRNU gain")
    fig.colorbar(im, ax=ax[0, 2])
    if report.prnu_se is not None:
        se = np.where(np.isfinite(report.prnu_se), report.prnu_se, np.nan)
        im = ax[1, 0].imshow(se, cmap="viridis")
        fig.colorbar(im, ax=ax[1, 0])
        ax[1, 0].set_title(f"PRNU standard error (median {np.nanmedian(se[normal]):.4f})")
    g = profile.prnu_gain[normal]
    ax[1, 1].hist(g, bins=60, color="0.3")
    ax[1, 1].set_xlabel("PRNU gain")
    ax[1, 1].set_title(f"PRNU spread: std {g.std():.4f}")
    share = n.get("level_information_share")
    if share is not None:
        rates = n.get("flat_mean_spike_rate", [])
        used = n.get("level_used", [])
        ax[1, 2].bar(range(len(share)), share, color=["tab:green" if u else "tab:red" for u in used])
        ax[1, 2].set_xticks(range(len(share)), [f"{r:.3f}" for r in rates], fontsize=8)
        ax[1, 2].set_xlabel("flat level: mean spikes per interval (green: used)")
        ax[1, 2].set_ylabel("share of PRNU information")
        ax[1, 2].set_title("which levels inform the PRNU map" + ("" if n.get("prnu_enough", True)
                                                                   else " (NOT ENOUGH)"), fontsize=10)
    tl = n.get("threshold_levels") or []
    if tl:
        xs = [t["level"] for t in tl if t["theta_e"] is not None]
        ys = [t["theta_e"] for t in tl if t["theta_e"] is not None]
        es = [t["se_e"] for t in tl if t["theta_e"] is not None]
        ax[2, 0].errorbar(xs, ys, yerr=es, fmt="o", color="k", capsize=3)
        th, ths = n["threshold_e"], n["threshold_se"]
        ax[2, 0].axhspan(th - ths, th + ths, color="tab:blue", alpha=0.3)
        ax[2, 0].axhline(th, color="tab:blue")
        half = 4 * max(ths, 0.1 * th)
        ax[2, 0].set_ylim(max(0.0, th - half), th + half)
        ax[2, 0].set_xlabel("flat level index")
        ax[2, 0].set_ylabel("threshold [e-]")
        ax[2, 0].set_title(f"photon transfer: theta = {th:.0f} +- {ths:.0f} e-")
    rl = n.get("reset_levels") or []
    if rl:
        idx = [i for i, r in enumerate(rl) if r.get("z") is not None]
        rho = [rl[i]["rho"] for i in idx]
        err = [1 / np.sqrt(max(rl[i]["n_pairs"], 1)) for i in idx]
        ax[2, 1].errorbar(idx, rho, yerr=err, fmt="o", color="k", capsize=3, label="observed")
        ax[2, 1].axhline(0.0, color="tab:orange", label="interval reset")
        pc = [(i, r["rho_crossing"]) for i, r in enumerate(rl) if r.get("rho_crossing") is not None]
        if pc:
            ax[2, 1].plot(*zip(*pc), "s", color="tab:purple", label="crossing reset (predicted)")
        ax[2, 1].legend(fontsize=8)
        ax[2, 1].set_xlabel("flat level index")
        ax[2, 1].set_ylabel("lag-1 ISI correlation")
        conf = n.get("reset_confidence")
        ax[2, 1].set_title(f"reset: {n.get('reset')}" + (f" (confidence {conf:.4f})" if conf is not None else ""))
    if report.sensitivity is not None:
        im = ax[2, 2].imshow(report.sensitivity, cmap="magma")
        fig.colorbar(im, ax=ax[2, 2])
        ax[2, 2].set_title(f"sensitivity {n['sensitivity_e_per_lux']:.2f} +- {n['sensitivity_se']:.2f} "
                           "e-/(lux interval)", fontsize=10)
    else:
        ax[2, 2].axis("off")
        ax[2, 2].text(0.05, 0.5, "sensitivity: give --flat-lux", fontsize=11)
    fig.suptitle(f"calibration of {profile.name}: {report.n_dark} dark, {report.n_flat} flat recordings")
    fig.tight_layout()
    ppath = out_stem.with_suffix(".png")
    with atomic_path(ppath) as tmp:
        fig.savefig(tmp, dpi=80)
    plt.close(fig)
    return [jpath, ppath]


def scene_hot_pixels(spikes, *, size: int = 5, factor: float = 4.0, z: float = 8.0, isolation: float = 2.0):
    """Hot pixels of a scene recording without dark frames: isolated spatial outliers of the spike count.

    For real recordings that come without a calibrated profile. ``spikes``
    bool (T, H, W); ``n`` = each pixel's spike count over the T intervals,
    ``m`` = the median count of its ``size`` x ``size`` neighbourhood (at least
    1). A pixel is hot when all of:

    * ``n > factor * m`` (far above its surroundings),
    * ``n - m > z * sqrt(m)`` (significant: a Poisson count of mean ``m`` has
      standard deviation ``sqrt(m)``; the crossing reset's counts vary less, so
      this is conservative),
    * ``n > isolation * max(8 neighbours)`` (a point: the pixels along a thin
      bright line or an edge have bright neighbours too).

    A single-pixel bright point of the scene (a star, a specular glint that
    does not move) passes the same tests and is taken for a hot pixel.
    Returns bool (H, W).
    """
    from scipy.ndimage import maximum_filter, median_filter
    s = np.asarray(spikes)
    if s.ndim != 3:
        raise InputError(f"spikes must be (T, H, W); got shape {s.shape}", field="spikes")
    n = s.sum(axis=0, dtype=np.int64).astype(np.float64)
    m = np.maximum(median_filter(n, size=int(size), mode="nearest"), 1.0)
    fp = np.ones((3, 3), bool)
    fp[1, 1] = False
    neighbours = maximum_filter(n, footprint=fp, mode="nearest")
    return (n > factor * m) & (n - m > z * np.sqrt(m)) & (n > isolation * neighbours)
