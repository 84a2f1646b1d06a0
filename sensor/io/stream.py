"""The one path from a rate input to spikes: a frames folder (or frames held in memory), an ``.npz`` / ``.npy``
rate array or an in-memory array, read in planned chunks (:mod:`sensor.io.reader`), through a
:class:`sensor.SpikeSimulator` that looks ahead, into a spike writer or into memory.

``render2spike simulate``, ``render2spike run``, the datasets and the studies all stream through
:func:`open_stream`. The spikes do not depend on how the input is read (chunk sizes, read-ahead): the same
input, profile, model and seed give the same spikes bit for bit.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Callable, Iterator

import numpy as np

from sensor.errors import InputError, ProfileError
from sensor.io.reader import ArraySource, RateSource, open_rate_input, plan_reads
from sensor.profile import SensorProfile
from sensor.simulator import SpikeSimulator


def _quiet(message: str) -> None:
    pass


def profile_for_input(profile: SensorProfile, shape, say: Callable[[str], None] = print) -> SensorProfile:
    """The profile itself, or its centred window (:meth:`SensorProfile.centred`) when the input is smaller,
    with a note through ``say``."""
    H, W = shape
    if (H, W) == profile.shape:
        return profile
    if H > profile.height or W > profile.width:
        raise ProfileError(f"input is {H}x{W} but profile '{profile.name}' is only {profile.height}x{profile.width}; "
                           "pass a profile of at least the input size (--profile)")
    top, left = (profile.height - H) // 2, (profile.width - W) // 2
    say(f"note: input is {H}x{W}; using the centred {H}x{W} window of profile '{profile.name}' "
        f"(rows {top}:{top + H}, cols {left}:{left + W})")
    return profile.centred(H, W)


@dataclass
class SpikeStream:
    """A rate input (``source``) and the simulator it feeds (``sim``, whose ``profile`` fits the input).

    :meth:`start` plans the reads and starts the reader; :meth:`blocks`, :meth:`write` and :meth:`collect`
    run the stream once (starting it first when needed): running it again is refused (RuntimeError), except
    :meth:`collect`, which returns the spikes it collected. :meth:`close` (or leaving a ``with`` block) stops
    the read-ahead thread and closes the input, also for a stream started and never read.
    """

    source: object
    sim: SpikeSimulator
    chunks: Iterator | None = None
    _state: str = "open"  # "open", "running", "done" (run to its end or failed) or "closed"
    _collected: object = None

    def __enter__(self) -> "SpikeStream":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Stop the read-ahead thread (pending reads cancelled) and close the input file; idempotent."""
        chunks, self.chunks = self.chunks, None
        try:
            if chunks is not None and hasattr(chunks, "close"):
                chunks.close()
        finally:
            close = getattr(self.source, "close", None)
            if close is not None:
                close()
            if self._state != "done":
                self._state = "closed"

    def _check_runnable(self) -> None:
        if self._state == "done":
            raise RuntimeError("this spike stream has already run (blocks, write and collect run it once); open "
                               "a new one with open_stream")
        if self._state == "closed":
            raise RuntimeError("this spike stream is closed; open a new one with open_stream")

    @property
    def profile(self) -> SensorProfile:
        return self.sim.profile

    @property
    def total(self) -> int:
        """Intervals the stream spans."""
        return self.source.n_intervals(self.profile.interval_s)

    def start(self, chunk: int | None = None, warm_up: bool = True) -> "SpikeStream":
        """Plan the reads (:func:`sensor.io.reader.plan_reads`; ``chunk``: keyframes per read, None: one
        simulator block's) and start reading: a reader thread starts on the first chunks at once, while
        ``warm_up`` loads the simulator's kernels here (:meth:`SpikeSimulator.warm_up`)."""
        self._check_runnable()
        if self.chunks is None:
            bounds, ahead = plan_reads(self.source, self.sim, chunk)
            self.chunks = self.source.chunks(self.profile, bounds, ahead)  # the reader thread starts now ...
            if warm_up:
                self.sim.warm_up()  # ... while numba loads the kernels here
        return self

    def blocks(self) -> Iterator[np.ndarray]:
        """Bit-packed spike blocks uint8 (B, ceil(H*W/8)), in order, then the last, partial one.

        The kernel's threads start on each block while this thread hands over the one before
        (``iter_feed_packed(lookahead=True)``); each chunk is handed over as read and checked (``owned``,
        ``checked``), its first ``overlap`` keyframes repeating the previous chunk's last.
        """
        self._check_runnable()
        if self._state == "running":
            raise RuntimeError("this spike stream is already being read (by blocks, write or collect)")
        self.start()
        chunks, sim = self.chunks, self.sim
        self._state = "running"
        try:
            for rate, t, overlap in chunks:
                yield from sim.iter_feed_packed(rate, t, checked=True, owned=True, overlap=overlap, lookahead=True)
            yield from sim.iter_finish_packed()  # the block in flight, then the last, partial one
        finally:
            self._state = "done"
            chunks.close()

    def write(self, writer, progress: Callable[[int], None] | None = None) -> None:
        """Stream into ``writer`` (:class:`sensor.io.spikefile.SpikeWriter`, open); ``progress(n)`` after each
        block of ``n`` intervals. Memory stays flat in duration."""
        shape = self.profile.shape
        for bits in self.blocks():
            writer.write_packed(bits, shape)  # counted, re-ordered and written by a writer thread
            if progress is not None:
                progress(bits.shape[0])

    def collect(self, progress: Callable[[int], None] | None = None):
        """The whole stream in memory, bit-packed (:class:`sensor.io.spikefile.PackedSpikes`); called again, the
        same spikes (the stream runs once)."""
        from sensor.io.spikefile import PackedSpikes
        if self._collected is not None:
            return self._collected
        parts = []
        for bits in self.blocks():
            parts.append(bits)
            if progress is not None:
                progress(bits.shape[0])
        packed = np.concatenate(parts) if parts else np.zeros((0, self.sim.n_bytes), np.uint8)
        self._collected = PackedSpikes(packed, self.profile.shape)
        return self._collected


