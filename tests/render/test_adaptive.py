"""Adaptive temporal sampling: fewer keyframes when static, interpolation error under the tolerance."""

import numpy as np
import pytest

from render2spike.render.sampling import TimeGrid, adaptive_ticks, change_metric, interpolate, interpolation_metric
from tests.render.conftest import needs_mitsuba


def test_time_grid_is_dyadic_and_exact():
    g = TimeGrid.make(0.01, 1000.0, 4000.0)
    assert (g.n_base, g.levels, g.step) == (10, 2, 4)
    assert g.time(0) == 0.0 and g.time(g.n_ticks) == 0.01
    assert g.base_ticks() == list(range(0, 41, 4))


def _window_error(interp, truth, W, D):
    """The criterion's measure of an actual midpoint error: (2/3) |e| min(W, D) / sqrt(W r), max over pixels."""
    e = np.abs(np.asarray(interp) - truth)
    return float(np.max((2 / 3) * e * min(W, D) / np.sqrt(W * np.maximum(truth, 1 / W))))


def test_adaptive_ticks_synthetic_edge():
    """A 1-D edge moving at 3 px per base interval: refined until the window error is small; static or linear: not."""
    g = TimeGrid.make(1.0, 10.0, 160.0)  # 10 base intervals, 4 halvings
    interval_s = 0.1 / 20  # 20 sensor intervals per base interval, as at 1 kHz keyframes
    W = 64
    x = np.arange(64) + 0.5

    def frame(tick, speed):
        pos = 10 + speed * g.time(tick)
        return 5.0 + 40.0 * np.clip(x - pos + 0.5, 0, 1)  # box-filtered step, e-/interval

    metric = interpolation_metric(0.0, 1.0, W, interval_s)
    tol = 0.25
    static = adaptive_ticks(g, lambda k: frame(k, 0.0), metric, tol)
    moving = adaptive_ticks(g, lambda k: frame(k, 30.0), metric, tol)
    # a brightness ramp, linear in time: interpolation is exact, nothing to refine
    ramp = adaptive_ticks(g, lambda k: 5.0 + 30.0 * g.time(k) + 0 * x, metric, tol)
    assert len(static) == g.n_base + 1 and len(ramp) == g.n_base + 1
    assert len(moving) > len(static)
    frames = [frame(k, 30.0) for k in moving]
    times = [g.time(k) for k in moving]
    for a, b in zip(moving[:-1], moving[1:]):
        if b - a < 2:
            continue  # the finest spacing: nothing more the sampler could do
        tm = 0.5 * (g.time(a) + g.time(b))
        truth = 5.0 + 40.0 * np.clip(x - (10 + 30.0 * tm) + 0.5, 0, 1)
        D = (g.time(b) - g.time(a)) / interval_s
        # the estimate |D2| / 4 is exact for a kink midway and at most 2x low at the midpoint of a segment
        # holding one kink (an edge entering or leaving a pixel), hence the factor 2
        assert _window_error(interpolate(times, frames, tm), truth, W, D) <= 2 * tol


def test_metric_ignores_render_noise():
    rng = np.random.default_rng(0)
    var = 4.0  # (e-/interval)^2 per keyframe
    f = [10.0 + rng.normal(0, 2.0, 5000) for _ in range(3)]
    m = interpolation_metric(var, 1.0, 64, 50e-6, z=4.0)
    # d > 0.25 needs e > 0.25 sqrt(64 * 10) / ((2/3) * 20) = 0.47, i.e. |D2| > 4 sigma + 1.9 = 4.39 sigma
    # (sigma = sqrt(6) * 2): probability 1.1e-5 per pixel, 0.06 for the 5000 pixels (fixed seed)
    assert m(*f, 1e-3) < 0.25
    # a real curvature of 8 sigma in one pixel is seen
    f[1][17] -= 8 * np.sqrt(6) * 2.0
    assert m(*f, 1e-3) > 0.25


@pytest.mark.render
@needs_mitsuba
def test_adaptive_render_static_vs_moving(tmp_path, write_scene):
    from render2spike.render.job import render_scene
    from render2spike.render.renderer import SceneRenderer
    from render2spike.render.scene import load_scene
    from sensor.io.frames import read_frames

    tol = 0.3
    objs = lambda v: [  # noqa: E731
        {"name": "back", "shape": "rectangle", "size": [10, 10], "position": [0, 0, -0.5],
         "material": {"reflectance": 0.1}},
        {"name": "tag", "shape": "rectangle", "size": [0.02, 0.02], "position": [-0.01, 0, 0],
         "material": {"reflectance": 0.8},
         "motion": {"parametric": [{"translate": {"velocity_m_s": [v, 0, 0]}}]}}]
    common = {"duration_s": 0.02, "reference": {"point": [0, 0, 0.05], "normal": [0, 0, 1]},
              "render": {"keyframe_rate_hz": 200, "max_depth": 2, "spp": 16,
                         "adaptive": {"enabled": True, "tolerance": tol, "max_rate_hz": 3200}}}
    counts = {}
    for name, v in (("static", 0.0), ("moving", 0.5)):  # 0.5 m/s = 200 px/s = 1 px per 200 Hz base interval
        sc = load_scene(write_scene(dict(common, objects=objs(v)), name=f"{name}.yaml"))
        res = render_scene(sc, tmp_path / name, progress=False, log=lambda *a: None)
        counts[name] = res.n_frames
    assert counts["static"] == 5  # the 200 Hz base grid over 20 ms
    assert counts["moving"] > counts["static"]
    # interpolation error at midpoints of the moving keyframes, against fresh high-spp renders
    sc = load_scene(tmp_path / "moving.yaml")
    seq = read_frames(tmp_path / "moving")
    times = seq.times_s
    frames = [seq.read(i).phi for i in range(len(seq))]
    r = SceneRenderer(sc)
    rng = np.random.Generator(np.random.PCG64(7))
    for i in rng.choice(len(times) - 1, size=4, replace=False):
        tm = 0.5 * (times[i] + times[i + 1])
        truth = r.render_frame(tm, 99, 64)
        interp = interpolate(times, frames, tm)
        # noise floor: keyframes at 16 spp; use the truth's own per-pixel variance x (1 + 64/16) as their sum
        var = truth["phi_var"] * (1 + 64 / 16)
        assert change_metric(interp, truth["phi"], var, np.zeros_like(var), z=4.0) <= tol
