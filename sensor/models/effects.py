"""The ELSSim detector effects as pure functions on arrays (one interval at a time).

The chain, for one interval m of the step simulator (Algorithm 2 of the paper)::

    lambda_m [e-]  --compute_electron_rate--->  + dark current [e-] (dark == "current" only)
                   --compute_collected_rate-->  expected collected e- (refractory, Eq. 6)
                   --compute_shot_noise------>  photoelectron count   (Poisson, line 6)
                   --compute_prnu------------>  charge [e-]           (PRNU gain, line 6)
    + compute_dark_events (Eq. 1): a dark event adds one full threshold (line 8; dark == "events" only)
    + compute_hot_pixel_charge (Eq. 4): Gaussian charge on hot pixels (line 10)
                   --compute_fire------------>  spike, reset to zero  (lines 11-13)

Each function takes physical arrays and, if stochastic, an explicit
``numpy.random.Generator``. Modelling choices where the paper is ambiguous are
made here and nowhere else (see ``docs/sensor.md``, "Departures and choices").
"""

from __future__ import annotations

import numpy as np


def compute_electron_rate(rate_e, dark_current_e):
    """Expected electrons generated per interval [e-]: photoelectrons plus the dark current (``dark == "current"``).

    Dark current as a charge: thermally generated electrons arrive in the photodiode as a Poisson process of
    ``dark_current_e`` per interval, independent of the photoelectrons, so the pixel's electron arrivals are one
    Poisson process of rate ``lambda_m + dark_current_e``: the dark electrons are counted toward the same
    ``k = ceil(theta / g)``, have their own shot noise, and are lost in the refractory (blind) time as light is.
    ``dark_current_e = None`` (``dark == "events"``) returns ``rate_e`` itself.
    """
    if dark_current_e is None:
        return rate_e
    return rate_e + dark_current_e


def compute_collected_rate(rate_e, refractory_fraction, spiked_prev):
    """Expected photoelectrons collected in this interval [e-] (refractory period, Eq. 6).

    After a spike in the previous interval the pixel recharges for
    ``refractory_s`` and collects no light meanwhile, so it integrates
    ``(1 - refractory_fraction)`` of the interval (with the defaults
    ``T_r / dt - 1 = 249`` of ``250`` time units).

    Choice: the refractory loss scales the *expected* count before Poisson
    sampling (photons that arrive while the pixel recharges are never
    collected). The paper's Algorithm 2 line 8 scales the already-sampled
    count; the two agree in mean and differ by < refractory_fraction in variance.
    """
    return np.where(spiked_prev, rate_e * (1.0 - refractory_fraction), rate_e)


def compute_shot_noise(expected_e, rng: np.random.Generator):
    """Photoelectron counts: Poisson(expected_e), float64 array of integers (shot noise, Eq. line 6).

    Choice: the Poisson variable is the number of *photoelectrons* (QE already
    applied by the render stage). Sampling photons and then thinning by QE gives
    the same Poisson law, so this loses nothing.
    """
    return rng.poisson(expected_e).astype(np.float64)


def compute_prnu(counts, gain):
    """Charge added to the integrator [e-]: counts times the PRNU gain (Algorithm 2 line 6).

    Faithful to the paper: the *sampled* count is multiplied by the per-pixel
    gain, so a pixel of gain g needs ``ceil(threshold / g)`` photoelectrons to
    fire (see :func:`count_threshold`). The alternative, Poisson(g * lambda)
    (PRNU as a QE variation), is not used.
    """
    return counts * gain


def count_threshold(threshold_e, gain):
    """Photoelectrons a pixel of PRNU gain ``gain`` needs to reach ``threshold_e``: ceil(theta / g).

    Integer-valued float array. The exact and fast simulators both use this.
    """
    q = np.float64(threshold_e) / np.asarray(gain, np.float64)
    k = np.ceil(q * (1.0 - 1e-12))  # relative guard: theta / g that is an integer up to round-off stays that integer
    return np.maximum(k, 1.0)


