"""Static-region reuse (render2spike.render.reuse): where it applies, the coverage test, the pixel-list launch,
and a render job whose frames reuse one static frame."""

import json

import numpy as np
import pytest
from scipy.ndimage import uniform_filter

from tests.render.conftest import BASE, needs_mitsuba

pytestmark = [needs_mitsuba, pytest.mark.render]

#: a cube sliding over a plane under a slanted sun: it moves, and so does its shadow
MOVER = {"name": "box", "shape": "cube", "size": [0.02, 0.02, 0.02], "position": [-0.02, 0, 0.02],
         "material": {"reflectance": 0.8},
         "motion": {"parametric": [{"translate": {"velocity_m_s": [4.0, 0, 0]}, "start_s": 0.0}]}}
SUN = [{"name": "sun", "type": "directional", "direction": [-0.6, 0, -1], "strength": 1.0,
        "spectrum": {"blackbody_k": 5000}}]


def _scene(write_scene, **changes):
    from render2spike.render.scene import load_scene
    d = {"objects": BASE["objects"] + [MOVER], "lights": SUN}
    d.update(changes)
    return load_scene(write_scene(d))


def test_reuse_applies_only_to_a_still_camera_with_movers_on_the_frozen_launch(write_scene):
    from render2spike.render.reuse import reuse_obstacle
    moving = _scene(write_scene)
    assert reuse_obstacle(moving, "frozen") is None
    assert "film launch" in reuse_obstacle(moving, "film")
    still = _scene(write_scene, objects=BASE["objects"])
    assert reuse_obstacle(still, "frozen") is None  # every keyframe is the static frame
    cam = dict(BASE["camera"], motion={"parametric": [{"translate": {"velocity_m_s": [0.1, 0, 0]}}]})
    assert "camera moves" in reuse_obstacle(_scene(write_scene, camera=cam), "frozen")
    off = _scene(write_scene, render=dict(BASE["render"], static_reuse=False))
    assert "static_reuse is false" in reuse_obstacle(off, "frozen")
    glow = dict(MOVER, emitter={"strength": 1.0})
    assert "emits light" in reuse_obstacle(_scene(write_scene, objects=BASE["objects"] + [glow]), "frozen")
    panel = {"name": "panel", "shape": "rectangle", "size": [0.05, 0.05], "position": [0.1, 0, 0.5],
             "emitter": {"strength": 1.0}}
    assert "area light" in reuse_obstacle(_scene(write_scene, objects=BASE["objects"] + [MOVER, panel]), "frozen")


def test_the_frames_hash_says_whether_a_static_frame_is_reused(write_scene):
    from render2spike.render.launch import settings_of
    from render2spike.render.reuse import REUSE_VERSION
    assert settings_of(_scene(write_scene), "llvm_ad_spectral", "frozen").get("static_reuse") == REUSE_VERSION
    off = _scene(write_scene, render=dict(BASE["render"], static_reuse=False))
    assert "static_reuse" not in settings_of(off, "llvm_ad_spectral", "frozen")


def test_everything_that_changes_between_two_times_is_inside_the_coverage(write_scene):
    """Pixels whose irradiance changes between t0 and t1 by more than 5 sigma (the cube, and its shadow on the
    plane) must all be dynamic at t0 or t1; the far plane must be static. Without the shadow rays the shadow's
    pixels would be outside the coverage and this fails."""
    from render2spike.render.renderer import SceneRenderer
    from render2spike.render.reuse import Coverage
    r = SceneRenderer(_scene(write_scene), launch="frozen")
    cov = Coverage(r)
    t0, t1 = 0.0, 0.004
    c0, c1 = cov(t0), cov(t1)
    assert 0.01 < c0.mean() < 0.5 and not np.array_equal(c0, c1)
    fa, fb = (r.render_frame(t, 1, 256, variance=True) for t in (t0, t1))
    # the variance of the difference, each pixel's pair estimate (one degree of freedom) pooled over 5 x 5
    z = (fa["phi"] - fb["phi"]) / np.sqrt(uniform_filter(fa["phi_var"] + fb["phi_var"], size=5, mode="nearest"))
    assert (np.abs(z) > 5.5).sum() > 10  # the cube and its shadow did move
    out = ~(c0 | c1)
    # outside the coverage the difference is render noise: no pixel beyond 5.5 sigma (1e-4 expected of a normal
    # over these ~1,300 pixels), and no systematic change (the mean z within 4.5 standard errors of 0)
    assert not np.any(np.abs(z[out]) > 5.5), np.argwhere((np.abs(z) > 5.5) & out)[:5]
    assert abs(z[out].mean()) < 4.5 / np.sqrt(out.sum()), z[out].mean()


