"""The suite's default worker processes (tests/conftest.py ``pytest_cmdline_main``)."""

from types import SimpleNamespace

import pytest

from tests import conftest


class _Plugins:
    def __init__(self, xdist: bool):
        self.xdist = xdist

    def hasplugin(self, name):
        return self.xdist and name == "xdist"


def _config(xdist=True, worker=False, **opts):
    base = dict(numprocesses=None, dist="no", tx=[], usepdb=False, trace=False, capture="fd", collectonly=False)
    base.update(opts)
    cfg = SimpleNamespace(pluginmanager=_Plugins(xdist), option=SimpleNamespace(**base))
    if worker:
        cfg.workerinput = {"workerid": "gw0"}
    return cfg


@pytest.fixture(autouse=True)
def _many_cores(monkeypatch):
    """16 cores and no worker count in the environment, unless a test says otherwise: on a 1-core machine the hook
    would otherwise change nothing whatever it did."""
    monkeypatch.delenv("RENDER2SPIKE_TEST_WORKERS", raising=False)
    monkeypatch.setattr(conftest.os, "cpu_count", lambda: 16)


def test_the_suite_defaults_to_two_workers_a_file_each():
    cfg = _config()
    conftest.pytest_cmdline_main(cfg)
    assert (cfg.option.numprocesses, cfg.option.dist) == (conftest.TEST_WORKERS, "loadfile")


def test_one_core_runs_the_suite_in_this_process(monkeypatch):
    monkeypatch.setattr(conftest.os, "cpu_count", lambda: 1)
    cfg = _config()
    conftest.pytest_cmdline_main(cfg)
    assert (cfg.option.numprocesses, cfg.option.dist) == (None, "no")


@pytest.mark.parametrize("opts", [dict(numprocesses=0), dict(numprocesses=3, dist="load"), dict(usepdb=True),
                                  dict(trace=True), dict(capture="no"), dict(collectonly=True), dict(tx=["popen"])])
def test_what_the_command_line_asks_for_is_kept(opts):
    cfg = _config(**opts)
    conftest.pytest_cmdline_main(cfg)
    assert vars(cfg.option) == vars(_config(**opts).option)


@pytest.mark.parametrize("where", [dict(xdist=False), dict(worker=True)])
def test_without_xdist_or_in_a_worker_nothing_changes(where):
    cfg = _config(**where)
    conftest.pytest_cmdline_main(cfg)
    assert cfg.option.numprocesses is None and cfg.option.dist == "no"


@pytest.mark.parametrize("value, want", [("4", 4), ("0", None), ("1", None)])
def test_the_environment_sets_the_workers(monkeypatch, value, want):
    monkeypatch.setenv("RENDER2SPIKE_TEST_WORKERS", value)
    cfg = _config()
    conftest.pytest_cmdline_main(cfg)
    assert cfg.option.numprocesses == want


def test_a_bad_worker_count_says_what_it_wants(monkeypatch):
    monkeypatch.setenv("RENDER2SPIKE_TEST_WORKERS", "two")
    with pytest.raises(pytest.UsageError, match="RENDER2SPIKE_TEST_WORKERS='two': expected a whole number"):
        conftest.pytest_cmdline_main(_config())
