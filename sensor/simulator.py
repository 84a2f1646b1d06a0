"""Run a spike model over a rate stream: the streaming class and the one-call function."""

from __future__ import annotations

from typing import Iterator

import numpy as np

from sensor.io.buffers import RecyclingPool
from sensor.errors import InputError
from sensor.models.registry import get_model
from sensor.models.step import SpikeModel, block_generator
from sensor.profile import SensorProfile
from sensor.rates import RateSchedule
from sensor.io.bits import pack_frames, unpack_frames


class SpikeSimulator:
    """Streaming spike simulation with state carried across chunks.

    Feed the rate in chunks of any size (:meth:`feed`), then call
    :meth:`finish`. Memory is bounded by one block of intervals (two with
    ``iter_feed_packed(lookahead=True)``) plus the buffered keyframes; the
    output for a given seed is bitwise identical for any chunking.

    Parameters
    ----------
    profile : SensorProfile or str
        The sensor (or the name / path of a profile).
    model : str
        ``elssim`` (default), ``ideal`` or ``isi``.
    seed : int
        Seed of every random draw of this stream.
    implementation : str
        ``auto`` (default: ``torch`` on a working CUDA device, else ``fast``), ``fast``
        (event-driven numba kernels on the CPU), ``torch`` (PyTorch, on ``device``) or
        ``reference`` (the step-by-step simulator that defines the model); see
        :func:`sensor.models.registry.get_model`.
    per_interval : bool
        True: the rate comes as one value per interval (no timestamps).
        False: keyframes with timestamps, interpolated piecewise-linearly.
    device : str, optional
        Device of the ``torch`` implementation (``cpu``, ``cuda``, ``cuda:N``; default
        ``$RENDER2SPIKE_SPIKE_DEVICE``, else CUDA when it works). With ``auto``, ``cpu`` picks ``fast``.
    """

    def __init__(self, profile, model: str = "elssim", seed: int = 0, *, implementation: str = "auto",
                 per_interval: bool = False, device: str | None = None):
        self.profile = profile if isinstance(profile, SensorProfile) else SensorProfile.load(profile)
        self.model_name = model
        self.seed = int(seed)
        self.model: SpikeModel = get_model(model, self.profile, implementation, device=device)
        self.implementation = self.model.implementation
        #: where the spikes are made: the torch model's device, else the CPU
        self.device = str(getattr(self.model, "device_name", "cpu"))
        self.schedule = RateSchedule(self.profile.interval_s, per_interval=per_interval)
        self.state = self.model.init_state()
        self.block = int(self.model.block_intervals)
        self.n_done = 0  # intervals simulated or started so far (with lookahead, the block in flight included)
        self.finished = False
        # packed spike blocks: a few in flight at once (the caller's, a writer's queue), then recycled
        self._bits = RecyclingPool(np.uint8, keep=5)
        # lookahead: the block whose tiles run on the pool while the caller handles the one before
        # (out, futures), see iter_feed_packed(lookahead=True)
        self._inflight: tuple | None = None
        self._failed: BaseException | None = None  # why a block started ahead was lost (the stream is then over)

    @property
    def looks_ahead(self) -> bool:
        """Whether ``iter_feed_packed(lookahead=True)`` starts blocks ahead with this model (the fast
        implementations) rather than running each one as it is asked for."""
        return hasattr(self.model, "submit_segments")

    @property
    def interval_s(self) -> float:
        return self.profile.interval_s

    def warm_up(self) -> None:
        """Load (or compile) the fast kernels now, not at the first block: numba's JIT cache load
        (~0.3 s once per process) runs here, on a throw-away 8 x 8 window of the profile with the
        same model and input kind. Meanwhile a helper thread faults in the memory of the first spike
        blocks (:meth:`sensor.io.buffers.RecyclingPool.reserve`). This stream's state and spikes are
        untouched."""
        if self.implementation != "fast":
            return
        h, w = min(8, self.profile.height), min(8, self.profile.width)
        # the spike blocks' memory, faulted in on a helper thread while numba loads (the blocks in flight:
        # the one being made, and those a background writer has queued and is writing)
        if getattr(self.model, "uses_segments", False):
            self._bits.reserve((self.block, self.n_bytes), 3)
        sim = SpikeSimulator(self.profile.window(0, 0, h, w), self.model_name, 0, implementation="fast",
                             per_interval=self.schedule.per_interval)
        rate = np.ones((2, h, w), np.float32)
        list(sim.iter_feed_packed(rate, None if sim.schedule.per_interval else [0.0, 2 * self.interval_s]))
        sim.finish_packed()

    def _check_shape(self, rate_e):
        rate_e = np.asarray(rate_e)
        if rate_e.ndim == 2:
            rate_e = rate_e[None]
        if rate_e.ndim != 3 or rate_e.shape[1:] != self.profile.shape:
            raise InputError(f"rate_e must be (K, {self.profile.height}, {self.profile.width}) to match profile "
                             f"'{self.profile.name}'; got {rate_e.shape}", field="rate_e")
        return rate_e

    def _run(self, m0: int, m1: int, packed: bool = False) -> np.ndarray:
        rng = block_generator(self.seed, self.model_name, m0 // self.block, self.implementation)
        if getattr(self.model, "uses_segments", False):
            # the block's bits go into a recycled array when the caller has dropped an earlier one (no fresh
            # memory per block: see sensor.io.buffers); unpacked output only needs them for a moment
            out = self._bits.take((m1 - m0, self.n_bytes))
            bits = self.model.run_segments(self.schedule.segments(m0, m1), self.state, rng, out=out)
            del out
            return bits if packed else unpack_frames(bits, self.profile.shape)
        out = self.model.run_block(self.schedule.rates(m0, m1), self.state, rng)
        return pack_frames(out) if packed else out

    def _submit(self, m0: int, m1: int) -> None:
        """Start block [m0, m1) on the pool behind the one in flight (:meth:`_FastModel.submit_segments`)."""
        rng = block_generator(self.seed, self.model_name, m0 // self.block, self.implementation)
        out = self._bits.take((m1 - m0, self.n_bytes))
        after = self._inflight[1] if self._inflight is not None else None
        futs = self.model.submit_segments(self.schedule.segments(m0, m1), self.state, rng, out, after=after)
        self._inflight = (out, futs)

    def _collect(self, inflight) -> np.ndarray:
        """The spikes of a block started by :meth:`_submit`, once its tiles are done."""
        out, futs = inflight
        try:
            for f in futs:
                f.result()
        except BaseException as e:
            self._failed = e  # the block is lost and the state is past it: nothing after it can be right
            raise
        return out

    def _check_usable(self) -> None:
        if self._failed is not None:
            raise RuntimeError(f"a block of this stream failed earlier ({type(self._failed).__name__}: "
                               f"{self._failed}); its spikes are lost, so the stream cannot go on: start a new "
                               "SpikeSimulator") from self._failed

    def _drain(self) -> Iterator[np.ndarray]:
        """The block still in flight, if any (lookahead)."""
        if self._inflight is not None:
            inflight, self._inflight = self._inflight, None
            yield self._collect(inflight)

    def _iter(self, rate_e, t_s, packed: bool, checked: bool = False, owned: bool = False,
              overlap: int = 0, lookahead: bool = False) -> Iterator[np.ndarray]:
        self._check_usable()
        if self.finished:
            raise InputError("this stream is finished; start a new SpikeSimulator")
        rate_e = self._check_shape(rate_e)
        if lookahead and not (packed and owned):
            raise ValueError("lookahead needs packed output and owned=True input (the block in flight reads the "
                             "keyframes after this call returns)")
        # lookahead only where the model starts blocks without waiting (the fast implementations)
        ahead = lookahead and self.looks_ahead
        if not ahead:  # a caller that stops looking ahead gets the block in flight first
            for bits in self._drain():
                yield bits if packed else unpack_frames(bits, self.profile.shape)
        # no copy of the caller's keyframes: the blocks they complete are simulated now, and the
        # few rows still needed afterwards are copied by detach() before control returns for good
        # (not even those when the caller hands the array over: owned)
        self.schedule.add(rate_e, None if t_s is None else np.atleast_1d(np.asarray(t_s, np.float64)), copy=False,
                          check=not checked, owned=owned, overlap=overlap)
        try:
            while self.schedule.covered() >= self.n_done + self.block:
                if ahead:
                    previous = self._inflight  # the new block's tiles each follow theirs in this one
                    try:
                        self._submit(self.n_done, self.n_done + self.block)
                    except BaseException as e:  # tiles of it may have run (one thread): the state is torn
                        self._failed = e
                        raise
                    self.n_done += self.block
                    if previous is not None:
                        yield self._collect(previous)
                    continue
                out = self._run(self.n_done, self.n_done + self.block, packed)
                self.n_done += self.block
                yield out
        finally:
            self.schedule.detach()

    def iter_feed(self, rate_e, t_s=None) -> Iterator[np.ndarray]:
        """Add rate data and yield spike blocks bool (B, H, W) as whole blocks become available."""
        return self._iter(rate_e, t_s, packed=False)

    def iter_feed_packed(self, rate_e, t_s=None, *, checked: bool = False, owned: bool = False,
                         overlap: int = 0, lookahead: bool = False) -> Iterator[np.ndarray]:
        """Like :meth:`iter_feed`, yielding bit-packed blocks uint8 (B, ceil(H*W/8)).

        Frame layout (:func:`pack_frames`): image orientation, pixel ``p = r*W + c``
        in byte ``p // 8``, bit ``p % 8`` (``np.packbits(..., bitorder='little')``).
        The fast implementations produce this directly (8x less memory than bool).

        For streaming readers that did the work already: ``checked=True`` skips the check that
        every rate is finite and >= 0 (:func:`sensor.rates.check_rates`; the reader checked it,
        naming its file and row); ``owned=True`` hands ``rate_e`` over (a float32 array the
        caller never modifies again), so the keyframes still needed after this call are kept
        without a copy. ``overlap=n``: the first ``n`` keyframes repeat the last ``n`` of the previous
        call (:meth:`RateSchedule.add`); a reader that delivers the rows of each block
        (:func:`sensor.rates.block_keyframe_rows`) this way spares the copy that joins keyframes
        spanning two chunks. None of these changes the spikes.

        ``lookahead=True`` (fast implementations; needs ``owned=True``): each block is started on the
        thread pool and the one before it is yielded while it runs, so the kernel's threads go on from one
        block to the next without waiting for the slowest tile or for the caller (its writer, its reader,
        this method's own set-up of the next block). The last block this call starts stays in flight: the
        next call that completes a block (or any call without lookahead, or :meth:`iter_finish_packed`)
        yields it first. Same spikes, in the same order. If a block's tiles fail, the error is raised when
        that block is handed over, and the stream cannot go on (the next block has run past it).
        """
        return self._iter(rate_e, t_s, packed=True, checked=checked, owned=owned, overlap=overlap,
                          lookahead=lookahead)

    def feed(self, rate_e, t_s=None) -> np.ndarray:
        """Add rate data; return the spikes bool (n, H, W) of the intervals completed by it."""
        blocks = list(self.iter_feed(rate_e, t_s))
        return np.concatenate(blocks) if blocks else np.zeros((0,) + self.profile.shape, bool)

    def finish(self) -> np.ndarray:
        """Simulate the last, partial block; return its spikes (n, H, W), after those of a block still in flight
        (``iter_feed_packed(lookahead=True)``). The stream then ends."""
        bits = self.finish_packed()
        return unpack_frames(bits, self.profile.shape)

    def finish_packed(self) -> np.ndarray:
        """Like :meth:`finish`, bit-packed: uint8 (n, ceil(H*W/8)), the block still in flight included."""
        parts = list(self.iter_finish_packed())
        if not parts:
            return np.zeros((0, self.n_bytes), np.uint8)
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    def iter_finish_packed(self) -> Iterator[np.ndarray]:
        """Like :meth:`finish_packed`, as blocks: the one still in flight (``lookahead``), then the last,
        partial one (none when the stream ends on a block boundary). The stream then ends."""
        self._check_usable()
        if self.finished:
            return
        yield from self._drain()
        self.finished = True
        end = self.schedule.covered()
        if end > self.n_done:
            out = self._run(self.n_done, end, packed=True)
            self.n_done = end
            yield out

    @property
    def n_bytes(self) -> int:
        """Bytes per packed frame, ceil(H*W/8)."""
        return (self.profile.height * self.profile.width + 7) // 8

    def describe(self) -> dict:
        """Metadata of this stream, stored with the spikes."""
        return {"model": self.model_name, "reset": self.profile.reset if self.model_name == "elssim" else None,
                "implementation": self.implementation, "device": self.device, "seed": self.seed,
                "block_intervals": self.block, "profile_id": self.profile.name,
                "interval_s": self.profile.interval_s, "threshold_e": self.profile.threshold_e,
                "packed_bit_order": "little"}


def simulate(rate_e, profile, model: str = "elssim", seed: int = 0, t_s=None, *, implementation: str = "auto",
             chunk: int | None = None, device: str | None = None) -> np.ndarray:
    """Simulate a spike stream in one call.

    Parameters
    ----------
    rate_e : array (K, H, W)
        Photoelectron rate [e-/interval]. With ``t_s`` None, one row per
        interval (K == T). With ``t_s``, keyframes interpolated piecewise-linearly.
    profile : SensorProfile or str
        Sensor instance (or bundled name / file path).
    model : str
        ``elssim``, ``ideal`` or ``isi``.
    seed : int
        Seed; the same seed gives the same spikes bitwise.
    t_s : array (K,), optional
        Keyframe times [s].
    implementation : str
        ``auto`` (default), ``fast``, ``torch`` or ``reference`` (the step simulator); see
        :class:`SpikeSimulator`.
    chunk : int, optional
        Feed the input this many keyframes at a time (for testing the streaming path).
    device : str, optional
        Device of the ``torch`` implementation (see :class:`SpikeSimulator`).

    Returns
    -------
    numpy.ndarray bool (T, H, W)
        One row per interval; ``T = K`` without timestamps, else the whole
        intervals between the first and last keyframe (see :mod:`sensor.rates`).
    """
    rate_e = np.asarray(rate_e, dtype=np.float32)
    if rate_e.ndim != 3:
        raise InputError(f"rate_e must be (K, H, W); got shape {rate_e.shape}", field="rate_e")
    if t_s is not None:
        t_s = np.asarray(t_s, np.float64)
        if t_s.shape != (rate_e.shape[0],):
            raise InputError(f"t_s has shape {t_s.shape}, expected ({rate_e.shape[0]},) to match rate_e",
                             field="t_s")
        from sensor.rates import check_times, n_intervals_spanned
        check_times(t_s)
    sim = SpikeSimulator(profile, model, seed, implementation=implementation, per_interval=t_s is None,
                         device=device)
    if t_s is not None and n_intervals_spanned(t_s[0], t_s[-1], sim.profile.interval_s) < 1:
        raise InputError(f"the keyframes span {t_s[-1] - t_s[0]:.6g} s ({t_s.size} keyframe(s)): less than one whole "
                         f"interval of {sim.profile.interval_s * 1e6:g} us (need at least two keyframes one interval "
                         "apart)", field="t_s")
    step = rate_e.shape[0] if not chunk else int(chunk)
    parts = []
    for i in range(0, rate_e.shape[0], max(step, 1)):
        parts.append(sim.feed(rate_e[i:i + step], None if t_s is None else t_s[i:i + step]))
    parts.append(sim.finish())
    return np.concatenate(parts)