def open_stream(source, profile, model: str = "elssim", seed: int = 0, *, t_s=None, reset: str | None = None,
                implementation: str = "auto", say: Callable[[str], None] | None = None,
                device: str | None = None) -> SpikeStream:
    """Open a rate input and make the simulator that streams it (nothing is read yet; see
    :meth:`SpikeStream.start`).

    ``source``: a frames folder, frames in memory (:class:`sensor.io.frames.MemoryFrameSequence`), an
    ``.npz`` (``rate_e`` [, ``t_s``]) or ``.npy`` file, an in-memory rate array
    (with keyframe times ``t_s``, or one row per interval), or a source of :mod:`sensor.io.reader`.
    ``profile``: a :class:`SensorProfile` or its name / path; its centred window is used when the input is
    smaller (:func:`profile_for_input`), with ``reset`` replacing its pixel reset when given. ``say`` gets the
    notes and warnings (None: silent). ``implementation`` and ``device``: see :class:`SpikeSimulator`. Raises InputError when the input spans less than one interval.
    """
    say = say or _quiet
    opened = not isinstance(source, (RateSource, ArraySource))
    src = open_rate_input(source, t_s)
    where = source if isinstance(source, (str, os.PathLike)) else getattr(src, "path", None)  # as given
    try:
        profile = profile if isinstance(profile, SensorProfile) else SensorProfile.load(profile)
        profile = profile_for_input(profile, src.shape, say)
        if reset:
            profile = profile.replace(reset=reset)
        rendered_for = (src.frames.manifest.get("profile") or {}).get("name") if src.kind == "frames" else None
        if rendered_for and rendered_for != profile.name:
            say(f"warning: the frames were rendered for profile '{rendered_for}' (its QE weights Phi); simulating "
                f"with '{profile.name}' uses that QE but this profile's pixel area and noise maps")
        sim = SpikeSimulator(profile, model, seed, implementation=implementation, per_interval=src.per_interval,
                             device=device)
        if src.n_intervals(profile.interval_s) < 1:
            what = "keyframes span" if not src.per_interval else "input holds"
            span = (f"{src.t_s[-1] - src.t_s[0]:.6g} s ({src.n} keyframe(s))" if not src.per_interval else "no rows")
            raise InputError(f"the {what} {span}: less than one whole interval of {profile.interval_s * 1e6:g} us "
                             "(need at least two keyframes one interval apart)", path=where,
                             field="frames" if src.kind == "frames" else "t_s")
    except BaseException:
        if opened:  # opened here: released here (a source the caller opened stays the caller's)
            src.close()
        raise
    return SpikeStream(src, sim)
