"""Event-driven ("fast") implementations of the spike models: cost grows with spikes, not intervals.

The model classes and their scheduling: the pixels are cut into tiles, each tile runs a numba
kernel of :mod:`sensor.models.kernels` (which explains why the event-driven path is the same
model as the step simulator, exact in distribution), and the tiles run on a thread pool.

Input: :class:`sensor.rates.Segments` (affine pieces of lambda between
keyframes), so the input cost is per keyframe, not per interval. Output: the
spike frames bit-packed, ``uint8 (B, ceil(H*W/8))``, pixel ``p = r*W + c`` in
byte ``p // 8``, bit ``p % 8`` (little bit order, image orientation).

Randomness and parallelism: the pixels are cut into fixed tiles of
:data:`TILE_PIXELS` pixels; block ``b`` of a stream draws from
``block_generator(seed, model, b, 'fast')``, whose ``spawn(n_tiles)`` children
give each tile its own generator. Tiles run on a thread pool (numba releases the
GIL); the result depends on neither the thread count nor the chunking.

Needs ``numba``. Without it, ``implementation='fast'`` falls back to the
reference step simulator with a warning.
"""

from __future__ import annotations

import os
import warnings
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from sensor.io.bits import unpack_frames
from sensor.models.effects import count_threshold, dark_event_probability
from sensor.models.kernels import HAVE_NUMBA, sample, xoshiro_state  # noqa: F401  (sample: re-exported)
from sensor.models.step import SpikeModel
from sensor.profile import SensorProfile
from sensor.rates import Segments

if HAVE_NUMBA:
    from sensor.models.kernels import crossing_tile, elssim_tile, ideal_tile, isi_tile

#: pixels per tile (a multiple of 8, so tiles own whole bytes of the packed output)
TILE_PIXELS = 8192
#: intervals per block of the fast implementations (part of their reproducibility contract)
FAST_BLOCK_INTERVALS = 1000


def n_threads() -> int:
    """Worker threads for the tiles: ``RENDER2SPIKE_THREADS`` or the CPUs this process may use."""
    env = os.environ.get("RENDER2SPIKE_THREADS")
    if env:
        try:
            return max(1, int(env))
        except ValueError:
            from sensor.errors import InputError
            raise InputError(f"must be a positive integer (worker threads of the fast simulator), got '{env}'",
                             field="RENDER2SPIKE_THREADS") from None
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover
        return max(1, os.cpu_count() or 1)


_POOL: ThreadPoolExecutor | None = None
_POOL_N = 0


def _pool() -> ThreadPoolExecutor:
    global _POOL, _POOL_N
    n = n_threads()
    if _POOL is None or _POOL_N != n:
        _POOL = ThreadPoolExecutor(max_workers=n, thread_name_prefix="render2spike-fast")
        _POOL_N = n
    return _POOL


