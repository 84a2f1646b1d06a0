"""PyTorch implementations of the spike models (``implementation="torch"``): the same models on a GPU or the CPU.

One code path for every device: the per-pixel maps, the state and the spikes live on ``self.device`` (a CUDA
device when one works, else the CPU; see :func:`spike_device`); the rate of each interval is evaluated there
from :class:`sensor.rates.Segments` (only the block's keyframe rows are copied in), the spikes are bit-packed
there and only the packed block, ``uint8 (B, ceil(H*W/8))`` in the layout of :mod:`sensor.models.fast`, comes
back to the host for writing. The loop runs over the intervals of a block; each step is vectorised over the
pixels.

The models, and why each is the reference's (equal in distribution, never bitwise: other random numbers):

* ``elssim``, ``interval`` reset (:class:`ELSSimTorch`): Algorithm 2 as :class:`sensor.models.step.ELSSimStep`
  defines it, by time rescaling as the fast kernel does (:mod:`sensor.models.kernels`): the photoelectron count
  since the last reset is a unit Poisson process in the collected expectation, so the pixel fires in the first
  interval whose collected ``lambda_m`` (plus the dark current with ``dark == "current"``; times ``1 - f``
  after a firing, Eq. 6) reaches a ``Gamma(k, 1)`` target, ``k = ceil(theta / g)``, or at a dark event
  (Bernoulli ``1 - exp(-mu_DC)``, Eq. 1); the reset discards the excess and draws a new target. Interval by
  interval for all pixels at once, without a Poisson draw (torch's CUDA Poisson sampler, cuRAND's, returns a
  rounded normal above 4000 expected counts). The hot pixels run on the host, as below.
* ``elssim``, ``crossing`` reset (:class:`ELSSimCrossingTorch`): the continuous-time pixel of
  :class:`sensor.models.step.ELSSimCrossingStep`, by time rescaling (as :class:`sensor.models.fast.ELSSimCrossingFast`):
  photoelectrons are a Poisson process of rate lambda_m within interval m, so the k-th one after the pixel
  starts collecting arrives when the collected ``Lambda = int lambda dt`` passes a ``Gamma(k, 1)`` target,
  ``k = ceil(theta / g)``. Per pixel the state holds the target still to collect (``rem``), the time of the
  pending dark event (``dark_next``; exponential gaps of mean ``1 / mu_DC``, memoryless, so it is kept while it
  falls after the blind time and redrawn from its end otherwise) and the end of the blind time. In interval m a
  pixel collecting from ``s = max(blind, m)`` fires at ``min(s + rem / lambda_m, dark_next)`` when that lies
  before ``m + 1`` (then a new target is drawn, it is blind for ``f``, and it may fire again in the same
  interval: the pixels that fired are iterated until none does), else ``rem -= lambda_m (m + 1 - s)``.
  The hot pixels of either reset (a Gaussian charge, or current, kept >= 0; 0.1 % of ``vidar-default``) are
  not vectorised: they run on the host, through the event-driven numba kernel of their reset on 1 x 8
  sub-sensors of just those pixels (:mod:`sensor.models.fast`, or the reference without numba), on host threads
  while the device works; their spike bits are copied to the device before packing.
* ``ideal`` (:class:`IdealTorch`): Algorithm 1, deterministic. lambda_m is evaluated in float64 from the
  pieces as the fast kernels do; with one rate per interval it is the float32 input exactly, so the spikes are
  bitwise the reference's; with keyframes a spike may move by one interval where the charge meets the
  threshold within float round-off (the reference uses a float32 matrix product).

``isi`` has no torch implementation (the registry gives the numba one).

Randomness: block ``b`` of a stream seeded with ``seed`` draws from
``block_generator(seed, model, b, "torch")`` (its own spawn key); that generator spawns two children: the first
seeds a ``torch.Generator`` on the device (one 63-bit seed), the second spawns one host generator per group of
:data:`HOT_GROUP_PIXELS` hot pixels. The
same seed on the same kind of device gives the same spikes for any chunking (blocks are fixed by absolute
interval index); the CPU and CUDA generators differ, so a stream made on one is not bitwise the one made on the
other.

Importing this module does not import torch: that happens when a model is made.
"""

