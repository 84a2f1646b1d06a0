"""render2spike reconstruction stage: classic (TFP, TFI) and learned (RSIR-architecture) methods,
datasets, training and metrics. Never imports Mitsuba."""

from .classic import tfp

__all__ = ["tfp"]
