"""Noise budget: fitted convergence, exact sample counts, one launch per frame, verification of the ratio."""

import math

import numpy as np
import pytest

from render2spike.render.noise import (BAND, Convergence, choose_spp_fit, exact_below, fit_convergence,
                                       verify_ratios)
from tests.render.conftest import needs_mitsuba


@pytest.mark.parametrize("a,b", [(3.0, 0.0), (0.0, 50.0), (2.0, 40.0)])
def test_fit_recovers_the_model_exactly(a, b):
    ns = [4, 16, 64]
    m = fit_convergence(ns, [a / n + b / n ** 2 for n in ns])
    for n in (4, 10, 100, 1000):
        assert math.isclose(m(n), a / n + b / n ** 2, rel_tol=1e-9)


@pytest.mark.parametrize("alpha", [1.2, 1.5, 1.8])
def test_fit_is_conservative_for_power_laws(alpha):
    """Between 1/n and 1/n^2 the A/n + B/n^2 fit over-estimates the variance beyond the pilots."""
    ns = [4, 16]
    m = fit_convergence(ns, [n ** -alpha for n in ns])
    for n in (32, 128, 1024):
        assert m(n) >= n ** -alpha
    # below the pilot the (n1/n)^2 growth is at least the power law's
    assert m(2) >= 2 ** -alpha and m(1) >= 1.0


def test_choose_spp_is_the_least_count_meeting_the_target():
    model = Convergence(2.0, 30.0, 4)
    r, W, K, target = 5.0, 64, 3.2, 0.2
    out = choose_spp_fit(np.full(10, r), model, W, K, target, 1, 4096)
    n = out["spp"]
    allowed = target ** 2 * K * r / W
    assert model(n) <= allowed < model(n - 1)
    assert out["predicted_ratio"] <= target and not out["clipped"]
    # a sampler that only takes even counts: rounded up to one
    assert choose_spp_fit(np.full(10, r), model, W, K, target, 1, 4096, exact=lambda k: k + k % 2)["spp"] % 2 == 0
    capped = choose_spp_fit(np.full(10, r), model, W, K, target, 1, n // 2)
    assert capped["clipped"] and capped["spp"] == n // 2 and capped["predicted_ratio"] > target


def test_exact_below():
    assert exact_below(lambda k: k + k % 2, 9) == 8
    assert exact_below(lambda k: k, 7) == 7


def test_verify_ratios_band_and_warnings():
    lo, hi = BAND[0] * 0.2, BAND[1] * 0.2
    ok, warn = verify_ratios([0.2, float("nan"), 0.21], 0.2, True)
    assert ok["n_verified"] == 2 and ok["in_band"] and warn is None
    _, warn = verify_ratios([hi * 1.1], 0.2, True, {"clipped": False})
    assert warn and "above" in warn
    assert verify_ratios([hi * 1.1], 0.2, True, {"clipped": True})[1] is None  # capped by max_spp: expected
    assert "below" in verify_ratios([lo * 0.9], 0.2, True, {"at_min_spp": False})[1]
    assert verify_ratios([lo * 0.9], 0.2, True, {"at_min_spp": True})[1] is None
    assert verify_ratios([hi * 2], 0.2, False)[1] is None  # a fixed spp is the user's choice


@needs_mitsuba
def test_frames_take_exactly_the_asked_samples_in_one_launch(write_scene, monkeypatch):
    from render2spike.render.renderer import SceneRenderer
    from render2spike.render.scene import load_scene
    r = SceneRenderer(load_scene(write_scene()))
    for spp in (1, 6, 16, 17, 64, 70, 130):
        counts = r.launch_counts(spp)
        assert sum(counts) == spp and all(r.effective_spp(n) == n for n in counts)
    assert r.launch_counts(64) == [64]
    calls = []
    orig = r.mi.render

    def counting(*a, **k):
        calls.append(k["spp"])
        return orig(*a, **k)
    monkeypatch.setattr(r.mi, "render", counting)
    f = r.render_frame(0.0, 0, 64, variance=False)
    assert calls == [64] and f["phi_var"] is None and f["spp"] == 64
    calls.clear()
    f = r.render_frame(0.0, 0, 64, variance=True)
    assert calls == [64, 64] and f["phi_var"].shape == f["phi"].shape
    # the frame is the first render: the same as without variance
    np.testing.assert_array_equal(f["phi"], r.render_frame(0.0, 0, 64, variance=False)["phi"])


def test_measured_model_interpolates_and_is_conservative_outside():
    from render2spike.render.noise import Measured
    ns = [4, 16, 64, 110]
    vs = [n ** -1.7 for n in ns]
    m = Measured(ns, vs)
    for n in ns:
        assert math.isclose(m(n), n ** -1.7, rel_tol=1e-12)
    assert math.isclose(m(32), 32 ** -1.7, rel_tol=1e-9)  # a power law between levels is exact
    assert m(2) >= 2 ** -1.7 and m(400) >= 400 ** -1.7  # outside: (n1/n)^2 below, 1/n above
    allowed = 50 ** -1.7
    assert abs(m.solve(allowed) - 50) < 1e-6
    # pair noise that makes v rise with n is flattened: V never increases
    m2 = Measured([4, 16, 64], [1.0, 0.1, 0.12])
    assert m2(64) <= m2(16)