from __future__ import annotations

import functools
import importlib.util
import os
import sys
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import numpy as np

from sensor.errors import InputError
from sensor.models.effects import count_threshold, dark_event_probability
from sensor.models.step import SpikeModel
from sensor.profile import MAP_NAMES, SensorProfile
from sensor.rates import Segments

#: environment variable that forces the spike stage's device: ``auto`` (default), ``cpu``, ``cuda`` or ``cuda:N``
DEVICE_ENV = "RENDER2SPIKE_SPIKE_DEVICE"
#: intervals per block of the torch implementation (part of its reproducibility contract)
TORCH_BLOCK_INTERVALS = 1000
#: hot pixels per host group of the crossing reset (part of its reproducibility contract: each group has its
#: own random stream, so the spikes do not depend on how many threads run the groups)
HOT_GROUP_PIXELS = 8

_HOT_POOL: ThreadPoolExecutor | None = None


def _hot_pool() -> ThreadPoolExecutor:
    """Threads for the crossing reset's hot-pixel groups: ``RENDER2SPIKE_THREADS`` or the usable CPUs, less the
    one that drives the device (at least 1)."""
    global _HOT_POOL
    if _HOT_POOL is None:
        try:
            n = len(os.sched_getaffinity(0))
        except AttributeError:  # pragma: no cover
            n = os.cpu_count() or 1
        env = os.environ.get("RENDER2SPIKE_THREADS")
        n = int(env) if env and env.isdigit() and int(env) > 0 else max(1, n - 1)
        _HOT_POOL = ThreadPoolExecutor(max_workers=n, thread_name_prefix="render2spike-torch-hot")
    return _HOT_POOL


def _import_torch():
    try:
        import torch
    except ImportError:
        raise InputError("the torch implementation needs PyTorch, which is not installed (pip install torch); "
                         "use implementation 'fast' or 'auto'", field="implementation") from None
    return torch


def _nvidia_driver_present() -> bool:
    """Cheap test, without importing torch: False when this Linux machine has no NVIDIA driver loaded."""
    if not sys.platform.startswith("linux"):
        return True  # no cheap test elsewhere: ask torch
    return os.path.exists("/proc/driver/nvidia/version") or os.path.exists("/dev/nvidiactl")


@functools.lru_cache(maxsize=1)
def cuda_works() -> bool:
    """Whether torch can run on a CUDA device here (a small operation on it succeeds).

    On Linux without an NVIDIA driver it answers False without importing torch, so that the ``auto`` choice
    costs nothing on a machine without a GPU.
    """
    if importlib.util.find_spec("torch") is None or not _nvidia_driver_present():
        return False
    try:
        import torch
        if not torch.cuda.is_available():
            return False
        x = torch.ones(8, device="cuda")
        return bool((x + x).sum().item() == 16.0)
    except Exception:  # noqa: BLE001 - any failure of the CUDA stack means: not usable
        return False


def spike_device(device: str | None = None) -> str:
    """The device the torch implementation runs on: ``device``, else ``$RENDER2SPIKE_SPIKE_DEVICE``, else auto.

    ``auto``: ``cuda`` when a CUDA device works (:func:`cuda_works`), else ``cpu``. ``cpu``, ``cuda`` and
    ``cuda:N`` are taken as given; an unknown name, or ``cuda`` where no CUDA device works, raises
    :class:`InputError` (one line naming the argument or the variable).
    """
    field = "device" if device is not None else DEVICE_ENV
    name = (device if device is not None else os.environ.get(DEVICE_ENV, "")).strip().lower() or "auto"
    if name == "auto":
        return "cuda" if cuda_works() else "cpu"
    base, _, index = name.partition(":")
    if base not in ("cpu", "cuda") or (index and (base != "cuda" or not index.isdigit())):
        raise InputError(f"unknown spike device '{name}'; valid choices: auto, cpu, cuda, cuda:N", field=field)
    if base == "cuda" and not cuda_works():
        raise InputError(f"'{name}' asked for, but no CUDA device works here (no NVIDIA driver, a CPU-only torch, "
                         "or the device failed a test operation); use 'cpu' or 'auto'", field=field)
    if index:
        import torch
        if int(index) >= torch.cuda.device_count():
            raise InputError(f"'{name}' asked for, but this machine has {torch.cuda.device_count()} CUDA device(s) "
                             f"(cuda:0 .. cuda:{torch.cuda.device_count() - 1})", field=field)
    return name