# ------------------------------------------------------------------------------------------ model classes
class _FastModel(SpikeModel):
    """Common machinery: tiles, thread pool, packed output, segment input."""

    implementation = "fast"
    block_intervals = FAST_BLOCK_INTERVALS
    #: the simulator hands this model :class:`Segments` and takes packed frames back
    uses_segments = True
    uses_rng = True

    def __init__(self, profile: SensorProfile):
        super().__init__(profile)
        self.n_pixels = profile.height * profile.width
        self.n_bytes = (self.n_pixels + 7) // 8
        self.tiles = [(p0, min(p0 + TILE_PIXELS, self.n_pixels)) for p0 in range(0, self.n_pixels, TILE_PIXELS)]

    def _elssim_maps(self, p: SensorProfile) -> None:
        """The per-pixel maps both elssim kernels take: gain, hot-pixel current and tiles, theta, dark current."""
        self.gain = p.prnu_gain.astype(np.float64).reshape(-1)
        self.hot_mu = p.hot_mu.astype(np.float64).reshape(-1)
        self.hot_sigma = p.hot_sigma.astype(np.float64).reshape(-1)
        hot = np.flatnonzero(p.hot_mask.reshape(-1)).astype(np.int64)
        self.hot_tiles = [hot[(hot >= p0) & (hot < p1)] for p0, p1 in self.tiles]
        self.theta = float(p.threshold_e)
        self.dc, self.use_dc = _dark_current(p)

    # the dense interface of SpikeModel, for callers that hand lambda per interval
    def run_block(self, lam, state, rng):
        lam = np.asarray(lam, np.float32)
        bits = self.run_segments(Segments.per_interval(lam, state["m"]), state, rng)
        return unpack_frames(bits, lam.shape[1:])

    def run_segments(self, seg: Segments, state: dict, rng, out=None) -> np.ndarray:
        """Packed spikes uint8 (m1 - m0, ceil(H*W/8)) for the block ``seg``; updates ``state``.

        ``out``: an array of that shape and dtype to write them into, whatever it holds (each tile's
        thread clears its own bytes first, in memory that is already mapped); default a new one.
        """
        if seg.m0 != state["m"]:
            raise ValueError(f"block starts at interval {seg.m0} but the state is at {state['m']}")
        if seg.rates.shape[1] != self.n_pixels:
            raise ValueError(f"segments have {seg.rates.shape[1]} pixels, the profile {self.n_pixels}")
        shape = (seg.m1 - seg.m0, self.n_bytes)
        if out is None:
            out, clear = np.zeros(shape, np.uint8), False
        elif out.shape != shape or out.dtype != np.uint8 or not out.flags.c_contiguous:
            raise ValueError(f"out must be a C-contiguous uint8 array of shape {shape}; got {out.dtype} {out.shape}")
        else:
            clear = True
        rngs = rng.spawn(len(self.tiles)) if self.uses_rng else [None] * len(self.tiles)
        jobs = [(t, g) for t, g in zip(self.tiles, rngs)]
        if len(jobs) == 1 or n_threads() == 1:
            for (p0, p1), g in jobs:
                self._tile_into(seg, state, g, p0, p1, out, clear)
        else:
            futs = [_pool().submit(self._tile_into, seg, state, g, p0, p1, out, clear) for (p0, p1), g in jobs]
            for f in futs:
                f.result()
        state["m"] = seg.m1
        return out

    def submit_segments(self, seg: Segments, state: dict, rng, out: np.ndarray, after=None) -> list:
        """Start the block ``seg`` on the thread pool and return at once: one future per tile, in tile order.

        What :meth:`run_segments` computes into ``out`` (same spikes, same ``state``), without its barrier:
        ``after`` (the futures this returned for the previous block) orders each tile after the same tile of
        the previous block, whose state it continues (a tile's state, random stream and output bytes are its
        own), so a thread that finishes its last tile of one block starts on the next block at once. The
        pool runs jobs in the order they were submitted, so a tile waiting for its predecessor waits for a
        job already running on another thread (never for one still queued; if ``RENDER2SPIKE_THREADS`` changes
        between two blocks, a new pool is made and may wait for the old one's jobs: slower, never stuck, as each
        pool only waits for work submitted before). ``state["m"]`` advances now.

        The caller keeps ``seg.rates`` unchanged and ``out`` untouched until every future is done. Call
        from one thread. Runs the tiles here, one after another, when the pool has one thread (the
        futures are then done)."""
        from concurrent.futures import Future
        if seg.m0 != state["m"]:
            raise ValueError(f"block starts at interval {seg.m0} but the state is at {state['m']}")
        if seg.rates.shape[1] != self.n_pixels:
            raise ValueError(f"segments have {seg.rates.shape[1]} pixels, the profile {self.n_pixels}")
        shape = (seg.m1 - seg.m0, self.n_bytes)
        if out.shape != shape or out.dtype != np.uint8 or not out.flags.c_contiguous:
            raise ValueError(f"out must be a C-contiguous uint8 array of shape {shape}; got {out.dtype} {out.shape}")
        if after is not None and len(after) != len(self.tiles):
            raise ValueError(f"after must hold one future per tile ({len(self.tiles)}); got {len(after)}")
        rngs = rng.spawn(len(self.tiles)) if self.uses_rng else [None] * len(self.tiles)
        futs = []
        if n_threads() == 1:
            for t, ((p0, p1), g) in enumerate(zip(self.tiles, rngs)):
                if after is not None:
                    after[t].result()
                f = Future()
                try:
                    self._tile_into(seg, state, g, p0, p1, out, True)
                    f.set_result(None)
                except BaseException as e:  # noqa: BLE001 - handed to whoever waits, as the pool would
                    f.set_exception(e)
                futs.append(f)
        else:
            pool = _pool()
            for t, ((p0, p1), g) in enumerate(zip(self.tiles, rngs)):
                futs.append(pool.submit(self._tile_after, None if after is None else after[t], seg, state, g, p0,
                                        p1, out))
        state["m"] = seg.m1
        return futs

    def _tile_after(self, prev, seg, state, rng, p0, p1, out):
        if prev is not None:
            prev.result()  # the same tile of the previous block (already running: the pool is FIFO)
        self._tile_into(seg, state, rng, p0, p1, out, True)

    def _tile_into(self, seg, state, rng, p0, p1, out, clear: bool):
        """One tile's spikes OR-ed into ``out``, after clearing the tile's bytes when asked (tiles start on
        whole bytes, TILE_PIXELS being a multiple of 8, so no two threads share a byte)."""
        if clear:
            out[:, p0 >> 3:(p1 + 7) >> 3] = 0
        self._tile(seg, state, rng, p0, p1, out)

    def _tile(self, seg, state, rng, p0, p1, out):  # pragma: no cover - abstract
        raise NotImplementedError


