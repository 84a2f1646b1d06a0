"""render2spike reconstruction stage: classic (TFP, TFI, dead-time-corrected TFP) and learned
(RSIR-architecture) methods, datasets, training and metrics. Never imports Mitsuba.

The numpy-only parts import here; the network (``recon.nets``), training (``recon.train``) and the
torch-facing pieces import PyTorch lazily. See ``docs/recon.md``.
"""

from .classic import (deadtime_correct, invert_renewal_rate, renewal_spike_rate, tfi, tfp, tfp_deadtime,
                      tfp_windows)

__all__ = ["tfp", "tfp_windows", "tfi", "tfp_deadtime", "deadtime_correct", "tfp_dt_denoised",
           "renewal_spike_rate", "invert_renewal_rate"]


def __getattr__(name):  # lazy, so `python -m recon.baselines` runs without a double import
    if name == "tfp_dt_denoised":
        from .baselines import tfp_dt_denoised
        return tfp_dt_denoised
    raise AttributeError(f"module 'recon' has no attribute '{name}'")