def test_a_pixel_list_launch_estimates_what_the_whole_frame_launch_does(write_scene):
    """Same pixels, independent seeds: the image means agree within 4.5 standard errors, and the per-pixel
    variances (pairs of renders) agree within the spread of a mean of n chi-square(1) ratios."""
    from render2spike.render.renderer import SceneRenderer
    r = SceneRenderer(_scene(write_scene), launch="frozen")
    pix = np.flatnonzero(np.arange(32 * 48) % 3 == 0)
    full = [r.render_exact(0.001, [s], 16)[0].ravel()[pix] for s in (3, 4)]
    part = [r.render_pixels(0.001, [s], 16, pix)[0] for s in (5, 6)]
    va = (full[0] - full[1]) ** 2 / 2
    vb = (part[0] - part[1]) ** 2 / 2
    n = pix.size
    sd = np.sqrt((va.sum() + vb.sum()) / n ** 2)
    z = (0.5 * (full[0] + full[1]).mean() - 0.5 * (part[0] + part[1]).mean()) / (sd / np.sqrt(2))
    assert abs(z) < 4.5, z
    # the log of the ratio of the two mean variances, against its standard error from the pixels' own spread
    # (delta method: relative standard error of each mean = std / (mean sqrt(n))); 4.5 of them
    se = np.sqrt((va.std(ddof=1) / va.mean()) ** 2 / n + (vb.std(ddof=1) / vb.mean()) ** 2 / n)
    assert abs(np.log(va.mean() / vb.mean())) < 4.5 * se, (va.mean(), vb.mean(), se)


def test_a_pixel_list_takes_a_recorded_length_within_the_slack_and_its_values_do_not_depend_on_it(write_scene):
    """The padded length serves the recording only: a pixel's values are the same whichever length the list is
    padded to; a list reuses a length recorded at its spp when at most PIXEL_SLACK longer, else its own."""
    from render2spike.render.frozen import PIXEL_SLACK, max_padded_pixels, padded_pixels
    from render2spike.render.renderer import SceneRenderer
    r = SceneRenderer(_scene(write_scene), launch="frozen")
    r.set_time(0.001)
    fl = r.frame_launch
    pix = np.arange(40, 40 + 700)
    own = fl.pixel_values(fl.launch_pixels(9, 16, r._cam_m, pix))["Phi"]
    assert fl.pixel_length(700, 16) == padded_pixels(700) == 704
    longer = np.arange(40, 40 + 760)  # a second length at 16 spp: room for growth, 760 * 1.125 -> 832
    fl.pixel_values(fl.launch_pixels(9, 16, r._cam_m, longer))
    assert fl.pixel_length(700, 16) == 704 and fl.pixel_length(690, 16) == 704  # the shortest that fits
    assert fl.pixel_length(760, 16) == 832 == max_padded_pixels(760) <= 760 * (1 + PIXEL_SLACK)
    assert fl.pixel_length(750, 16) == 832  # a recorded one, not padded_pixels' 768
    assert fl.pixel_length(600, 16) == max_padded_pixels(600) == 672  # 704 would be more than the slack longer
    assert fl.pixel_length(720, 4) == padded_pixels(720)  # lengths are per spp; the first one is tight
    again = fl.pixel_values(fl.launch_pixels(9, 16, r._cam_m, np.arange(40, 40 + 750)))["Phi"]
    assert np.array_equal(again[:700], own)  # padded to 832 this time: the same values


def test_a_render_reuses_one_static_frame_and_checks_it(tmp_path, write_scene):
    from render2spike.render.job import render_scene
    from sensor.io.frames import read_frames
    scene = _scene(write_scene, duration_s=0.008, render=dict(BASE["render"], keyframe_rate_hz=1000,
                                                              adaptive={"enabled": False}))
    res = render_scene(scene, tmp_path / "f", progress=False, log=lambda *a: None)
    man = res.manifest
    sr = man["static_reuse"]
    assert sr["applied"] and 0.01 < sr["dynamic_fraction"]["mean"] < 0.6
    assert sr["static_check"] and all(c["z2_mean"] < c["limit"] for c in sr["static_check"])
    assert man["noise_budget"]["static"]["spp"] >= 1
    seq = read_frames(tmp_path / "f")
    phi = np.stack([seq.read_phi(i) for i in range(len(seq))])
    same = np.all(phi == phi[:1], axis=0)  # pixels equal in every keyframe: the static frame's
    assert 0.3 < same.mean() < 0.99
    assert json.loads((tmp_path / "f" / "frames.json").read_text())["static_reuse"]["applied"]