def _dark_current(profile: SensorProfile):
    """(dark current [e-/interval] per pixel, float64 flat; whether it is used): ``dark == "current"``."""
    return profile.dark_current_e.astype(np.float64).reshape(-1), profile.dark == "current"


def _gamma_constants(profile: SensorProfile):
    """Marsaglia-Tsang constants (d = k - 1/3, c = 1/sqrt(9 d)) of each pixel's Gamma(k, 1), k = ceil(theta/g)."""
    k = count_threshold(profile.threshold_e, profile.prnu_gain).reshape(-1)
    d = k - 1.0 / 3.0
    return d, 1.0 / np.sqrt(9.0 * d)


class ELSSimFast(_FastModel):
    """``elssim``, event-driven: one Gamma variate per light spike, geometric dark gaps (see the kernels' doc).

    With ``dark == "current"`` the kernel adds each pixel's ``dark_current_e`` to its light rate (no copy of the
    input): the Gamma targets then count photoelectrons and dark electrons together, and there are no dark events.
    """

    name = "elssim"

    def __init__(self, profile: SensorProfile):
        super().__init__(profile)
        p = profile
        self.gb, self.gc = _gamma_constants(p)
        self.omf = (1.0 - p.refractory_fraction.astype(np.float64)).reshape(-1)
        pd = dark_event_probability(p.dark_rate).reshape(-1)
        self.has_dark = (pd > 0).astype(np.uint8)
        with np.errstate(divide="ignore"):
            self.dinv = np.where(pd > 0, -1.0 / np.log1p(-np.minimum(pd, 1.0)), 0.0)
        self._elssim_maps(p)

    def init_state(self) -> dict:
        n = self.n_pixels
        return {"m": 0, "rem": np.full(n, np.nan), "dark_next": np.zeros(n, np.int64),
                "refr": np.zeros(n, np.uint8), "guard": np.zeros(n, np.int64), "v": np.zeros(n, np.float64)}

    def _tile(self, seg, state, rng, p0, p1, out):
        ti = p0 // TILE_PIXELS
        elssim_tile(rng, xoshiro_state(rng), seg.rates, seg.start, seg.length, seg.lo, seg.nk, seg.w, seg.m0, p0, p1,
                     self.hot_tiles[ti], self.gb, self.gc, self.omf, self.dinv, self.has_dark, self.gain,
                     self.hot_mu, self.hot_sigma, self.theta,
                     state["rem"], state["dark_next"], state["refr"], state["guard"], state["v"], out, self.dc,
                     self.use_dc)


