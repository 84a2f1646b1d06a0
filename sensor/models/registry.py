"""The model registry: every spike model by name, its reference, fast and torch implementations.

``get_model(name, profile, implementation)`` picks the class. The reference classes
(:mod:`sensor.models.step`) define the models; the fast ones (:mod:`sensor.models.fast`, numba on the
CPU) and the torch ones (:mod:`sensor.models.torch_models`, PyTorch on a GPU or the CPU) are listed here
and imported on first use, so that ``import sensor`` loads neither numba nor torch. ``auto`` (the
default) is ``torch`` on a CUDA device when one works, else ``fast``. No implementation module imports
this one.
"""

from __future__ import annotations

from sensor.errors import UnknownMethodError
from sensor.models.step import ELSSimCrossingStep, ELSSimStep, IdealModel, ISIModel, SpikeModel
from sensor.profile import SensorProfile

#: the reference implementation of each model, for profiles with the ``interval`` reset (and for models
#: with one pixel, whatever the reset)
REFERENCE = {"ideal": IdealModel, "elssim": ELSSimStep, "isi": ISIModel}
#: models whose pixel follows the profile's ``reset``: the class per reset (the ``REFERENCE`` one is "interval")
REFERENCE_BY_RESET = {("elssim", "crossing"): ELSSimCrossingStep}
#: (model, reset) -> name of the fast class in :mod:`sensor.models.fast`
FAST = {("elssim", "interval"): "ELSSimFast", ("elssim", "crossing"): "ELSSimCrossingFast",
        ("ideal", "interval"): "IdealFast", ("isi", "interval"): "ISIFast"}

#: (model, reset) -> name of the torch class in :mod:`sensor.models.torch_models` (``isi`` has none: ``fast``)
TORCH = {("elssim", "interval"): "ELSSimTorch", ("elssim", "crossing"): "ELSSimCrossingTorch",
         ("ideal", "interval"): "IdealTorch"}

MODELS = tuple(REFERENCE)
IMPLEMENTATIONS = ("auto", "fast", "reference", "torch")


def fast_implementations() -> dict:
    """(model, reset) -> fast class; empty when the fast kernels are unavailable (no numba)."""
    try:
        from sensor.models import fast
    except ImportError:
        return {}
    if not fast.HAVE_NUMBA:
        return {}
    return {key: getattr(fast, cls) for key, cls in FAST.items()}


def auto_implementation(device: str | None = None) -> str:
    """What ``auto`` means here: ``torch`` when the spike device (``device``, else
    ``$RENDER2SPIKE_SPIKE_DEVICE``, else auto-detected) is a working CUDA device, else ``fast``.

    Without an NVIDIA driver this imports neither torch nor numba; a bad device name raises InputError.
    """
    from sensor.models.torch_models import spike_device
    return "fast" if spike_device(device) == "cpu" else "torch"


def _key(name: str, profile: SensorProfile):
    return (name, profile.reset) if (name, profile.reset) in REFERENCE_BY_RESET else (name, "interval")


def resolve_implementation(name: str, profile: SensorProfile, implementation: str = "auto",
                           device: str | None = None) -> str:
    """The implementation :func:`get_model` gives for these arguments (``auto`` resolved; ``torch`` is
    ``fast`` for a model without a torch class; ``fast`` is ``reference`` without numba)."""
    if implementation not in IMPLEMENTATIONS:
        raise UnknownMethodError("implementation", implementation, IMPLEMENTATIONS)
    if implementation == "auto":
        implementation = auto_implementation(device)
    key = _key(name, profile)
    if implementation == "torch" and key not in TORCH:
        implementation = "fast"
    if implementation == "fast" and key not in fast_implementations():
        implementation = "reference"
    return implementation


def get_model(name: str, profile: SensorProfile, implementation: str = "auto", device: str | None = None) -> SpikeModel:
    """Instantiate model ``name`` with ``implementation``.

    ``auto``: ``torch`` on a working CUDA device, else ``fast`` (:func:`auto_implementation`); ``torch`` runs
    on ``device`` (``cpu``, ``cuda``, ``cuda:N``; default: ``$RENDER2SPIKE_SPIKE_DEVICE``, else CUDA when it
    works) and is ``fast`` for ``isi``, which has no torch class; ``fast`` falls back to ``reference`` when
    none exists. The model's ``implementation`` attribute says which one was made.

    ``elssim`` follows ``profile.reset`` (``interval``: Algorithm 2; ``crossing``: the
    continuous-time pixel); ``ideal`` and ``isi`` have one pixel each and ignore it.
    """
    if name not in REFERENCE:
        raise UnknownMethodError("spike model", name, REFERENCE)
    implementation = resolve_implementation(name, profile, implementation, device)
    key = _key(name, profile)
    if implementation == "torch":
        from sensor.models import torch_models
        return getattr(torch_models, TORCH[key])(profile, device=device)
    if implementation == "fast":
        return fast_implementations()[key](profile)
    return REFERENCE_BY_RESET.get(key, REFERENCE[name])(profile)
