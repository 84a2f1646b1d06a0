"""Base keyframes in blocks: where only the camera moves, one frozen launch renders several keyframes, each at its
own camera pose (frozen.FrozenLaunch.launch_block)."""

from __future__ import annotations

import gc
import json

import numpy as np
import pytest

from tests.render.conftest import BASE, needs_mitsuba

pytestmark = [pytest.mark.render, needs_mitsuba]

#: a checkered plane under the sun and a sky, and a camera panning at 2 m/s (about 1.5 px a millisecond)
PAN = {
    "objects": [{"name": "plane", "shape": "rectangle", "size": [10, 10],
                 "material": {"reflectance": {"texture": "checker", "squares": 40, "low": 0.1, "high": 0.8}}}],
    "lights": BASE["lights"] + [{"name": "sky", "type": "environment", "strength": 0.05}],
    "camera": dict(BASE["camera"], motion={"parametric": [{"translate": {"velocity_m_s": [2.0, 0.0, 0.0]}}]}),
}


def _scene(write_scene, **changes):
    from render2spike.render.scene import load_scene
    return load_scene(write_scene({**PAN, **changes}))


def _killed_and_resumed(scene, out, monkeypatch, owner, name: str, calls: int):
    """Render ``scene`` into ``out``, killed (KeyboardInterrupt) at the call of ``owner.name`` after ``calls`` of
    them, then resumed; -> the resumed render's result."""
    from render2spike.render.job import render_scene
    orig, n = getattr(owner, name), {"calls": 0}

    def killed(self, *args, **kw):
        n["calls"] += 1
        if n["calls"] > calls:
            raise KeyboardInterrupt
        return orig(self, *args, **kw)

    monkeypatch.setattr(owner, name, killed)
    with pytest.raises(KeyboardInterrupt):
        render_scene(scene, out, progress=False, log=lambda *a: None)
    monkeypatch.setattr(owner, name, orig)
    return render_scene(scene, out, progress=False, log=lambda *a: None)


def test_blocks_apply_where_only_the_camera_moves(write_scene):
    from render2spike.render.frozen import BLOCK_KEYFRAMES, BLOCK_VERSION, block_obstacle
    from render2spike.render.launch import settings_of
    pan = _scene(write_scene)
    assert block_obstacle(pan, "frozen") is None
    assert settings_of(pan, "llvm_ad_spectral", "frozen")["keyframe_blocks"] == {"keyframes": BLOCK_KEYFRAMES,
                                                                                "version": BLOCK_VERSION}
    assert "film launch" in block_obstacle(pan, "film")
    assert "keyframe_blocks" not in settings_of(pan, "llvm_ad_spectral", "film")
    still = _scene(write_scene, camera=BASE["camera"])
    assert "nothing moves" in block_obstacle(still, "frozen")
    mover = dict(PAN["objects"][0], name="slab", size=[0.1, 0.1], position=[0, 0, 0.05],
                 motion={"parametric": [{"translate": {"velocity_m_s": [0.1, 0, 0]}}]})
    moving = _scene(write_scene, objects=PAN["objects"] + [mover])
    assert "object 'slab' moves" in block_obstacle(moving, "frozen")
    off = _scene(write_scene, render=dict(BASE["render"], keyframe_blocks=False))
    assert "keyframe_blocks is false" in block_obstacle(off, "frozen")
    assert "keyframe_blocks" not in settings_of(off, "llvm_ad_spectral", "frozen")