def _host_elssim(profile: SensorProfile) -> SpikeModel:
    """The CPU ``elssim`` model of ``profile``'s reset: the numba kernel, else the reference (what the registry's
    ``fast`` gives; chosen here so that this module does not import the registry, which imports it)."""
    crossing = profile.reset == "crossing"
    from sensor.models.kernels import HAVE_NUMBA
    if HAVE_NUMBA:
        from sensor.models import fast
        return (fast.ELSSimCrossingFast if crossing else fast.ELSSimFast)(profile)
    from sensor.models.step import ELSSimCrossingStep, ELSSimStep
    return (ELSSimCrossingStep if crossing else ELSSimStep)(profile)


# ------------------------------------------------------------------------------------------ model classes
class _TorchModel(SpikeModel):
    """Common machinery: device, maps, lambda from segments on the device, packed output."""

    implementation = "torch"
    block_intervals = TORCH_BLOCK_INTERVALS
    #: the simulator hands this model :class:`Segments` and takes packed frames back
    uses_segments = True
    uses_rng = True
    #: how new Gamma targets are drawn for the pixels that fired: True for every pixel, kept under the mask of
    #: those that fired (no host synchronisation, no gather: the GPU's choice), False for the gathered pixels
    #: that fired only (the fewest draws: the CPU's choice); None: by device (True on CUDA). Same law.
    dense_rounds: bool | None = None

    def __init__(self, profile: SensorProfile, device: str | None = None):
        super().__init__(profile)
        self.torch = torch = _import_torch()
        self.device_name = spike_device(device)
        self.device = torch.device(self.device_name)
        self.n_pixels = profile.height * profile.width
        self.n_bytes = (self.n_pixels + 7) // 8
        self._bit_weights = torch.tensor([1 << b for b in range(8)], dtype=torch.uint8, device=self.device)
        p = profile
        #: dark current [e-/interval] added to the light of every pixel (dark == "current"); None otherwise
        self.dc = self._f64(p.dark_current_e) if p.dark == "current" else None

    # helpers -------------------------------------------------------------------------------------
    def _f64(self, a):
        return self.torch.as_tensor(np.asarray(a, np.float64).reshape(-1), device=self.device)

    def _generator(self, rng: np.random.Generator):
        """(torch.Generator on the device, host numpy generator): the two children of the block's generator."""
        dev_rng, host_rng = rng.spawn(2)
        g = self.torch.Generator(device=self.device)
        g.manual_seed(int(dev_rng.integers(0, 2 ** 63 - 1)))
        return g, host_rng

    def _lambdas(self, seg: Segments):
        """(q, lambda of interval m0 + q as float64 (P,) on the device) for every interval of the block.

        Per piece: ``l0 = sum_r w[i, 1, r] R[lo + r]`` and ``sl = sum_r w[i, 2, r] R[lo + r]`` in float64, in the
        order of the fast kernels; interval q of the piece has ``l0 + sl * q``.
        """
        torch = self.torch
        with warnings.catch_warnings():  # a read-only input (a reader's buffer) is fine: R is never written
            warnings.simplefilter("ignore", UserWarning)
            R = torch.from_numpy(seg.rates)
        R = R.to(self.device)  # (K, P) float32: the block's keyframe rows
        for i in range(seg.n_pieces):
            lo, nk, n = int(seg.lo[i]), int(seg.nk[i]), int(seg.length[i])
            l0 = None
            sl = None
            for r in range(nk):
                x = R[lo + r].to(torch.float64)
                w1, w2 = float(seg.w[i, 1, r]), float(seg.w[i, 2, r])
                l0 = w1 * x if l0 is None else l0 + w1 * x
                if n > 1 and w2 != 0.0:
                    sl = w2 * x if sl is None else sl + w2 * x
            s0 = int(seg.start[i])
            for q in range(n):
                yield s0 + q, (l0 if (sl is None or q == 0) else l0 + sl * float(q))

    def _dense(self) -> bool:
        return self.dense_rounds if self.dense_rounds is not None else self.device.type == "cuda"

    # hot pixels on the host ---------------------------------------------------------------------
    def _setup_hot(self, profile: SensorProfile) -> None:
        """The hot pixels as host models (the numba kernel of the profile's reset, or the reference), in fixed
        groups of :data:`HOT_GROUP_PIXELS`, each with its own state and random stream."""
        hot = np.flatnonzero(profile.hot_mask.reshape(-1))
        self.cold = self.torch.as_tensor(~profile.hot_mask.reshape(-1), device=self.device)
        self.hot_idx = self.torch.as_tensor(hot, dtype=self.torch.int64, device=self.device)
        self.hot_groups = [hot[i:i + HOT_GROUP_PIXELS] for i in range(0, hot.size, HOT_GROUP_PIXELS)]
        self.hot_models = []
        if hot.size:
            self.hot_models = [_host_elssim(_pixel_subprofile(profile, grp)) for grp in self.hot_groups]

    def _hot_group(self, j, seg, state, rng):
        """The spikes of hot-pixel group ``j``, bool (B, its pixels) on the host."""
        from sensor.io.bits import unpack_frames
        grp, model = self.hot_groups[j], self.hot_models[j]
        hseg = Segments(seg.rates[:, grp], seg.start, seg.length, seg.lo, seg.nk, seg.w, seg.m0, seg.m1)
        shape = (1, int(grp.size))
        if getattr(model, "uses_segments", False):
            bits = model.run_segments(hseg, state["hot"][j], rng)
            return unpack_frames(bits, shape).reshape(bits.shape[0], -1)
        lam = hseg.dense().astype(np.float32).reshape((-1,) + shape)
        return model.run_block(lam, state["hot"][j], rng).reshape(lam.shape[0], -1)

    def _submit_hot(self, seg, state, host_rng) -> list:
        """Start the hot-pixel groups of this block on host threads (they run while this thread drives the
        device); one future per group."""
        if not self.hot_models:
            return []
        pool = _hot_pool()
        return [pool.submit(self._hot_group, j, seg, state, r)
                for j, r in enumerate(host_rng.spawn(len(self.hot_models)))]

    def _collect_hot(self, jobs, spk) -> None:
        """The hot pixels' spikes into the device's spike block."""
        if jobs:
            hot = np.concatenate([job.result() for job in jobs], axis=1)
            spk.index_copy_(1, self.hot_idx, self.torch.from_numpy(np.ascontiguousarray(hot)).to(self.device))

    def _rate(self, lam):
        return lam if self.dc is None else lam + self.dc

    def _pack(self, spk):
        """bool (B, P) on the device -> uint8 (B, ceil(P/8)) on the device (little bit order)."""
        torch = self.torch
        B = spk.shape[0]
        x = spk.to(torch.uint8)
        pad = self.n_bytes * 8 - self.n_pixels
        if pad:
            x = torch.nn.functional.pad(x, (0, pad))
        return (x.view(B, self.n_bytes, 8) * self._bit_weights).sum(dim=2, dtype=torch.uint8)

    # the dense interface of SpikeModel, for callers that hand lambda per interval
    def run_block(self, lam, state, rng):
        from sensor.io.bits import unpack_frames
        lam = np.asarray(lam, np.float32)
        bits = self.run_segments(Segments.per_interval(lam, state["m"]), state, rng)
        return unpack_frames(bits, lam.shape[1:])

    def run_segments(self, seg: Segments, state: dict, rng, out=None) -> np.ndarray:
        """Packed spikes uint8 (m1 - m0, ceil(H*W/8)) on the host for the block ``seg``; updates ``state``
        (kept on the device). ``out``: a C-contiguous uint8 array of that shape to write them into."""
        if seg.m0 != state["m"]:
            raise ValueError(f"block starts at interval {seg.m0} but the state is at {state['m']}")
        if seg.rates.shape[1] != self.n_pixels:
            raise ValueError(f"segments have {seg.rates.shape[1]} pixels, the profile {self.n_pixels}")
        shape = (seg.m1 - seg.m0, self.n_bytes)
        if out is not None and (out.shape != shape or out.dtype != np.uint8 or not out.flags.c_contiguous):
            raise ValueError(f"out must be a C-contiguous uint8 array of shape {shape}; got {out.dtype} {out.shape}")
        torch = self.torch
        g, host_rng = self._generator(rng) if self.uses_rng else (None, None)
        spk = torch.zeros((shape[0], self.n_pixels), dtype=torch.bool, device=self.device)
        self._block(seg, state, g, host_rng, spk)
        packed = self._pack(spk)
        if out is None:
            out = np.empty(shape, np.uint8)
        torch.from_numpy(out).copy_(packed)
        state["m"] = seg.m1
        return out

    def _block(self, seg, state, g, host_rng, spk):  # pragma: no cover - abstract
        raise NotImplementedError


