"""Statistical checks of the crossing reset shared by every implementation's tests (test_crossing.py runs them on
the reference and numba kernels, test_torch_models.py on the torch one per device).

Each takes ``sim(rate (T, H, W) float32, profile, seed) -> bool spikes (T, H, W)`` and ``make_profile(h, w,
theta)``, a crossing-reset profile with no refractory period, and asserts within ``Z`` standard errors."""

from __future__ import annotations

import numpy as np
from scipy import stats

from sensor.analysis import theory

from ..conftest import Z


def nth_isis(s, j):
    """The j-th read-out ISI (1-based: between spikes j and j+1) of every pixel of a bool (T, H, W) stream that has
    one: one per pixel, so independent samples."""
    flat = s.reshape(s.shape[0], -1)
    out = []
    for c in range(flat.shape[1]):
        t = np.flatnonzero(flat[:, c])
        if t.size > j:
            out.append(t[j] - t[j - 1])
    return np.asarray(out)


def check_prnu_gain_sets_the_photoelectrons_needed(sim, make_profile) -> None:
    """PRNU gains 0.8 and 1.25 at theta 20 e-: the pixels fire as if their threshold were 25 and 16 e-."""
    lam, theta, T, H, W = 3.0, 20.0, 2000, 30, 20
    gain = np.where(np.arange(H * W).reshape(H, W) % 2 == 0, 0.8, 1.25).astype(np.float32)
    s = sim(np.full((T, H, W), lam, np.float32), make_profile(H, W, theta).replace(prnu_gain=gain), 13)
    for g, k in ((0.8, 25), (1.25, 16)):
        sel = gain == np.float32(g)
        expected = theory.crossing_readout_probability(np.full(T, lam), k).sum()
        _, var = theory.crossing_window_count_moments(lam, k, T)
        counts = s[:, sel].sum(axis=0)
        assert abs(counts.mean() - expected) < Z * np.sqrt(var / counts.size), (g, counts.mean(), expected)


def check_hot_pixel_current_fires_at_every_whole_threshold(sim, make_profile) -> None:
    """No light, no dark, f = 0, current X_m ~ N(mu, sigma^2) theta per interval with P(X < 0) ~ 1e-12: the charge
    is never clipped and each firing keeps the rest of the interval's charge, so the firings by interval T are
    exactly floor(S_T), S_T = sum of T currents ~ N(T mu, T sigma^2); X < 1 gives at most one per interval."""
    H, W, T, mu, sig = 10, 10, 3000, 0.07, 0.01
    prof = make_profile(H, W, 500.0).replace(hot_mask=np.ones((H, W), bool), hot_mu=np.full((H, W), mu),
                                             hot_sigma=np.full((H, W), sig))
    s = sim(np.zeros((T, H, W), np.float32), prof, 14)
    j = np.arange(1, int(T * mu + 20 * np.sqrt(T) * sig + 10))
    tail = stats.norm.sf((j - T * mu) / (sig * np.sqrt(T)))  # P(S_T >= j)
    m1 = tail.sum()
    m2 = ((2 * j - 1) * tail).sum()
    counts = s.sum(axis=0).ravel()
    se = np.sqrt((m2 - m1 * m1) / counts.size)
    assert abs(counts.mean() - m1) < Z * se, (counts.mean(), m1, se)
    # teeth: the interval reset fires every ceil(1 / X) intervals, about T / 15 = 200 < 209.5
    assert abs(T / np.ceil(1 / mu) - m1) > 10 * Z * se