def dark_event_probability(dark_rate):
    """Probability of at least one dark event in an interval: 1 - exp(-mu_DC) (Eq. 1)."""
    return -np.expm1(-np.asarray(dark_rate, np.float64))


def dark_spike_probability(dark, dark_rate, dark_current_e, threshold_e, gain):
    """Expected dark spikes per interval of a pixel in the dark, float64 array (the dark floor of its rate).

    ``dark == "events"``: the probability of at least one dark event, ``1 - exp(-mu_DC)``
    (:func:`dark_event_probability`). ``dark == "current"``: the dark current's firing rate
    ``d / k`` with ``k = ceil(theta / g)`` (:func:`count_threshold`), capped at 1 (the read-out
    reports at most one spike per interval); the blind time after each spike is neglected
    (it shortens a dark pixel's collection by ``refractory_fraction * rate``, under 1e-5 here).
    """
    if dark == "events":
        return dark_event_probability(dark_rate)
    k = count_threshold(threshold_e, gain)
    return np.minimum(np.asarray(dark_current_e, np.float64) / k, 1.0)


def compute_dark_events(p_dark, rng: np.random.Generator):
    """Whether a dark event occurs this interval, bool array (Eq. 1, Algorithm 2 line 8).

    Algorithm 2 adds ``N_DC * theta`` with N_DC ~ Poisson(mu_DC): any N_DC >= 1
    alone reaches the threshold, so only P(N_DC >= 1) = ``p_dark`` matters and a
    Bernoulli draw is exactly equivalent (and one uniform per pixel).
    """
    return rng.random(p_dark.shape) < p_dark


def compute_hot_pixel_charge(hot_index, hot_mu, hot_sigma, threshold_e, rng: np.random.Generator):
    """Hot-pixel charge this interval [e-] for the flat indices ``hot_index`` (Eq. 4, line 10).

    N_HP ~ Normal(mu_HP, sigma_HP^2) in units of the threshold, times theta.
    Negative draws are allowed; the integrator is clipped at zero afterwards
    (:func:`compute_fire`), since a reset pixel cannot hold negative charge.
    """
    return rng.normal(hot_mu, hot_sigma) * threshold_e


def compute_fire(voltage_e, threshold_e):
    """Fire and reset: returns (spikes bool, voltage after reset) (Algorithm 2 lines 11-13).

    The integrator is first clipped at zero (hot-pixel draws can be negative),
    then every pixel at or above the threshold spikes and resets to zero; the
    excess charge is discarded (reset-to-zero, as in the paper).
    """
    v = np.maximum(voltage_e, 0.0)
    spikes = v >= threshold_e
    v[spikes] = 0.0
    return spikes, v


# ------------------------------------------------------------------------------------------------------------
# The crossing reset (profile.reset == "crossing"): the same effects in continuous time.
#
# Time t is measured in intervals (interval m covers [m, m + 1)). Within interval m photoelectrons arrive as a
# Poisson process of constant rate lambda_m per interval (piecewise constant in time); the pixel of PRNU gain g
# fires at the k-th photoelectron since its last reset, k = ceil(theta / g) (the same count as Algorithm 2), at
# that very moment; it is then blind (collects nothing: light, dark or hot-pixel charge) for the refractory
# fraction f of an interval, and integrates again from zero. Dark events form a Poisson process of mu_DC per
# interval (Eq. 1 in continuous time); each adds theta, so it fires the pixel at once. Hot pixels get a charge
# current of N(mu_HP, sigma_HP^2) theta per interval, drawn once per interval and spread evenly over it (Eq. 4 as
# a current); the charge is kept >= 0 continuously. The read-out reports, per interval, whether the pixel fired at
# least once in it. See docs/sensor.md, "The crossing reset".