class IdealTorch(_TorchModel):
    """``ideal`` (Algorithm 1): V += lambda_m; spike and reset to 0 at V >= theta. Deterministic."""

    name = "ideal"
    uses_rng = False

    def init_state(self) -> dict:
        return {"m": 0, "v": self.torch.zeros(self.n_pixels, dtype=self.torch.float64, device=self.device)}

    def _block(self, seg, state, g, host_rng, spk):
        theta = float(self.profile.threshold_e)
        v = state["v"]
        for q, lam in self._lambdas(seg):
            v += lam
            s = v >= theta
            v.masked_fill_(s, 0.0)
            spk[q] = s


class ELSSimTorch(_TorchModel):
    """``elssim`` with the interval reset: Algorithm 2 by time rescaling, vectorised over the pixels.

    Per pixel the state holds the photoelectrons still to collect before the count since the last reset
    reaches ``k = ceil(theta / g)``, as a ``Gamma(k, 1)`` target in expected photoelectrons (the count is a unit
    Poisson process in the collected expectation, see :mod:`sensor.models.kernels`), and whether it fired in the
    previous interval. Interval m collects ``lambda_m`` (plus the dark current with ``dark == "current"``;
    times ``1 - f`` after a firing, Eq. 6); the pixel fires when that reaches the target, or at a dark event
    (Bernoulli ``1 - exp(-mu_DC)``, Eq. 1), and then draws a new target (the reset discards the excess). The
    hot pixels (Gaussian charge, clipped at 0) run on the host (:meth:`_setup_hot`). No Poisson draw: cuRAND's
    Poisson sampler, which torch uses on CUDA, returns a rounded normal above 4000 expected counts; the Gamma
    sampler is Marsaglia-Tsang's rejection method, exact.

    Draws: at the stream's first block a Gamma target per pixel; per interval a uniform per pixel (with dark
    events) and the new targets (:attr:`dense_rounds`).
    """

    name = "elssim"

    def __init__(self, profile: SensorProfile, device: str | None = None):
        super().__init__(profile, device)
        p = profile
        self.k = self._f64(count_threshold(p.threshold_e, p.prnu_gain))
        self.omf = self._f64(1.0 - p.refractory_fraction.astype(np.float64))
        pd = dark_event_probability(p.dark_rate).reshape(-1)
        self.has_dark = bool(np.any(pd > 0))
        self.p_dark = self._f64(pd)
        self._setup_hot(p)

    def init_state(self) -> dict:
        torch = self.torch
        n, dev = self.n_pixels, self.device
        return {"m": 0, "started": False,
                "rem": torch.full((n,), float("nan"), dtype=torch.float64, device=dev),
                "spiked": torch.zeros(n, dtype=torch.bool, device=dev),
                "hot": [hm.init_state() for hm in self.hot_models]}

    def _block(self, seg, state, g, host_rng, spk):
        torch = self.torch
        jobs = self._submit_hot(seg, state, host_rng)
        rem, spiked = state["rem"], state["spiked"]
        if not state["started"]:  # the stream starts reset
            rem.copy_(torch._standard_gamma(self.k, generator=g))
            state["started"] = True
        dense = self._dense()
        for q, lam in self._lambdas(seg):
            rate = self._rate(lam)
            collected = torch.where(spiked, rate * self.omf, rate)  # refractory after a firing (Eq. 6)
            fire = rem <= collected
            if self.has_dark:  # a dark event (Eq. 1) fires the pixel whatever its charge
                fire |= torch.rand(self.n_pixels, generator=g, dtype=torch.float64, device=self.device) < self.p_dark
            fire &= self.cold
            rem.sub_(collected)
            if dense:
                rem.copy_(torch.where(fire, torch._standard_gamma(self.k, generator=g), rem))
            else:
                idx = fire.nonzero().squeeze(1)
                rem.index_copy_(0, idx, torch._standard_gamma(self.k.index_select(0, idx), generator=g))
            spiked = fire
            spk[q] = fire
        state["spiked"] = spiked
        self._collect_hot(jobs, spk)


