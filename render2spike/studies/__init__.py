"""Studies: questions answered with the whole chain (render -> spikes -> reconstruction).

* :mod:`.lux` -- reconstruction quality vs light level and noise model (``render2spike study lux``)
* :mod:`.motion` -- quality and blur width vs a scene parameter such as speed (``render2spike study motion``)
* :mod:`.generalisation` -- networks trained on one noise model, tested on every other
  (``render2spike study generalisation``)
* :mod:`.common` -- pre-rolled simulation, model specs, scoring with recon's method registry, statistics

Datasets for training live in :mod:`render2spike.dataset`.
"""

from .lux import (STUDY_METHODS, SweepJob, make_client, plan_lux_sweep, reference_lux_of, run_job, run_jobs,
                  summarise, write_study)

__all__ = ["STUDY_METHODS", "SweepJob", "make_client", "plan_lux_sweep", "reference_lux_of", "run_job", "run_jobs",
           "summarise", "write_study"]
