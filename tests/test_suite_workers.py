"""The suite's default worker processes (tests/conftest.py ``pytest_cmdline_main``)."""

from types import SimpleNamespace

import pytest

from tests import conftest


class _Plugins:
    def __init__(self, xdist: bool):
        self.xdist = xdist

    def hasplugin(self, name):
        return self.xdist and name == "xdist"


def _config(xdist=True, **opts):
    base = dict(numprocesses=None, dist="no", tx=[], usepdb=False, collectonly=False)
    base.update(opts)
    return SimpleNamespace(pluginmanager=_Plugins(xdist), option=SimpleNamespace(**base))


def test_the_suite_defaults_to_two_workers_a_file_each(monkeypatch):
    monkeypatch.delenv("RENDER2SPIKE_TEST_WORKERS", raising=False)
    monkeypatch.setattr(conftest.os, "cpu_count", lambda: 16)
    cfg = _config()
    conftest.pytest_cmdline_main(cfg)
    assert (cfg.option.numprocesses, cfg.option.dist) == (conftest.TEST_WORKERS, "loadfile")


def test_one_core_runs_the_suite_in_this_process(monkeypatch):
    monkeypatch.delenv("RENDER2SPIKE_TEST_WORKERS", raising=False)
    monkeypatch.setattr(conftest.os, "cpu_count", lambda: 1)
    cfg = _config()
    conftest.pytest_cmdline_main(cfg)
    assert (cfg.option.numprocesses, cfg.option.dist) == (None, "no")


@pytest.mark.parametrize("opts", [dict(numprocesses=0), dict(numprocesses=3, dist="load"), dict(usepdb=True),
                                  dict(collectonly=True), dict(tx=["popen"])])
def test_what_the_command_line_asks_for_is_kept(monkeypatch, opts):
    monkeypatch.delenv("RENDER2SPIKE_TEST_WORKERS", raising=False)
    cfg = _config(**opts)
    conftest.pytest_cmdline_main(cfg)
    assert vars(cfg.option) == vars(_config(**opts).option)


def test_without_xdist_nothing_changes(monkeypatch):
    monkeypatch.delenv("RENDER2SPIKE_TEST_WORKERS", raising=False)
    cfg = _config(xdist=False)
    conftest.pytest_cmdline_main(cfg)
    assert cfg.option.numprocesses is None


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