def _pixel_subprofile(profile: SensorProfile, idx: np.ndarray) -> SensorProfile:
    """The pixels ``idx`` (flat indices) of ``profile`` as a 1 x n sensor (same scalars, their maps)."""
    maps = {nm: getattr(profile, nm).reshape(-1)[idx][None, :].copy() for nm in MAP_NAMES}
    return replace(profile, name=f"{profile.name}[{idx.size} pixels]", height=1, width=int(idx.size),
                   raw_width=None, **maps)


class ELSSimCrossingTorch(_TorchModel):
    """``elssim`` with the crossing reset: time rescaling on the device, the hot pixels on the host.

    Draws: at the stream's first block a Gamma(k) target for every pixel, then an exponential (dark) for every
    pixel with dark events; per interval, for each round of firings, a Gamma target and an exponential for the
    pixels that fired (on the CPU) or for all pixels, kept where they fired (on CUDA: see :attr:`dense_rounds`).
    See the module docstring for why this is the reference's law.
    """

    name = "elssim"

    def __init__(self, profile: SensorProfile, device: str | None = None):
        super().__init__(profile, device)
        p = profile
        self.k = self._f64(count_threshold(p.threshold_e, p.prnu_gain))
        self.f = self._f64(p.refractory_fraction)
        mu = p.dark_rate.astype(np.float64).reshape(-1)
        self.has_dark = bool(np.any(mu > 0))
        self.mu = self._f64(mu)
        self._setup_hot(p)

    def init_state(self) -> dict:
        torch = self.torch
        n, dev = self.n_pixels, self.device
        return {"m": 0, "started": False,
                # Gamma(k) target still to collect [expected photoelectrons]; time of the pending dark event and
                # end of the blind time [intervals since the stream start]
                "rem": torch.full((n,), float("nan"), dtype=torch.float64, device=dev),
                "dark_next": torch.full((n,), float("inf"), dtype=torch.float64, device=dev),
                "blind": torch.zeros(n, dtype=torch.float64, device=dev),
                "hot": [hm.init_state() for hm in self.hot_models]}

    def _exp_after(self, t0, mu, g):
        """t0 + Exp(mu) per pixel (inf where mu = 0)."""
        e = self.torch.empty_like(t0).exponential_(generator=g)
        return t0 + e / mu

    def _rounds_compact(self, row, fired, tau, lam, m1, state, g):
        """The firings after the first pass, on the pixels that fired only (gathered by index): each round
        resets them, draws their new Gamma target (and dark event), and keeps those that fire again before m1.
        Two host synchronisations per round; the fewest draws (the CPU's choice)."""
        torch = self.torch
        rem, dark_next, blind = state["rem"], state["dark_next"], state["blind"]
        idx = fired.nonzero().squeeze(1)
        t = tau.index_select(0, idx)  # their firing times
        # (index_select / index_copy_ rather than x[idx]: torch's CPU advanced indexing is ~100x slower)
        while idx.numel():
            row.index_fill_(0, idx, True)
            s_new = t + self.f.index_select(0, idx)
            lam_i = lam.index_select(0, idx)
            r_new = torch._standard_gamma(self.k.index_select(0, idx), generator=g)
            dn = dark_next.index_select(0, idx)
            if self.has_dark:  # a dark event that fired, or falls in the blind time, is gone: the next one
                dn = torch.where((dn <= t) | (dn < s_new), self._exp_after(s_new, self.mu.index_select(0, idx), g), dn)
            tau_i = torch.minimum(s_new + r_new / lam_i, dn)
            again = tau_i < m1
            r_new = torch.where(again, r_new, r_new - lam_i * torch.clamp(m1 - s_new, min=0.0))
            blind.index_copy_(0, idx, s_new)
            rem.index_copy_(0, idx, r_new)
            dark_next.index_copy_(0, idx, dn)
            sel = again.nonzero().squeeze(1)
            idx, t = idx.index_select(0, sel), tau_i.index_select(0, sel)

    def _rounds_dense(self, row, fired, tau, lam, m1, state, g):
        """The same rounds on whole arrays under the mask of the pixels that fired: a Gamma (and an exponential)
        is drawn for every pixel each round and kept where it fired. One host synchronisation per round, no
        gather (the GPU's choice: its kernels are cheap, its synchronisations are not). Same law."""
        torch = self.torch
        rem, dark_next, blind = state["rem"], state["dark_next"], state["blind"]
        while True:
            row |= fired
            s_new = torch.where(fired, tau + self.f, blind)
            rem.copy_(torch.where(fired, torch._standard_gamma(self.k, generator=g), rem))
            if self.has_dark:  # a dark event that fired, or falls in the blind time, is gone: the next one
                redraw = fired & ((dark_next <= tau) | (dark_next < s_new))
                dark_next.copy_(torch.where(redraw, self._exp_after(s_new, self.mu, g), dark_next))
            blind.copy_(s_new)
            tau = torch.minimum(s_new + rem / lam, dark_next)
            again = fired & (tau < m1)
            rem.sub_(torch.where(fired & ~again, lam * torch.clamp(m1 - s_new, min=0.0), 0.0))
            if not bool(again.any()):
                return
            fired = again

    def _block(self, seg, state, g, host_rng, spk):
        torch = self.torch
        hot_jobs = self._submit_hot(seg, state, host_rng)
        rem, dark_next, blind = state["rem"], state["dark_next"], state["blind"]
        if not state["started"]:  # the stream starts reset and not blind at t = 0
            rem.copy_(torch._standard_gamma(self.k, generator=g))
            if self.has_dark:
                dark_next.copy_(self._exp_after(torch.zeros_like(blind), self.mu, g))
            state["started"] = True
        cold = self.cold
        dense = self._dense()
        for q, lam in self._lambdas(seg):
            lam = self._rate(lam)
            m = float(seg.m0 + q)
            m1 = m + 1.0
            # ---- first pass, all pixels: collect from s = max(blind, m) to the first firing or m + 1
            s = torch.clamp(blind, min=m)
            tau = torch.minimum(s + rem / lam, dark_next)  # rem / 0 = inf: no light, no light firing
            fired = cold & (tau < m1)
            rem.sub_(torch.where(fired, 0.0, lam * torch.clamp(m1 - s, min=0.0)))
            # ---- the pixels that fired: reset, blind for f, and on to the next firing in this interval
            if dense:
                self._rounds_dense(spk[q], fired, tau, lam, m1, state, g)
            else:
                self._rounds_compact(spk[q], fired, tau, lam, m1, state, g)
        self._collect_hot(hot_jobs, spk)
