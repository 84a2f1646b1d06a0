"""Golden test: the README's main job on a small window gives the same frames and spikes, bit for bit.

The hashes in ``tests/golden/golden.json`` were recorded with ``python3 -m tests.golden.record``. They pin
the frames (Phi and E pixels, times, seeds) of ``render2spike run rotating_disk`` on a 16 x 24 window for
10 ms, its spikes (``.npz`` and ``.dat``), ``render2spike simulate`` of those frames with each other model,
reset and the reference simulator, and ``sensor.simulate`` of a fixed rate array. A change that is meant to
leave behaviour alone must leave every hash alone; a change of physics or sampling re-records them and says
why in its commit.
"""

import json
from pathlib import Path

import pytest

from tests.render.conftest import needs_mitsuba

GOLDEN = Path(__file__).parent / "golden" / "golden.json"


@pytest.fixture(autouse=True)
def _spikes_on_the_cpu(monkeypatch):
    """The hashes are of the numba kernels: on a machine with CUDA, ``auto`` would pick the torch implementation."""
    monkeypatch.setenv("RENDER2SPIKE_SPIKE_DEVICE", "cpu")


def _llvm_variant_works() -> bool:
    try:
        from render2spike.render.backend import find_libllvm, probe_variant
        from tests.golden.record import VARIANT
        return probe_variant(VARIANT, find_libllvm())[0]
    except ImportError:
        return False


@needs_mitsuba
@pytest.mark.render
def test_main_job_hashes_unchanged(tmp_path):
    from tests.golden.record import record
    if not _llvm_variant_works():
        pytest.skip("Mitsuba's LLVM variant does not run here (libLLVM 19 missing): the hashes are of its frames")
    want = json.loads(GOLDEN.read_text())
    got = record(tmp_path)
    assert got["run"]["frames"] == want["run"]["frames"], "rendered frames differ from the golden run"
    for key in sorted(want):
        assert got[key] == want[key], f"{key}: {got[key]} != golden {want[key]}"


def test_in_memory_simulation_hashes_unchanged():
    from tests.golden.record import in_memory_cases
    want = json.loads(GOLDEN.read_text())["in-memory"]
    assert in_memory_cases() == want
