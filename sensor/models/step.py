"""The step (reference) spike models behind one streaming interface.

A model turns lambda (expected photoelectrons per interval, float32 (B, H, W))
into spikes (bool (B, H, W)), one block of intervals at a time, carrying its
state (integrator charge, last spike, ...) from block to block.

Randomness: block ``b`` of a stream seeded with ``seed`` draws from its own
generator ``PCG64(SeedSequence(seed, spawn_key=(stream_key, b)))`` (the
GalSim-style child seed for that stage and block). Blocks are fixed by absolute
interval index, never by how the caller chunks the input, so a seed gives
bitwise-identical spikes for any chunk size.

The models (registered in :mod:`sensor.models.registry`):

* ``ideal``  Algorithm 1: deterministic integrate-and-fire of lambda, reset to
  zero; no shot, dark, hot-pixel, PRNU or refractory effects (quantisation only).
* ``elssim`` Algorithm 2, with every effect of :mod:`sensor.models.effects`. It follows the
  profile's ``reset``: ``interval`` is Algorithm 2 as published (:class:`ELSSimStep`),
  ``crossing`` the continuous-time pixel that resets at its threshold crossing
  (:class:`ELSSimCrossingStep`).
* ``isi``    an inter-spike-interval baseline in the style of RSIR /
  NeuSpike-Net (see :class:`ISIModel`).

Each model may have several *implementations* (``reference``: the
step-by-step simulator, one interval at a time, here; ``fast``: event-driven, see
:mod:`sensor.models.fast`; ``torch``: PyTorch on a GPU or the CPU, see
:mod:`sensor.models.torch_models`). The reference is the definition.
"""

from __future__ import annotations

import numpy as np

from sensor.models.effects import (compute_collected_rate, compute_dark_events, compute_electron_rate, compute_fire,
                      compute_hot_pixel_charge,
                      compute_hot_pixel_crossings, compute_light_or_dark_crossing, compute_prnu, compute_shot_noise,
                      count_threshold, dark_event_probability)
from sensor.profile import SensorProfile

#: spawn-key tags: one per model so two models with the same seed use different streams
STREAM_KEYS = {"ideal": 0, "elssim": 1, "isi": 2}


def block_generator(seed: int, model: str, block_index: int, implementation: str = "reference") -> np.random.Generator:
    """The generator of one block: a child of ``seed`` keyed by model, implementation and block index."""
    impl_key = {"reference": 0, "fast": 1, "torch": 2}.get(implementation, 7)
    ss = np.random.SeedSequence(int(seed), spawn_key=(STREAM_KEYS.get(model, 99), impl_key, int(block_index)))
    return np.random.Generator(np.random.PCG64(ss))


class SpikeModel:
    """Interface of a streaming spike model implementation.

    Subclasses set ``name`` / ``implementation`` and implement
    :meth:`init_state` and :meth:`run_block`.
    """

    name = "base"
    implementation = "reference"
    #: intervals per block; fixed per implementation (part of its reproducibility contract)
    block_intervals = 256

    def __init__(self, profile: SensorProfile):
        self.profile = profile

    def init_state(self) -> dict:
        raise NotImplementedError

    def run_block(self, lam: np.ndarray, state: dict, rng: np.random.Generator | None) -> np.ndarray:
        """Spikes bool (B, H, W) for lambda (B, H, W) [e-]; updates ``state`` in place."""
        raise NotImplementedError


class IdealModel(SpikeModel):
    """Algorithm 1: V += lambda_m; spike and reset to 0 when V >= theta. Deterministic."""

    name = "ideal"

    def init_state(self) -> dict:
        return {"v": np.zeros(self.profile.shape, np.float64)}

    def run_block(self, lam, state, rng=None):
        theta = self.profile.threshold_e
        out = np.zeros(lam.shape, bool)
        v = state["v"]
        for i in range(lam.shape[0]):
            v += lam[i]
            s = v >= theta
            v[s] = 0.0
            out[i] = s
        return out