def compute_light_or_dark_crossing(count, k, t_start, t_end, rate_e, dark_rate, rng: np.random.Generator):
    """First firing of non-hot pixels in ``[t_start, t_end)`` (one piece of constant light), exact times.

    Parameters (1-D arrays of the same length, one entry per pixel)
    ----------
    count : float64
        Photoelectrons collected since the last reset (integer-valued, < k).
    k : float64
        Photoelectrons needed to fire, ``ceil(theta / g)``.
    t_start, t_end : float64
        Collection window [intervals]; ``t_start`` is after any blind time.
    rate_e : float64
        Photoelectron rate [e-/interval] in the window (constant).
    dark_rate : float64
        mu_DC [dark events per interval].

    Returns
    -------
    (tau, count_after) : float64 arrays
        ``tau`` the firing time [intervals] (``inf`` when the pixel does not fire
        in the window); ``count_after`` the count at ``t_end`` when it does not
        fire (0 where it fires).

    How (exact in distribution): the first dark event comes at ``t_start + E / mu_DC``,
    ``E ~ Exp(1)``; the light window ends there (or at ``t_end``). Its photoelectron
    count is ``N ~ Poisson(rate (w - t_start))``; if ``count + N >= k`` the pixel fires
    at the arrival of photoelectron ``j = k - count``, whose time is ``t_start + (w -
    t_start) B`` with ``B ~ Beta(j, N - j + 1)`` (the j-th of N uniform arrival times).
    Otherwise a dark event inside the window fires it. Draws, in this order:
    exponential, Poisson, beta (each for all pixels of the call).
    """
    n = count.size
    with np.errstate(divide="ignore"):
        d = np.where(dark_rate > 0, t_start + rng.standard_exponential(n) / np.where(dark_rate > 0, dark_rate, 1.0),
                     np.inf)
    w = np.minimum(d, t_end)
    got = rng.poisson(rate_e * (w - t_start)).astype(np.float64)
    need = k - count
    light = count + got >= k
    a = np.where(light, need, 1.0)
    b = np.where(light, got - need + 1.0, 1.0)
    frac = rng.beta(a, b)
    tau = np.where(light, t_start + (w - t_start) * frac, np.where(d < t_end, d, np.inf))
    return tau, np.where(np.isfinite(tau), 0.0, count + got)


def compute_hot_pixel_crossings(v_e, t_start, t_end, rate_e, current_e, gain, threshold_e, dark_rate,
                                refractory_fraction, rng: np.random.Generator):
    """One hot pixel through ``[t_start, t_end)`` under the crossing reset (scalars; exact event times).

    ``v_e`` is the charge [e-] at ``t_start``; ``current_e`` the hot-pixel current
    [e- per interval] of this interval (``N(mu_HP, sigma_HP^2) theta``, may be
    negative: the charge then falls, and stays at 0 once it reaches 0). Each
    photoelectron adds ``gain`` e-, a dark event fires at once. Returns
    ``(v_e at t_end, blind_until, list of firing times)``; after a firing the
    pixel holds 0 and is blind until ``tau + f`` (``blind_until`` may lie past
    ``t_end``: the next interval starts blind). Draws per sub-window: exponential
    (dark), Poisson (photoelectrons), uniforms (their times).
    """
    times = []
    s = float(t_start)
    v = float(v_e)
    blind = s
    while s < t_end:
        d = s + rng.standard_exponential() / dark_rate if dark_rate > 0 else np.inf
        w = min(d, t_end)
        arr = np.sort(rng.random(rng.poisson(rate_e * (w - s)))) * (w - s) + s
        tau = np.inf
        t0 = s
        for ta in np.append(arr, w):
            # charge ramps with the current from t0 to ta (kept >= 0): does it reach theta first?
            if current_e > 0 and v + current_e * (ta - t0) >= threshold_e:
                tau = t0 + (threshold_e - v) / current_e
                break
            v = max(v + current_e * (ta - t0), 0.0)
            t0 = ta
            if ta < w:  # a photoelectron
                v += gain
                if v >= threshold_e:
                    tau = ta
                    break
        if not np.isfinite(tau) and d < t_end:
            tau = d
        if not np.isfinite(tau):
            break
        times.append(tau)
        v = 0.0
        blind = tau + refractory_fraction
        s = blind
    return v, max(blind, float(t_start)), times
