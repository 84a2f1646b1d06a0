"""Model specs: ``MODEL`` or ``MODEL:RESET`` (``elssim:crossing``), parsed and validated in one place."""

from __future__ import annotations

from dataclasses import dataclass

from sensor.errors import InputError, UnknownMethodError
from sensor.models.registry import MODELS
from sensor.profile import RESETS


@dataclass(frozen=True)
class ModelSpec:
    """A spike model: registry name plus the pixel reset (None: the profile's own)."""

    name: str
    reset: str | None = None

    @property
    def label(self) -> str:
        return self.name if self.reset is None else f"{self.name}:{self.reset}"

    def profile(self, profile):
        """``profile`` with this spec's reset applied (unchanged when the spec names none)."""
        return profile if self.reset is None else profile.replace(reset=self.reset)


def parse_model_spec(spec) -> ModelSpec:
    """``"elssim"`` -> ModelSpec("elssim"); ``"elssim:crossing"`` -> ModelSpec("elssim", "crossing").

    Unknown model or reset names raise :class:`UnknownMethodError` listing the valid choices.
    """
    if isinstance(spec, ModelSpec):
        return spec
    name, _, reset = str(spec).strip().partition(":")
    if name not in MODELS:
        raise UnknownMethodError("spike model", name, tuple(MODELS) + ("MODEL:RESET",))
    if reset and reset not in RESETS:
        raise UnknownMethodError("pixel reset", reset, RESETS)
    if reset and name == "ideal":
        raise InputError(f"'{spec}': the ideal model has no reset to choose (Algorithm 1 drops the charge at each "
                         "firing); give 'ideal'", field="model")
    return ModelSpec(name, reset or None)


def parse_models(text) -> list[ModelSpec]:
    """``"elssim:interval,elssim:crossing,isi,ideal"`` (or a sequence of specs) -> specs, in order."""
    items = [t.strip() if isinstance(t, str) else t
             for t in (text.split(",") if isinstance(text, str) else text)]
    items = [t for t in items if not isinstance(t, str) or t]
    if not items:
        raise InputError("no models given", field="--models")
    return [parse_model_spec(t) for t in items]
