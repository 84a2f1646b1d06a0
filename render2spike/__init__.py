"""render2spike: physically based rendering-to-spike-camera simulation.

Stages (data flows one way): ``render2spike`` (scenes, Mitsuba rendering,
photometry, CLI, pipelines, studies) -> ``sensor`` (spike models, profiles,
calibration, spike files) -> ``recon`` (reconstruction, datasets, training,
metrics).
"""

from sensor.fileio import package_version as _pv

__version__ = _pv()