def test_the_ratio_with_a_per_pixel_k_is_the_scalar_one_when_k_is_uniform():
    from render2spike.render.noise import render_noise_ratio
    rng = np.random.default_rng(0)
    r, v = rng.uniform(10, 20, (8, 8)), rng.uniform(0.1, 1, (8, 8))
    a = render_noise_ratio(r, v, 64, 3.2, 5.0)
    b = render_noise_ratio(r, v, 64, np.full((8, 8), 3.2), 5.0)
    assert b == pytest.approx(a, rel=1e-12)
    c = render_noise_ratio(r, v, 64, np.where(np.arange(64).reshape(8, 8) < 32, 3.2, 1.0), 5.0)
    assert c > a  # static pixels carry their error into every keyframe: K = 1


def test_refined_keyframes_are_rendered_at_their_levels_spp(tmp_path, write_scene):
    """An unclipped budget with refinement: each level's spp is at most the level above's, a refined keyframe's
    header carries its level's spp, and a base keyframe the base spp."""
    from render2spike.render.job import render_scene
    from render2spike.render.sampling import TimeGrid, tick_level
    from sensor.io.frames import read_frames
    render = dict(BASE["render"], keyframe_rate_hz=1000, noise={"target_ratio": 0.4},
                  adaptive={"enabled": True, "tolerance": 0.02, "max_rate_hz": 4000})
    scene = _scene(write_scene, duration_s=0.004, render=render)
    res = render_scene(scene, tmp_path / "f", progress=False, log=lambda *a: None)
    man = res.manifest
    levels = man["spp_by_level"]
    assert len(levels) == 3 and not man["noise_budget"]["clipped"]
    assert levels == sorted(levels, reverse=True) and levels[1] < levels[0]
    assert man["temporal_sampling"]["n_refined"] > 0
    grid = TimeGrid.make(scene.duration_s, 1000, 4000)
    seq = read_frames(tmp_path / "f")
    seen = set()
    for i in range(len(seq)):
        fr = seq.read(i)
        tick = int(round(fr.time_s / scene.duration_s * grid.n_ticks))
        lv = tick_level(grid, tick)
        seen.add(lv)
        assert int(fr.header["spp"]) == levels[lv], (tick, lv)
    assert {0, 1} <= seen


def test_a_mover_that_enters_the_view_later_is_budgeted_on_the_whole_frame(tmp_path, write_scene):
    from render2spike.render.job import render_scene
    late = dict(MOVER, position=[-0.2, 0, 0.02],
                motion={"parametric": [{"translate": {"velocity_m_s": [40.0, 0, 0]}, "start_s": 0.0}]})
    scene = _scene(write_scene, objects=BASE["objects"] + [late], duration_s=0.01,
                   render=dict(BASE["render"], keyframe_rate_hz=400, adaptive={"enabled": False}))
    res = render_scene(scene, tmp_path / "f", progress=False, log=lambda *a: None)
    sr = res.manifest["static_reuse"]
    assert sr["applied"] and sr["dynamic_fraction"]["t0"] == 0.0 and sr["dynamic_fraction"]["max"] > 0.0
    assert np.isfinite(res.manifest["noise_budget"]["predicted_ratio"]) and res.spp >= 1
    assert all(c["z2_mean"] < c["limit"] for c in sr["static_check"])


def _killed_after_two_and_resumed(scene, out, monkeypatch):
    """Render ``scene`` into ``out``, killed after two keyframes, then resumed; -> the resumed render's result."""
    from render2spike.render import reuse as reuse_mod
    from render2spike.render.job import render_scene
    orig, calls = reuse_mod.render_frame_reused, {"n": 0}

    def killed(*args, **kw):
        calls["n"] += 1
        if calls["n"] > 2:
            raise KeyboardInterrupt
        return orig(*args, **kw)

    monkeypatch.setattr(reuse_mod, "render_frame_reused", killed)
    with pytest.raises(KeyboardInterrupt):
        render_scene(scene, out, progress=False, log=lambda *a: None)
    monkeypatch.setattr(reuse_mod, "render_frame_reused", orig)
    res = render_scene(scene, out, progress=False, log=lambda *a: None)
    return res