def test_a_block_of_frames_estimates_what_frames_of_their_own_do(write_scene):
    """Four frames at four camera poses in one launch against each frame in a launch of its own, six independent
    seeds each: per pixel, the means over the seeds agree (a chi-square over the pixels) and so do the variances;
    a block frame set against another time's own frame does not agree (each block frame took its own pose)."""
    from render2spike.render.renderer import SceneRenderer
    gc.collect()
    r = SceneRenderer(_scene(write_scene), launch="frozen")
    times, spp, n_seeds = [0.0, 0.002, 0.004, 0.006], 16, 6
    assert r.frame_launch.block_size(spp) >= len(times)
    block = np.stack([np.stack([p for p, _ in r.render_block(times, 1000 + s, spp)]) for s in range(n_seeds)])
    own = np.stack([np.stack([r.render_raw(t, 2000 + 10 * s + j, spp)[0] for j, t in enumerate(times)])
                    for s in range(n_seeds)])  # (seed, frame, H, W)
    mb, mo = block.mean(axis=0), own.mean(axis=0)
    vb, vo = block.var(axis=0, ddof=1), own.var(axis=0, ddof=1)

    def chi2_per_pixel(a, va, b, vb_):
        """Mean over pixels of (a - b)^2 / (va + vb) / n: about 1 (a little more: the variances are estimates)
        when the means agree."""
        return float(np.mean((a - b) ** 2 / np.maximum((va + vb_) / n_seeds, 1e-300)))

    n_pix = mb[0].size
    for f in range(len(times)):
        # with 2 x 5 degrees of freedom in each pixel's variance the ratio is F(1, 10): mean 10 / 8 = 1.25, standard
        # deviation 2.2, so over the 1536 pixels the mean has a standard error of about 0.055: 1.6 is 6 of them above
        assert chi2_per_pixel(mb[f], vb[f], mo[f], vo[f]) < 1.6, f
        # against the frame of another time (the camera 8 mm, about 3 px, away) the checker's edges disagree: the
        # ratio is then in the thousands; 8.0 (5x the limit above) is only the line between the two cases
        other = (f + 2) % len(times)
        assert chi2_per_pixel(mb[f], vb[f], mo[other], vo[other]) > 8.0, (f, other)
        # equal variances: the per-pixel difference of the two variance estimates has mean zero
        d = (vb[f] - vo[f]).ravel()
        z = d.mean() / (d.std(ddof=1) / np.sqrt(n_pix))
        assert abs(z) < 4.5, (f, z)


def test_the_frames_of_one_block_have_independent_errors(write_scene):
    """One camera pose three times in a block: the three frames estimate one image, and their errors must be
    independent (the noise budget counts on the errors of K keyframes averaging). Per pixel over the seeds, the mean
    square of two frames' difference estimates var_a + var_b - 2 cov, and the seeds' spread estimates var_a + var_b:
    their ratio over the pixels, R, is 1 for independent errors and 0 for frames that share their samples. Its
    standard error comes from the pixels (a ratio estimator, pixels independent: their samples are other lanes)."""
    from render2spike.render.renderer import SceneRenderer
    gc.collect()
    r = SceneRenderer(_scene(write_scene), launch="frozen")
    spp, n_seeds = 16, 8
    frames = np.stack([np.stack([p for p, _ in r.render_block([0.002] * 3, 3000 + s, spp)])
                       for s in range(n_seeds)])  # (seed, frame, H, W)
    for f, g in ((0, 1), (1, 2), (0, 2)):
        num = ((frames[:, f] - frames[:, g]) ** 2).mean(axis=0).ravel()  # the mean difference is 0: one image
        den = (frames[:, f].var(axis=0, ddof=1) + frames[:, g].var(axis=0, ddof=1)).ravel()
        ratio = num.sum() / den.sum()
        se = np.sqrt(((num - ratio * den) ** 2).sum()) / den.sum()
        assert se < 0.1, se  # enough pixels to tell 1 from a correlation of 0.5 (R = 0.5) at 5 standard errors
        assert abs(ratio - 1.0) < 5 * se, (f, g, ratio, se)


