"""Variant selection: CUDA when a GPU works, LLVM otherwise, the override wins; hashes keep CPU and GPU apart."""

import pytest

from render2spike.render import backend
from render2spike.render.backend import (FALLBACK_VARIANT, GPU_VARIANT, PREFERRED_VARIANT, choose_variant,
                                         variant_family)
from sensor.errors import DependencyError

ALL = {"scalar_spectral", "llvm_ad_spectral", "cuda_ad_spectral"}


def probe_with(ok: dict):
    calls = []

    def probe(v):
        calls.append(v)
        return ok.get(v, False), "" if ok.get(v) else f"{v} failed"
    return probe, calls


def test_gpu_chosen_when_present_and_working():
    probe, calls = probe_with({GPU_VARIANT: True, PREFERRED_VARIANT: True})
    assert choose_variant(None, ALL, True, probe) == (GPU_VARIANT, [])
    assert calls == [GPU_VARIANT]


def test_no_gpu_no_cuda_probe():
    probe, calls = probe_with({GPU_VARIANT: True, PREFERRED_VARIANT: True})
    assert choose_variant(None, ALL, False, probe) == (PREFERRED_VARIANT, [])
    assert calls == [PREFERRED_VARIANT]  # the GPU probe is never run without a device


def test_broken_gpu_falls_back_to_llvm_with_a_note():
    probe, calls = probe_with({PREFERRED_VARIANT: True})
    v, notes = choose_variant(None, ALL, True, probe)
    assert v == PREFERRED_VARIANT and calls == [GPU_VARIANT, PREFERRED_VARIANT]
    assert len(notes) == 1 and GPU_VARIANT in notes[0]


def test_build_without_cuda_variant_is_not_probed():
    probe, calls = probe_with({GPU_VARIANT: True, PREFERRED_VARIANT: True})
    assert choose_variant(None, ALL - {GPU_VARIANT}, True, probe)[0] == PREFERRED_VARIANT
    assert GPU_VARIANT not in calls


def test_nothing_works_scalar():
    probe, _ = probe_with({})
    v, notes = choose_variant(None, ALL, True, probe)
    assert v == FALLBACK_VARIANT and len(notes) == 2


def test_override_wins_and_is_checked():
    probe, calls = probe_with({GPU_VARIANT: True, PREFERRED_VARIANT: True})
    assert choose_variant(PREFERRED_VARIANT, ALL, True, probe)[0] == PREFERRED_VARIANT
    assert calls == [PREFERRED_VARIANT]
    assert choose_variant("scalar_spectral", ALL, True, probe)[0] == "scalar_spectral"
    probe, _ = probe_with({})
    with pytest.raises(DependencyError, match="NVIDIA"):
        choose_variant(GPU_VARIANT, ALL, False, probe)
    with pytest.raises(DependencyError, match="not available"):
        choose_variant("cuda_ad_rgb", ALL, False, probe)


def test_cuda_device_present_needs_a_device_node(monkeypatch):
    import glob
    monkeypatch.setattr(backend.sys, "platform", "linux")
    monkeypatch.setattr(glob, "glob", lambda pat: [])
    assert backend.cuda_device_present() is False
    monkeypatch.setattr(glob, "glob", lambda pat: ["/dev/nvidia0"])
    import ctypes.util
    monkeypatch.setattr(ctypes.util, "find_library", lambda name: "libcuda.so.1" if name == "cuda" else None)
    assert backend.cuda_device_present() is True


def test_scene_hash_separates_cpu_and_gpu_frames(write_scene):
    from render2spike.render.launch import settings_of
    from render2spike.render.scene import load_scene
    sc = load_scene(write_scene())
    assert variant_family(GPU_VARIANT) == "cuda" and variant_family(PREFERRED_VARIANT) == "llvm"
    hashes = {v: sc.content_hash(settings_of(sc, v)) for v in (GPU_VARIANT, PREFERRED_VARIANT, FALLBACK_VARIANT)}
    assert len(set(hashes.values())) == 3


def test_a_forced_variant_that_fails_says_what_to_use_instead():
    """The CUDA probe's Dr.Jit text tells its own API users to call jit_init: not passed on to ours."""
    def probe(v):
        return False, ("ImportError: jit_init_thread_state(): the CUDA backend hasn't been initialized. "
                       "Make sure to call jit_init(JitBackend::CUDA) to properly initialize this backend.")
    with pytest.raises(DependencyError) as err:
        choose_variant(GPU_VARIANT, ALL, False, probe)
    msg = str(err.value)
    assert "NVIDIA" in msg and "--variant auto" in msg and "jit_init(" not in msg


def test_a_forced_variant_does_not_stick(monkeypatch):
    """After a call that forced a variant, a call without one is back on the automatic choice."""
    pytest.importorskip("mitsuba")
    monkeypatch.delenv("RENDER2SPIKE_VARIANT", raising=False)
    auto = backend.mitsuba().variant()
    try:
        assert backend.mitsuba(FALLBACK_VARIANT).variant() == FALLBACK_VARIANT
        assert backend.mitsuba().variant() == auto
        monkeypatch.setenv("RENDER2SPIKE_VARIANT", FALLBACK_VARIANT)
        assert backend.mitsuba().variant() == FALLBACK_VARIANT      # the variable counts...
        assert backend.mitsuba(backend.AUTO).variant() == auto      # ...unless auto is asked for
        monkeypatch.setenv("RENDER2SPIKE_VARIANT", "auto")
        assert backend.mitsuba().variant() == auto                  # "auto" in the variable: the same
        with pytest.raises(DependencyError, match="spectral"):
            backend.mitsuba("scalar_rgb")
    finally:
        monkeypatch.delenv("RENDER2SPIKE_VARIANT", raising=False)
        backend.mitsuba()  # leave the process on the automatic choice for the tests after this one