class ELSSimStep(SpikeModel):
    """Algorithm 2, step by step (the reference definition of ``elssim``).

    Per interval, in this order: the electron rate (light plus dark current when
    ``dark == "current"``), refractory-scaled expected count (Eq. 6),
    Poisson shot noise, PRNU gain, dark event (Eq. 1), hot-pixel charge
    (Eq. 4), clip at zero, fire and reset to zero. Random draws per interval, in
    this order: Poisson (H, W), uniform (H, W), normal (number of hot pixels).
    """

    name = "elssim"

    def __init__(self, profile: SensorProfile):
        super().__init__(profile)
        p = profile
        self.p_dark = dark_event_probability(p.dark_rate)
        self.has_dark = bool(np.any(self.p_dark > 0))
        self.f_ref = p.refractory_fraction.astype(np.float64)
        self.gain = p.prnu_gain.astype(np.float64)
        self.hot_index = np.flatnonzero(p.hot_mask)
        self.hot_mu = p.hot_mu.reshape(-1)[self.hot_index].astype(np.float64)
        self.hot_sigma = p.hot_sigma.reshape(-1)[self.hot_index].astype(np.float64)
        #: dark current [e-/interval] added to the light (dark == "current"); None with dark events
        self.dark_e = p.dark_current_e.astype(np.float64) if p.dark == "current" else None

    def init_state(self) -> dict:
        shape = self.profile.shape
        return {"v": np.zeros(shape, np.float64), "spiked": np.zeros(shape, bool)}

    def run_block(self, lam, state, rng):
        theta = self.profile.threshold_e
        out = np.zeros(lam.shape, bool)
        v, spiked = state["v"], state["spiked"]
        for i in range(lam.shape[0]):
            rate = compute_electron_rate(lam[i].astype(np.float64), self.dark_e)
            expected = compute_collected_rate(rate, self.f_ref, spiked)
            v += compute_prnu(compute_shot_noise(expected, rng), self.gain)
            if self.has_dark:
                v[compute_dark_events(self.p_dark, rng)] += theta
            if self.hot_index.size:
                vf = v.reshape(-1)
                vf[self.hot_index] += compute_hot_pixel_charge(self.hot_index, self.hot_mu, self.hot_sigma, theta, rng)
            spiked, v = compute_fire(v, theta)
            out[i] = spiked
        state["v"], state["spiked"] = v, spiked
        return out


class ELSSimCrossingStep(SpikeModel):
    """``elssim`` with the crossing reset, interval by interval with exact firing times (the reference).

    With ``dark == "current"`` every pixel's photoelectron rate is ``lambda_m + dark_current_e``
    (:func:`compute_electron_rate`) and there are no dark events (mu_DC = 0).

    The model (see :mod:`sensor.models.effects`, "The crossing reset", and docs/sensor.md):
    within interval m photoelectrons arrive as a Poisson process of rate lambda_m;
    a pixel fires at the moment it holds ``k = ceil(theta / g)`` of them, or at a
    dark event (Poisson process of rate mu_DC), resets to zero at once, is blind
    for ``f = refractory_s / interval_s`` and goes on integrating; hot pixels add a
    charge current. Interval m reads 1 when the pixel fired at least once in
    ``[m, m + 1)``.

    Per interval: the non-hot pixels go through
    :func:`compute_light_or_dark_crossing` as often as they fire (vectorised), the
    hot pixels through :func:`compute_hot_pixel_crossings` (one draw of the
    current per interval, ``normal`` for all hot pixels first). Set
    ``record_crossings = True`` to collect the exact firing times in
    ``state["crossings"]`` (a list of ``(flat pixel index, time [intervals])``
    array pairs), for tests of the continuous-time law.
    """

    name = "elssim"
    record_crossings = False

    def __init__(self, profile: SensorProfile):
        super().__init__(profile)
        p = profile
        self.k = count_threshold(p.threshold_e, p.prnu_gain).reshape(-1)
        self.f = p.refractory_fraction.astype(np.float64).reshape(-1)
        self.mu = p.dark_rate.astype(np.float64).reshape(-1)
        self.gain = p.prnu_gain.astype(np.float64).reshape(-1)
        hot = p.hot_mask.reshape(-1)
        self.hot_index = np.flatnonzero(hot)
        self.cold_index = np.flatnonzero(~hot)
        self.hot_mu = p.hot_mu.reshape(-1)[self.hot_index].astype(np.float64)
        self.hot_sigma = p.hot_sigma.reshape(-1)[self.hot_index].astype(np.float64)
        #: dark current [e-/interval] added to the light of every pixel (dark == "current"); None with dark events
        self.dark_e = p.dark_current_e.astype(np.float64).reshape(-1) if p.dark == "current" else None

    def init_state(self) -> dict:
        n = self.profile.height * self.profile.width
        # count: photoelectrons since reset (non-hot pixels); v: charge [e-] (hot pixels); blind: blind until [t]
        return {"m": 0, "count": np.zeros(n), "v": np.zeros(n), "blind": np.zeros(n), "crossings": []}

    def run_block(self, lam, state, rng):
        theta = float(self.profile.threshold_e)
        B = lam.shape[0]
        out = np.zeros((B, lam.shape[1] * lam.shape[2]), bool)
        count, v, blind = state["count"], state["v"], state["blind"]
        cold = self.cold_index
        k_c, f_c, mu_c = self.k[cold], self.f[cold], self.mu[cold]
        for i in range(B):
            m = float(state["m"] + i)
            lam_i = compute_electron_rate(lam[i].reshape(-1).astype(np.float64), self.dark_e)
            # ---- non-hot pixels: fire as often as the light / dark events say, vectorised
            sel = np.arange(cold.size)
            start = np.maximum(blind[cold], m)
            while sel.size:
                sel = sel[start[sel] < m + 1.0]
                if not sel.size:
                    break
                px = cold[sel]
                tau, after = compute_light_or_dark_crossing(count[px], k_c[sel], start[sel], np.full(sel.size, m + 1.0),
                                                            lam_i[px], mu_c[sel], rng)
                count[px] = after
                fired = np.isfinite(tau)
                out[i, px[fired]] = True
                if self.record_crossings and fired.any():
                    state["crossings"].append((px[fired], tau[fired]))
                sel = sel[fired]
                start[sel] = tau[fired] + f_c[sel]
                blind[cold[sel]] = start[sel]
            # ---- hot pixels: exact event-by-event walk
            if self.hot_index.size:
                cur = rng.normal(self.hot_mu, self.hot_sigma) * theta
                for j, h in enumerate(self.hot_index):
                    s0 = max(blind[h], m)
                    if s0 >= m + 1.0:
                        continue
                    v[h], b, times = compute_hot_pixel_crossings(v[h], s0, m + 1.0, lam_i[h], cur[j], self.gain[h],
                                                                 theta, self.mu[h], self.f[h], rng)
                    if times:
                        out[i, h] = True
                        blind[h] = b
                        if self.record_crossings:
                            state["crossings"].append((np.full(len(times), h), np.asarray(times)))
        state["m"] += B
        return out.reshape(lam.shape)