def test_a_killed_and_resumed_render_with_reuse_writes_the_same_frames(tmp_path, write_scene, monkeypatch):
    """The static frame is made again from the render seed on resume: the frames of a render killed after two
    keyframes and resumed are byte for byte those of an uninterrupted one."""
    from render2spike.render.job import render_scene
    from tests.render.test_reproducible import _assert_same_frames
    scene = _scene(write_scene, duration_s=0.006, render=dict(BASE["render"], keyframe_rate_hz=1000,
                                                              adaptive={"enabled": False},
                                                              noise={"max_spp": 16}))  # a cheap budget
    whole = render_scene(scene, tmp_path / "a", progress=False, log=lambda *a: None)
    assert whole.manifest["static_reuse"]["applied"]
    assert whole.manifest["static_reuse"]["static_source"] == "pilot"  # made again from the pilot's seeds
    res = _killed_after_two_and_resumed(scene, tmp_path / "b", monkeypatch)
    assert res.n_rendered == res.n_frames - 2
    _assert_same_frames(tmp_path / "a", tmp_path / "b")


def test_the_static_frame_is_the_pilots_pair_when_that_meets_its_budget(tmp_path, write_scene, monkeypatch):
    """The noise pilot renders pairs of the whole frame at t = 0; its pair at its highest count is the static frame
    when its measured ratio is not above the band: nothing is rendered for it (no launch, no kernel of its own)."""
    from render2spike.render import reuse as reuse_mod
    from render2spike.render.job import render_scene
    made = []
    orig = reuse_mod.StaticFrame.__init__

    def counted(self, rnd, spp, seeds, valid, renders=None):
        made.append(renders is None)
        orig(self, rnd, spp, seeds, valid, renders)
    monkeypatch.setattr(reuse_mod.StaticFrame, "__init__", counted)
    scene = _scene(write_scene, duration_s=0.003, render=dict(BASE["render"], keyframe_rate_hz=1000,
                                                              adaptive={"enabled": False}, noise={"max_spp": 16}))
    res = render_scene(scene, tmp_path / "f", progress=False, log=lambda *a: None)
    sr, budget = res.manifest["static_reuse"], res.manifest["noise_budget"]
    assert made == [False] and sr["static_source"] == "pilot"
    assert sr["static_spp"] == max(budget["pilot"]["spp"])
    (m,) = sr["static_measured"]
    assert m["source"] == "pilot" and m["ratio"] <= 1.1 * 0.2
    assert len(sr["static_seeds"]) == 2  # the pair's (a resumed render makes it again from them)
    from render2spike.render.job import spp_text
    assert spp_text(res.manifest, res.spp).endswith(f"one static frame at {sr['static_spp']} spp (the noise pilot's pair)")


def test_a_static_frame_that_misses_the_band_is_rendered_again_and_resumes_as_kept(tmp_path, write_scene,
                                                                                     monkeypatch):
    """Without the pilot's pairs (which would be the static frame), a static count far below the need (1 spp,
    forced): its own pair measures it above the band, so the frame is
    rendered again at more samples until its ratio is in the band; the attempts are in the manifest, and a render
    killed after two keyframes and resumed makes the same static frame (its count and attempt kept in the state),
    so the same frames."""
    from render2spike.render import reuse as reuse_mod
    from render2spike.render.job import render_scene
    from render2spike.render.noise import BAND
    from tests.render.test_reproducible import _assert_same_frames
    orig_spp = reuse_mod.static_spp

    def too_few(*args, **kw):
        return dict(orig_spp(*args, **kw), spp=1)

    monkeypatch.setattr(reuse_mod, "static_spp", too_few)
    import render2spike.render.job as job_mod
    orig_pilot = job_mod.pilot_budget
    monkeypatch.setattr(job_mod, "pilot_budget", lambda *a, **kw: orig_pilot(*a, **dict(kw, keep_raw=None)))
    scene = _scene(write_scene, duration_s=0.004, render=dict(BASE["render"], keyframe_rate_hz=1000,
                                                              adaptive={"enabled": False},
                                                              noise={"max_spp": 16}))  # static frame <= 128 spp
    whole = render_scene(scene, tmp_path / "a", progress=False, log=lambda *a: None)
    sr = whole.manifest["static_reuse"]
    tried = sr["static_measured"]
    assert len(tried) >= 2 and tried[0]["spp"] == 1 and tried[0]["ratio"] > BAND[1] * 0.2
    kept = next(t for t in tried if t["spp"] == sr["static_spp"])
    assert BAND[0] * 0.2 <= kept["ratio"] <= 1.1 * 0.2
    res = _killed_after_two_and_resumed(scene, tmp_path / "b", monkeypatch)
    assert res.manifest["static_reuse"]["static_measured"] == [kept]  # rendered once, as kept
    _assert_same_frames(tmp_path / "a", tmp_path / "b")