class ELSSimCrossingFast(_FastModel):
    """``elssim`` with the crossing reset, event-driven (profile.reset == "crossing").

    Why it is the reference's model (:class:`sensor.models.step.ELSSimCrossingStep`):
    photoelectrons form a Poisson process of rate lambda(t) (constant within an
    interval), so in the rescaled time ``Lambda(t) = int lambda`` they are a unit
    Poisson process and the k-th one after the pixel starts collecting comes when
    the collected ``Lambda`` passes ``Gamma(k, 1)`` (time rescaling). With the crossing
    reset there is no end-of-interval reset to undo this: a firing at time tau draws
    the next target, the pixel collects nothing until ``tau + f`` (blind), and the
    crossing time inside an interval is ``t = start + (target - collected) / lambda_m``
    exactly. Dark events are a Poisson process of rate mu_DC: exponential gaps, the
    pending one kept while it falls after the blind time (memoryless), redrawn from the
    end of the blind time otherwise. Hot pixels (a current within each interval, kept
    >= 0) draw the photoelectron count of each window (up to the next dark event or the
    interval end); when neither a firing nor the clip at 0 is possible (charge plus all
    photoelectrons plus the positive current stays below theta) only the end charge
    matters, otherwise the arrival times (iid uniform given their number) are walked in
    order and the current's crossing is solved linearly. With ``dark == "current"`` a hot pixel draws one
    Poisson count per stretch of intervals whose currents are >= 0 (the charge then only rises) and finds the
    firing by a search among the arrivals' order statistics (see :mod:`sensor.models.kernels`). Equal in
    distribution to the reference, never bitwise.
    No lock-step path: bright light costs one Gamma per firing.
    """

    name = "elssim"

    def __init__(self, profile: SensorProfile):
        super().__init__(profile)
        p = profile
        self.gb, self.gc = _gamma_constants(p)
        self.fr = p.refractory_fraction.astype(np.float64).reshape(-1)
        self.mu = p.dark_rate.astype(np.float64).reshape(-1)
        self._elssim_maps(p)

    def init_state(self) -> dict:
        n = self.n_pixels
        return {"m": 0, "rem": np.full(n, np.nan), "dark_next": np.full(n, np.inf), "blind": np.zeros(n),
                "guard": np.full(n, np.inf), "v": np.zeros(n)}

    def _tile(self, seg, state, rng, p0, p1, out):
        ti = p0 // TILE_PIXELS
        crossing_tile(rng, xoshiro_state(rng), seg.rates, seg.start, seg.length, seg.lo, seg.nk, seg.w, seg.m0,
                       p0, p1, self.hot_tiles[ti], self.gb, self.gc, self.fr, self.mu, self.gain, self.hot_mu,
                       self.hot_sigma, self.theta, state["rem"], state["dark_next"], state["blind"], state["guard"],
                       state["v"], out, self.dc, self.use_dc)


class IdealFast(_FastModel):
    """``ideal``, event-driven: whole pieces are added at once while the charge stays below threshold."""

    name = "ideal"
    uses_rng = False

    def init_state(self) -> dict:
        return {"m": 0, "v": np.zeros(self.n_pixels, np.float64)}

    def _tile(self, seg, state, rng, p0, p1, out):
        ideal_tile(seg.rates, seg.start, seg.length, seg.lo, seg.nk, seg.w, seg.m0, p0, p1,
                    float(self.profile.threshold_e), state["v"], out)


class ISIFast(_FastModel):
    """``isi``: the reference's Gamma inter-spike intervals, skipping the intervals between firings."""

    name = "isi"

    def __init__(self, profile: SensorProfile):
        super().__init__(profile)
        p = profile
        self.gb, self.gc = _gamma_constants(p)
        # counts throughout (see sensor.models.step.ISIModel): the gain enters once, through k
        self.dark_q = ((p.dark_rate.astype(np.float64) + p.hot_mu) * p.threshold_e / p.prnu_gain).reshape(-1)
        if p.dark == "current":  # dark electrons per interval count as photoelectrons
            self.dark_q = self.dark_q + p.dark_current_e.astype(np.float64).reshape(-1)

    def init_state(self) -> dict:
        return {"m": 0, "tau": np.full(self.n_pixels, np.nan)}

    def _tile(self, seg, state, rng, p0, p1, out):
        isi_tile(rng, xoshiro_state(rng), seg.rates, seg.start, seg.length, seg.lo, seg.nk, seg.w, seg.m0, p0, p1,
                  self.gb, self.gc, self.dark_q, state["tau"], out)


if not HAVE_NUMBA:  # pragma: no cover
    warnings.warn("numba is not installed: implementation='fast' falls back to the reference step simulator "
                  "(about 100x slower); `pip install numba` to enable it", RuntimeWarning, stacklevel=2)