class ISIModel(SpikeModel):
    """Inter-spike-interval baseline in the style of RSIR / NeuSpike-Net.

    The ISI view draws whole inter-spike intervals instead of integrating
    interval by interval. After a spike at continuous time tau [intervals], the
    next one comes at ``tau + ISI`` with

        ISI ~ Gamma(k, 1 / q),  q = lambda(tau) + (mu_DC + hot_mu) * theta / g   [photoelectrons/interval]

    i.e. the time to collect ``k = ceil(theta / g)`` photoelectrons at the
    constant rate ``q`` seen when the ISI starts (counts throughout, so the
    PRNU gain enters once, through ``k``; dark and hot-pixel currents are
    charges ``mu theta`` per interval, i.e. ``mu theta / g`` photoelectron
    equivalents). Its differences from ELSSim are
    exactly the ones the paper criticises: dark current is a current that adds
    to the photocurrent (coupled with light, not an independent per-interval
    event), the intensity is frozen over each ISI, there is no refractory
    period, and the fractional phase is kept in continuous time; the spike is
    read out in the interval containing its time (integer-ISI quantisation).
    Several firings inside one interval give one spike. Hot pixels add a
    constant current ``hot_mu * theta`` (their sigma is ignored). With
    ``dark == "current"`` the dark term is the pixel's ``dark_current_e``
    (dark electrons per interval, counted as photoelectrons) instead of
    ``mu_DC * theta / g``.
    """

    name = "isi"

    def __init__(self, profile: SensorProfile):
        super().__init__(profile)
        p = profile
        self.k = count_threshold(p.threshold_e, p.prnu_gain)
        # dark + hot current as photoelectron equivalents per interval
        self.dark_q = (p.dark_rate.astype(np.float64) + p.hot_mu) * p.threshold_e / p.prnu_gain.astype(np.float64)
        if p.dark == "current":  # dark electrons per interval (counted as photoelectrons), not mu_DC theta / g
            self.dark_q = self.dark_q + p.dark_current_e.astype(np.float64)

    def init_state(self) -> dict:
        # tau: time of the next firing [intervals since stream start]; NaN = not drawn (start, or no charge)
        return {"tau": np.full(self.profile.shape, np.nan), "m": 0}

    def _draw(self, idx, q, t_from, tau, rng):
        kk = self.k.reshape(-1)[idx]
        isi = np.full(idx.size, np.nan)  # no charge: wait, and draw again at the next interval
        pos = q > 0
        isi[pos] = rng.gamma(kk[pos], 1.0 / q[pos])
        tau.reshape(-1)[idx] = t_from + isi

    def run_block(self, lam, state, rng):
        tau = state["tau"]
        m_start = state["m"]
        out = np.zeros(lam.shape, bool)
        dark_f = self.dark_q.reshape(-1)
        for i in range(lam.shape[0]):
            m = m_start + i
            lam_f = lam[i].reshape(-1).astype(np.float64)
            tf = tau.reshape(-1)
            new = np.flatnonzero(np.isnan(tf))
            if new.size:  # stream start: integration begins at the start of interval m
                self._draw(new, lam_f[new] + dark_f[new], float(m), tau, rng)
            idx = np.flatnonzero(tf < m + 1)
            if idx.size:
                out[i].reshape(-1)[idx] = True
            while idx.size:
                self._draw(idx, lam_f[idx] + dark_f[idx], tf[idx], tau, rng)
                idx = idx[tf[idx] < m + 1]
        state["m"] = m_start + lam.shape[0]
        return out
