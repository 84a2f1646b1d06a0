"""The ELSSim detector effects as pure functions on arrays (one interval at a time).

The chain, for one interval m of the step simulator (Algorithm 2 of the paper)::

    lambda_m [e-]  --compute_collected_rate-->  expected collected e- (refractory, Eq. 6)
                   --compute_shot_noise------>  photoelectron count   (Poisson, line 6)
                   --compute_prnu------------>  charge [e-]           (PRNU gain, line 6)
    + compute_dark_events (Eq. 1): a dark event adds one full threshold (line 8)
    + compute_hot_pixel_charge (Eq. 4): Gaussian charge on hot pixels (line 10)
                   --compute_fire------------>  spike, reset to zero  (lines 11-13)

Each function takes physical arrays and, if stochastic, an explicit
``numpy.random.Generator``. Modelling choices where the paper is ambiguous are
made here and nowhere else (see ``docs/sensor.md``, "Departures and choices").
"""

from __future__ import annotations

import numpy as np


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
