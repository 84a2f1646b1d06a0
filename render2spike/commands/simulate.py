"""``render2spike simulate``: irradiance frames or a rate array -> spike stream."""

from __future__ import annotations

from render2spike.commands._common import seed as _seed_type

import argparse
import contextlib
import sys
import time
from pathlib import Path

HELP = "simulate a spike stream from irradiance frames or a photoelectron-rate array"
DESCRIPTION = """\
Turn time-varying light into the spike stream of a spike camera.

INPUT is one of
  * a frames folder written by `render2spike render` (frames.json + EXR files with
    channel Phi in e-/(s m^2)); Phi is converted to photoelectrons per interval
    with the profile's pixel area x fill factor x T_r and interpolated
    piecewise-linearly between frame timestamps;
  * an .npz file with `rate_e` (K, H, W) [expected photoelectrons per interval]
    and optionally `t_s` (K,) [s] keyframe times (without `t_s`: one row per
    interval of T_r = 50 us);
  * an .npy file holding `rate_e` (T, H, W), one row per interval.

The output is an .npz container (bit-packed spikes + metadata: interval, model,
profile, seed, source) or a SpikeCV-compatible .dat file. Both are written as the
blocks come (memory stays flat in duration): the .npz deflated block by block
(level 1), the .dat around the page cache where the file system allows
(O_DIRECT; set RENDER2SPIKE_DIRECT_IO=0 to write through the page cache).
If INPUT is smaller than the profile, the centred window of the profile is used.
"""
EXAMPLES = """\
examples:
  render2spike simulate out/frames --out spikes.npz
  render2spike simulate rate.npz --out spikes.dat --model isi --seed 7
  render2spike simulate out/frames --out ref.npz --reference   # step-by-step reference simulator
  render2spike simulate out/frames --out gpu.npz --implementation torch --device cuda  # PyTorch on the GPU
  render2spike simulate rate.npz --out alg2.npz --reset interval  # Algorithm 2's end-of-interval reset
"""


