"""Shared test configuration.

* ``--runslow`` (or ``-m slow``) runs the slow tests: tighter statistical runs,
  bigger renders, longer training. The default run skips them.
* Every stochastic test uses a fixed seed; tolerances come from the statistics
  (binomial / Poisson standard errors at a stated number of sigmas).
"""

import os

import pytest

# z-score used for two-sided statistical tolerances: P(false failure) ~ 1e-4 per check
Z = 3.9


def pytest_addoption(parser):
    parser.addoption("--runslow", action="store_true", default=False, help="run tests marked slow")


def pytest_configure(config):
    if config.getoption("--runslow"):
        # override the default "-m 'not slow'" from pyproject
        config.option.markexpr = ""


@pytest.fixture
def z():
    """Two-sided z-score for statistical tolerances."""
    return Z


@pytest.fixture
def slow_scale(request):
    """1 in the default run, larger with --runslow (more samples -> tighter checks)."""
    return 8 if request.config.getoption("--runslow") else 1


@pytest.fixture(autouse=True)
def _no_display(monkeypatch):
    monkeypatch.setenv("MPLBACKEND", "Agg")
    os.environ.setdefault("MPLBACKEND", "Agg")