def test_a_camera_pan_renders_its_base_keyframes_in_blocks_and_resumes_the_same(tmp_path, write_scene, monkeypatch):
    """A render of a panning camera takes its 21 base keyframes in two blocks (16 and 5); killed during the
    second block and resumed, it makes the same frames, bit for bit, as an uninterrupted render."""
    from render2spike.render import renderer as rmod
    from render2spike.render.job import render_scene
    from tests.render.test_reproducible import _assert_same_frames
    scene = _scene(write_scene, duration_s=0.02,
                   render=dict(BASE["render"], spp=8, keyframe_rate_hz=1000, adaptive={"enabled": False}))
    whole = render_scene(scene, tmp_path / "a", progress=False, log=lambda *a: None)
    kb = whole.manifest["keyframe_blocks"]
    assert kb == {"applied": True, "keyframes_per_block": 16, "n_blocks_this_run": 2}
    from render2spike.render.job import spp_text
    assert spp_text(whole.manifest, whole.spp) == "8 spp, base keyframes up to 16 to a launch"
    assert whole.n_frames == 21 and np.isfinite(whole.manifest["render_noise_ratio"]["mean"])  # tick 0 verified
    from sensor.io.frames import read_frames
    seq = read_frames(tmp_path / "a")
    # [block, place in it] in each frame's header (a JSON string there)
    assert [json.loads(seq.read(i).header["keyframe_block"]) for i in (0, 15, 16, 20)] == [[0, 0], [0, 15], [1, 0],
                                                                                           [1, 4]]
    # each frame is its own time's: nearer a 64-spp render at its time than one at any other keyframe's time (the pan
    # moves the checker's edge 0.8 px a millisecond: a frame one place off in its block would be nearest its
    # neighbour's time)
    from render2spike.render.photometry import apply_factors
    from render2spike.render.renderer import SceneRenderer
    r = SceneRenderer(scene, launch="frozen")
    refs = [apply_factors(*r.render_raw(rec["time_s"], 77 + t, 64), r._factors)[0]
            for t, rec in enumerate(whole.manifest["frames"])]
    for t in (0, 1, 7, 14, 15, 16, 17, 20):
        dist = [np.mean((seq.read_phi(t) - ref) ** 2) for ref in refs]
        assert int(np.argmin(dist)) == t, (t, dist)
    del r
    gc.collect()
    # dies at the second block: the first block's 16 frames are written
    res = _killed_and_resumed(scene, tmp_path / "b", monkeypatch, rmod.SceneRenderer, "render_block", 1)
    assert res.n_rendered == 5 and res.manifest["keyframe_blocks"]["n_blocks_this_run"] == 1
    _assert_same_frames(tmp_path / "a", tmp_path / "b")


def test_a_render_killed_inside_a_block_takes_the_frames_it_lacks_from_that_block_again(tmp_path, write_scene,
                                                                                      monkeypatch):
    """Blocks of 4 (BLOCK_KEYFRAMES patched), 13 base keyframes, killed after the sixth frame: the second block
    is half written. The resumed render makes that block again, from its seed and its poses, and takes only the
    frames it lacks: every frame bit for bit an uninterrupted render's."""
    from render2spike.render import frozen
    from render2spike.render import job as job_mod
    from render2spike.render.job import render_scene
    from tests.render.test_reproducible import _assert_same_frames
    monkeypatch.setattr(frozen, "BLOCK_KEYFRAMES", 4)
    scene = _scene(write_scene, duration_s=0.012,
                   render=dict(BASE["render"], spp=8, keyframe_rate_hz=1000, adaptive={"enabled": False}))
    whole = render_scene(scene, tmp_path / "a", progress=False, log=lambda *a: None)
    assert whole.n_frames == 13 and whole.manifest["keyframe_blocks"]["n_blocks_this_run"] == 4
    res = _killed_and_resumed(scene, tmp_path / "b", monkeypatch, job_mod._Keyframes, "_block_frame", 6)
    assert res.n_rendered == 7 and res.manifest["keyframe_blocks"]["n_blocks_this_run"] == 3  # ticks 6-12: blocks 1-3
    _assert_same_frames(tmp_path / "a", tmp_path / "b")