def register(sub) -> None:
    from sensor.models.registry import IMPLEMENTATIONS, MODELS
    from sensor.profile import RESETS

    from render2spike.commands._common import add_overwrite
    p = sub.add_parser("simulate", help=HELP, description=DESCRIPTION, epilog=EXAMPLES,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("input", metavar="INPUT", help="frames folder, .npz (rate_e[, t_s]) or .npy (rate_e per interval)")
    p.add_argument("--out", required=True, metavar="SPIKES", help="output .npz (with metadata) or .dat")
    p.add_argument("--model", default="elssim", choices=MODELS, help="noise model (default: elssim)")
    p.add_argument("--profile", default="vidar-default", metavar="NAME|PATH",
                   help="sensor profile: bundled name or .npz file (default: vidar-default)")
    p.add_argument("--seed", type=_seed_type, default=0, help="spike seed: seeds every random draw of the simulation (default: 0)")
    p.add_argument("--reset", choices=RESETS, default=None,
                   help="pixel reset of elssim, overriding the profile's: 'crossing' (fires and resets the moment "
                        "the charge reaches the threshold; vidar-default) or 'interval' (Algorithm 2 as published)")
    p.add_argument("--implementation", choices=IMPLEMENTATIONS, default=None,
                   help="spike simulator: 'auto' (default: 'torch' on a working CUDA GPU, else 'fast'), 'fast' "
                        "(event-driven numba kernels on the CPU cores), 'torch' (PyTorch, on --device) or "
                        "'reference' (the step-by-step simulator that defines the model)")
    p.add_argument("--device", default=None, metavar="DEVICE",
                   help="device of the torch implementation: auto, cpu, cuda or cuda:N (default: "
                        "$RENDER2SPIKE_SPIKE_DEVICE, else auto: CUDA when it works); with --implementation auto, "
                        "'cpu' picks 'fast'")
    p.add_argument("--reference", action="store_true",
                   help="use the step-by-step reference simulator (the same as --implementation reference)")
    p.add_argument("--chunk", type=int, default=None, metavar="K",
                   help="keyframes read per step (the result does not depend on it). Default: the keyframes of "
                        "one simulator block (1000 intervals) per read, so no block's keyframes are joined from "
                        "two reads, or 32 when a block's keyframes exceed 64 MB. A reader thread keeps about two "
                        "blocks of keyframes read ahead, at most 256 MB, and reuses up to 6 chunk buffers")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_overwrite(p)
    p.set_defaults(func=run)


def run(args) -> int:
    frozen = {}
    try:
        return _run(args, frozen)
    finally:
        if frozen.get("frozen"):  # the start-up's objects go back to the collector (see _start_up)
            import gc
            gc.unfreeze()


def _run(args, frozen: dict) -> int:
    from tqdm import tqdm

    from sensor.io.spikefile import SpikeWriter

    t0 = time.perf_counter()
    say = (lambda m: None) if args.quiet else print
    with _start_up(frozen):
        stream = _prepare(args, say)
    profile, sim = stream.profile, stream.sim
    extra = {"input_kind": stream.source.kind, "simulator": sim.describe()}
    total = stream.total
    with SpikeWriter(args.out, interval_s=profile.interval_s, model=args.model, profile_id=profile.name,
                     seed=args.seed, source=str(Path(args.input).resolve()), implementation=sim.implementation,
                     extra=extra, background=True, expected_intervals=total) as writer, \
            tqdm(total=total, unit="interval", disable=args.quiet, desc="simulate") as bar:
        stream.write(writer, bar.update)
    dt = time.perf_counter() - t0
    n = writer.n_intervals
    rate_hz = writer.n_spikes / max(n * profile.height * profile.width, 1) / profile.interval_s
    impl = sim.implementation if sim.implementation != "torch" else f"torch on {sim.device}"
    say(f"wrote {args.out}: {n} intervals ({n * profile.interval_s:.4f} s of camera time), {profile.height}x"
        f"{profile.width}, model {args.model} ({impl}), seed {args.seed}; mean spike rate "
        f"{rate_hz:.1f} Hz per pixel; {dt:.1f} s wall")
    return 0


@contextlib.contextmanager
def _start_up(frozen: dict | None = None):
    """No cyclic garbage collection while the command starts: imports and numba's cache load make only
    long-lived objects, and the collector's passes over them slow the start-up.

    With a ``frozen`` dict they are then kept out of the run's collections too (``gc.freeze``, and
    ``frozen["frozen"]`` set; :func:`run` calls ``gc.unfreeze`` when it ends, so an in-process caller gets
    its collector back as it was), so the run's first collections, on the main thread between kernel
    blocks, do not scan them. The price: garbage the start-up made is freed only when the run ends.
    Nothing is frozen when the collector was off, or when the process froze objects itself.
    """
    import gc
    was = gc.isenabled()
    freeze = frozen is not None and was and gc.get_freeze_count() == 0
    gc.disable()
    try:
        yield
    finally:
        if freeze:
            gc.freeze()
            frozen["frozen"] = True
        if was:
            gc.enable()


def _lean_numba() -> None:
    """In the ``render2spike`` command only: numba's optional extras stay unloaded.

    When numba first loads a kernel it imports its NumPy support, which looks for SciPy's BLAS and for
    cffi, a sizeable part of the command's start-up; the spike kernels use neither. That support is
    imported here with both hidden, so numba records them as absent for this process. A program that
    imports the package, or has SciPy already, is left alone."""
    import importlib.abc

    import render2spike
    if not render2spike.cli_process() or "scipy" in sys.modules or "numba.np.arraymath" in sys.modules:
        return

    class _Hide(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path, target=None):
            if name.split(".")[0] in ("scipy", "cffi"):
                raise ImportError(f"{name} is not loaded by render2spike simulate")
            return None

    hide = _Hide()
    sys.meta_path.insert(0, hide)
    try:
        import numba.core.typing.cffi_utils  # noqa: F401
        import numba.np.arraymath  # noqa: F401
    except ImportError:  # no numba: the reference simulator runs
        pass
    finally:
        sys.meta_path.remove(hide)


def _prepare(args, say):
    """Open INPUT and the profile, make the simulator, start reading, load the kernels."""
    _lean_numba()
    from sensor.errors import InputError
    from sensor.io.stream import open_stream

    from render2spike.commands._common import check_output
    implementation = getattr(args, "implementation", None)
    if args.reference and implementation not in (None, "reference"):
        raise InputError(f"--reference and --implementation {implementation} disagree; give one of them",
                         field="--implementation")
    implementation = "reference" if args.reference else (implementation or "auto")
    check_output(args.out, inputs=[args.input], overwrite=args.overwrite, say=say)
    stream = open_stream(args.input, args.profile, args.model, args.seed, reset=getattr(args, "reset", None),
                         implementation=implementation, device=getattr(args, "device", None), say=say)
    if args.chunk is not None and args.chunk < 1:
        raise InputError(f"--chunk must be a positive number of keyframes, got {args.chunk}", field="--chunk")
    return stream.start(args.chunk)  # the reader thread starts, while numba loads the kernels
