"""The model registry: every spike model by name, its reference and fast implementations.

``get_model(name, profile, implementation)`` picks the class. The reference classes
(:mod:`sensor.models.step`) define the models; the fast ones (:mod:`sensor.models.fast`)
are listed here and imported on first use, so that ``import sensor`` does not load numba.
Neither implementation module imports this one.
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

MODELS = tuple(REFERENCE)
IMPLEMENTATIONS = ("fast", "reference")


def fast_implementations() -> dict:
    """(model, reset) -> fast class; empty when the fast kernels are unavailable (no numba)."""
    try:
        from sensor.models import fast
    except ImportError:
        return {}
    if not fast.HAVE_NUMBA:
        return {}
    return {key: getattr(fast, cls) for key, cls in FAST.items()}


def get_model(name: str, profile: SensorProfile, implementation: str = "fast") -> SpikeModel:
    """Instantiate model ``name`` with ``implementation`` ('fast' falls back to 'reference' when none exists).

    ``elssim`` follows ``profile.reset`` (``interval``: Algorithm 2; ``crossing``: the
    continuous-time pixel); ``ideal`` and ``isi`` have one pixel each and ignore it.
    """
    if name not in REFERENCE:
        raise UnknownMethodError("spike model", name, REFERENCE)
    if implementation not in IMPLEMENTATIONS:
        raise UnknownMethodError("implementation", implementation, IMPLEMENTATIONS)
    key = (name, profile.reset) if (name, profile.reset) in REFERENCE_BY_RESET else (name, "interval")
    if implementation == "fast":
        fast = fast_implementations()
        if key in fast:
            return fast[key](profile)
    return REFERENCE_BY_RESET.get(key, REFERENCE[name])(profile)