def test_a_static_region_without_light_keeps_the_pilots_pair(tmp_path, write_scene):
    """A mover with nothing behind it and a sensor without dark current: the static pixels are black, so their
    ratio is not defined (nan) and no count can miss the band. The pilot's pair is the static frame (it costs
    nothing), the render finishes, and the static pixels stay black."""
    from render2spike.render.job import render_scene
    scene = _scene(write_scene, objects=[MOVER], duration_s=0.003,
                   render=dict(BASE["render"], keyframe_rate_hz=1000, adaptive={"enabled": False},
                               noise={"max_spp": 16}))
    res = render_scene(scene, tmp_path / "f", progress=False, log=lambda *a: None)
    sr = res.manifest["static_reuse"]
    (m,) = sr["static_measured"]
    assert sr["applied"] and sr["static_source"] == "pilot" and m["source"] == "pilot" and np.isnan(m["ratio"])
    from sensor.io.frames import read_frames
    seq = read_frames(tmp_path / "f")
    phi = np.stack([seq.read_phi(i) for i in range(len(seq))])
    assert np.isfinite(phi).all() and (phi == 0).all(axis=0).mean() > 0.5


def test_static_retry_counts():
    from render2spike.render.reuse import square_count, static_retry_spp
    e = lambda k: k  # noqa: E731  (a sampler that takes every count)
    assert [square_count(n, 1000, e) for n in (1, 2, 4, 5, 17, 30, 64)] == [1, 4, 4, 9, 25, 36, 64]
    assert square_count(2000, 1024, e) == 1024
    assert static_retry_spp([(30, 0.272)], 0.2, 1024, e) == 64  # up like 1/n: 55.5 -> the next square
    assert static_retry_spp([(64, 0.0985)], 0.2, 1024, e) == 36  # down like 1/n^2: 31.5 -> the nearest square
    assert static_retry_spp([(3, 0.138)], 0.2, 1024, e) == 2  # below 4: the nearest count
    assert static_retry_spp([(4, 0.3)], 0.2, 8, e) == 8  # capped
    assert static_retry_spp([(1, 0.1)], 0.2, 8, e) is None  # nothing below 1
    # between a count above the target and one below: the power law through them (here ratio ~ 1/n: 32 -> 36)
    assert static_retry_spp([(16, 0.4), (64, 0.1)], 0.2, 1024, e) == 36
    assert static_retry_spp([(16, 0.4), (64, 0.1), (36, 0.2 * 1.2)], 0.2, 1024, e) == 49
    assert static_retry_spp([(30, 0.3), (36, 0.1)], 0.2, 1024, e) == 32  # no square between: the nearest count
    assert static_retry_spp([(30, 0.3), (31, 0.1)], 0.2, 1024, e) is None  # nothing between
    assert static_retry_spp([(16, float("nan"))], 0.2, 1024, e) is None  # no ratio to go by


def test_a_given_spp_is_the_static_frames_too(tmp_path, write_scene):
    from render2spike.render.job import render_scene
    scene = _scene(write_scene, duration_s=0.003, render=dict(BASE["render"], spp=16, keyframe_rate_hz=1000,
                                                              adaptive={"enabled": False}))
    res = render_scene(scene, tmp_path / "f", progress=False, log=lambda *a: None)
    assert res.manifest["static_reuse"]["static_spp"] == 16 and res.manifest["spp_by_level"] == [16]


def test_a_still_scene_renders_one_static_frame_and_every_keyframe_is_it(tmp_path, write_scene):
    from render2spike.render.job import render_scene
    from sensor.io.frames import read_frames
    scene = _scene(write_scene, objects=BASE["objects"], duration_s=0.01)
    res = render_scene(scene, tmp_path / "f", progress=False, log=lambda *a: None)
    sr = res.manifest["static_reuse"]
    assert sr["applied"] and sr["dynamic_fraction"]["max"] == 0.0
    assert res.manifest["temporal_sampling"]["n_refined"] == 0  # identical keyframes: nothing to refine
    seq = read_frames(tmp_path / "f")
    first = seq.read_phi(0)
    assert all(np.array_equal(seq.read_phi(i), first) for i in range(len(seq)))
    assert all(c["z2_mean"] < c["limit"] for c in sr["static_check"])
