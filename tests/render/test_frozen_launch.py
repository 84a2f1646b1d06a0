"""The frozen launch (render2spike/render/frozen.py): its parts against Mitsuba's, its replays against the same
function unfrozen, its frames against the film launch's, and its place in the render job.

A camera with Mitsuba's spectral film anywhere in the process breaks ``drjit.freeze`` (see the module), so the
tests that call a frozen function first let go of every film-launch renderer (``_collect``).
"""

import gc
import json

import numpy as np
import pytest
from scipy import stats

from tests.render.conftest import assert_image_means_agree, film_and_frozen_frames, needs_mitsuba

pytestmark = [pytest.mark.render, needs_mitsuba]

#: a plane, a small moving cube in front of it, and a camera that pans: every input of the frozen launch moves
MOVING = [
    {"name": "back", "shape": "rectangle", "size": [10, 10], "position": [0, 0, -0.5], "material": {"reflectance": 0.3}},
    {"name": "thing", "shape": "cube", "size": [0.03, 0.03, 0.03], "position": [0, 0, 0], "material": {"reflectance": 0.8},
     "motion": {"parametric": [{"translate": {"velocity_m_s": [0.25, 0.1, 0.0]}}]}},
]


def _scene(write_scene, pan=True):
    from render2spike.render.scene import load_scene
    changes = {"objects": MOVING, "reference": {"point": [0, 0, 0.05], "normal": [0, 0, 1]}}
    if pan:
        from tests.render.conftest import BASE
        cam = dict(BASE["camera"])
        cam["motion"] = {"parametric": [{"translate": {"velocity_m_s": [0.5, 0.0, 0.0]}}]}
        changes["camera"] = cam
    return load_scene(write_scene(changes))


def _collect():
    gc.collect()


def test_response_tables_quantiles_cover_every_wavelength_a_response_sees():
    from render2spike.render.frozen import response_tables
    wl_a = np.arange(400.0, 701.0, 5.0)
    a = np.where((wl_a > 450) & (wl_a < 650), 1.0, 0.0)  # a band with zero ends
    wl_b = np.arange(380.0, 781.0, 1.0)
    b = np.exp(-0.5 * ((wl_b - 555.0) / 40.0) ** 2)
    lo, step, tables, q, ranges = response_tables({"A": (wl_a, a), "B": (wl_b, b)}, n_quantiles=512)
    assert lo == 380.0 and step == 1.0 and len(q) == 513 and ranges == {"A": (400.0, 700.0), "B": (380.0, 780.0)}
    assert q[0] >= 380.0 and q[-1] <= 780.0 and np.all(np.diff(q) >= 0)
    grid = lo + step * np.arange(len(tables["A"]))
    np.testing.assert_allclose(tables["A"], np.interp(grid, wl_a, a, left=0, right=0))
    # every wavelength where a response is above zero falls in a part of non-zero width
    fine = np.linspace(380.0, 780.0, 40001)
    seen = (np.interp(fine, grid, tables["A"]) + np.interp(fine, grid, tables["B"])) > 0
    j = np.clip(np.searchsorted(q, fine, side="right") - 1, 0, len(q) - 2)
    assert np.all((q[j + 1] - q[j])[seen] > 0)
    with pytest.raises(ValueError, match="off the 1 nm grid"):
        response_tables({"A": (np.array([400.0, 400.5, 700.0]), np.ones(3))})
    with pytest.raises(ValueError, match="zero everywhere"):
        response_tables({"A": (wl_a, np.zeros_like(a))})


def test_wavelength_estimator_integrates_each_response(write_scene):
    # the Dr.Jit code itself: on a fine stratified grid of u, the mean of response(lambda) / p(lambda) is the
    # response's integral. Each term is a float32 product (relative rounding <= 3 x 6e-8, unbiased in sign)
    # summed in float64, and the midpoint rule over 2^22 strata of piecewise-linear functions errs far less:
    # 1e-6 bounds both with room (about 1e-11 seen)
    from render2spike.render.renderer import SceneRenderer
    r = SceneRenderer(_scene(write_scene, pan=False), launch="frozen")
    fl, mi = r._frozen, r.mi
    n = 1 << 20
    u = mi.Float((np.arange(n) + 0.5) / n / 4.0)  # the four strata cover [0, 1) once
    lam, inv_p = fl.wavelengths(u, fl._quantiles)
    grid_tables = [np.asarray(t, np.float64) for t in fl._tables]
    for name, tab, tab_np, rng in zip(fl.names, fl._tables, grid_tables, fl._ranges):
        est = sum(np.asarray(fl.response(tab, lam[i], rng) * inv_p[i], np.float64).sum() for i in range(4)) / (4 * n)
        exact = np.trapezoid(tab_np, dx=fl._step)
        assert abs(est / exact - 1.0) < 1e-6, (name, est, exact)
        # and the response is the table's linear interpolation, zero outside it
        x = np.array([fl._lo - 3.0, fl._lo + 0.25, fl._lo + 10.5, fl._lo + fl._nbins + 2.0])
        got = np.asarray(fl.response(tab, mi.Float(x), rng), np.float64)
        want = np.interp(x, fl._lo + np.arange(len(tab_np)), tab_np, left=0.0, right=0.0)
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-7)


def test_responses_are_mitsubas_irregular_spectra_even_where_they_end_above_zero(write_scene):
    # a band that ends at 1 inside the other curve's range: Mitsuba's `irregular` spectrum drops to 0 right after
    # its last point, and so must the frozen launch's response (a table alone would ramp it down over 1 nm)
    from render2spike.render.frozen import FrozenLaunch
    from render2spike.render.renderer import SceneRenderer
    r = SceneRenderer(_scene(write_scene, pan=False), launch="frozen")
    mi, dr = r.mi, r._dr
    curves = {"band": (np.array([400.0, 450.0, 500.0]), np.array([0.5, 1.0, 1.0])),
              "wide": (np.arange(350.0, 1001.0, 5.0), np.linspace(0.2, 0.9, 131))}
    fl = FrozenLaunch(mi, dr, r.mi_scene, 4, 4, 30.0, 1e-3, 1e4, curves, "multijitter", frozen=False)
    lam = np.array([350.0, 399.5, 400.0, 425.3, 499.5, 500.0, 500.5, 501.0, 777.7, 1000.0, 1000.5])
    for (name, (wl, v)), tab, rng in zip(curves.items(), fl._tables, fl._ranges):
        spec = mi.load_dict({"type": "irregular", "wavelengths": ", ".join(str(x) for x in wl),
                             "values": ", ".join(str(x) for x in v)})
        si = dr.zeros(mi.SurfaceInteraction3f)
        want = []
        for x in lam:
            si.wavelengths = mi.UnpolarizedSpectrum(float(x))
            want.append(float(np.asarray(spec.eval(si)[0]).ravel()[0]))
        got = np.asarray(fl.response(tab, mi.Float(lam), rng), np.float64)
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-7, err_msg=name)


def test_primary_rays_are_mitsubas_perspective_camera(write_scene):
    # same film positions, same pose: the frozen launch's rays are the film camera's (no frozen call here, so the
    # film renderer may stay alive)
    from render2spike.render.renderer import SceneRenderer
    sc = _scene(write_scene)
    rf = SceneRenderer(sc, launch="film")
    rz = SceneRenderer(sc, launch="frozen", calibration=rf.calibration)
    mi = rf.mi
    rng = np.random.default_rng(3)
    pos = rng.random((2, 257))
    pos[:, :4] = [[0.0, 1.0, 0.5, 0.999], [0.0, 1.0, 0.5, 0.001]]
    for t_s in (0.0, 0.013):
        rf.set_time(t_s)
        rz.set_time(t_s)
        ray = rf.sensor.sample_ray(0.0, 0.5, mi.Point2f(pos[0], pos[1]), mi.Point2f(0.5, 0.5))[0]
        o, d, maxt = rz._frozen.primary_rays(mi.Transform4f(rz._cam_m.tolist()), mi.Vector2f(pos[0], pos[1]))
        # float32 on both sides along different operation sequences (Mitsuba inverts its projection matrix):
        # unit directions and origins ~1 m from the world origin agree to a few float32 ulps (6e-8 at 0.5-1);
        # 2e-6 allows ~30 ulps, far below a half-pixel error (a pixel is ~2.5e-3 rad here)
        np.testing.assert_allclose(np.asarray(d), np.asarray(ray.d), atol=2e-6)
        np.testing.assert_allclose(np.asarray(o), np.asarray(ray.o), atol=2e-6)
        np.testing.assert_allclose(np.asarray(maxt), np.asarray(ray.maxt), rtol=1e-5)


def test_frozen_replays_are_the_unfrozen_function_bitwise(write_scene):
    from render2spike.render.frozen import FrozenLaunch
    from render2spike.render.renderer import SceneRenderer
    _collect()
    r = SceneRenderer(_scene(write_scene), launch="frozen")
    fl = r._frozen
    ref = FrozenLaunch(r.mi, r._dr, r.mi_scene, fl.height, fl.width, 1.0, 1.0, 2.0,
                       {"Phi": (np.array([400.0, 700.0]), np.ones(2))}, "multijitter", frozen=False)
    ref.__dict__.update({k: v for k, v in fl.__dict__.items()  # same camera, tables
                         if k not in ("_fn", "_fn_px", "_fn_block", "frozen")})
    assert ref.frozen is False and ref._fn == ref._launch and ref._fn_px == ref._launch_px
    assert ref._fn_block == ref._launch_block
    warm = tuple((0.001 * k, 100 + k, spp) for spp in (16, 4) for k in range(4))
    calls = ((0.004, 8, 16), (0.013, 123456789, 4), (0.004, 8, 16), (0.02, 9, 4), (0.007, 11, 16))
    frozen = []
    for k, (t_s, seed, spp) in enumerate(warm + calls):
        if k == len(warm):
            # a sample count is recorded at its first call, and again at some of its next few (Dr.Jit re-records
            # when an input's layout changed: twice more over the first 5 frames of the rotating disk, never
            # after in 300 frames); then only replayed
            n_warm = fl.n_recordings
            assert 2 <= n_warm <= len(warm), n_warm
        r.set_time(t_s)
        out = fl.channels(fl.launch(seed, spp, r._cam_m))
        if k >= len(warm):
            frozen.append(out)
    # new poses, new seeds: replays, no recording (they are inputs, not constants of the recording)
    assert fl.n_recordings == n_warm, (fl.n_recordings, n_warm)
    for (t_s, seed, spp), a in zip(calls, frozen):  # and each is the same function unfrozen, bit for bit
        r.set_time(t_s)
        b = ref.channels(ref.launch(seed, spp, r._cam_m))
        for c in ("Phi", "E"):
            np.testing.assert_array_equal(a[c], b[c])
            assert np.all(np.isfinite(a[c])) and a[c].mean() > 0
    np.testing.assert_array_equal(frozen[0]["Phi"], frozen[2]["Phi"])  # the same frame again: the same bits
    assert not np.array_equal(frozen[0]["Phi"], frozen[4]["Phi"])
    # the other two recorded functions, a list of pixels and a block of camera poses, twice (other seeds, pixels and
    # poses in each place): each the unfrozen function bit for bit
    poses = []
    for t_s in (0.0, 0.004, 0.009):
        r.set_time(t_s)
        poses.append(np.array(r._cam_m))
    rng = np.random.default_rng(3)
    n_rec = fl.n_recordings
    for seed in (21, 22):
        pix = np.sort(rng.choice(fl.height * fl.width, 300, replace=False))
        a, b = (x.pixel_values(x.launch_pixels(seed, 16, r._cam_m, pix)) for x in (fl, ref))
        order = poses[seed - 21:] + poses[:seed - 21]  # the same number of frames, other poses in each place
        fa, fb = (x.block_channels(x.launch_block(seed, 4, order)) for x in (fl, ref))
        assert len(fa) == len(fb) == 3
        for c in ("Phi", "E"):
            np.testing.assert_array_equal(a[c], b[c])
            for f, g in zip(fa, fb):
                np.testing.assert_array_equal(f[c], g[c])
                assert np.all(np.isfinite(f[c])) and f[c].mean() > 0
    assert fl.n_recordings > n_rec  # the two were recorded (and at times again at the second call, as above)


def test_a_moving_mesh_is_an_instance_and_every_replay_traces_its_pose():
    # The film launch moves a mesh by rewriting its vertices; frozen replays after such a rewrite traced a stale
    # structure on Mitsuba 3.9.1's LLVM variant (on the bundled translating_object: wrong geometry in 4 of
    # 12 frames, in some runs 8, unless Dr.Jit happened to record again). The frozen launch moves meshes as instances: each
    # replay, one per new pose, must be the unfrozen function at that pose, frame after frame
    from render2spike.render.frozen import FrozenLaunch
    from render2spike.render.renderer import SceneRenderer
    from render2spike.render.scene import load_scene
    _collect()
    sc = load_scene("translating_object")
    r = SceneRenderer(sc, launch="frozen")
    assert r._moving["cube"][:2] == ("instance", "cube.to_world")  # an instance's transform, not vertices
    fl = r._frozen
    ref = FrozenLaunch(r.mi, r._dr, r.mi_scene, fl.height, fl.width, 1.0, 1.0, 2.0,
                       {"Phi": (np.array([400.0, 700.0]), np.ones(2))}, "multijitter", frozen=False)
    ref.__dict__.update({k: v for k, v in fl.__dict__.items() if k not in ("_fn", "frozen")})
    means = []
    for k, t_s in enumerate(np.linspace(0.0, sc.duration_s, 9, endpoint=False)):
        r.set_time(float(t_s))
        a = fl.channels(fl.launch(100 + k, 4, r._cam_m))["Phi"]
        b = ref.channels(ref.launch(100 + k, 4, r._cam_m))["Phi"]
        np.testing.assert_array_equal(a, b, err_msg=f"replay at t = {t_s} s")
        means.append(a.mean())
    assert len(set(np.round(means, 12))) > 1  # the cube moved in view


def test_a_scaled_turned_moving_mesh_file_renders_as_in_the_film_launch(tmp_path, write_scene):
    # The instance starts from the mesh's t = 0 world pose, so its smooth vertex normals are made from the same
    # world-space vertices as the film launch's (an instance of the unscaled mesh carried them through a
    # non-uniform scale: image means 40-80 standard deviations apart, in review). Same time, independent seeds:
    # the image means must agree within what each frame's own variance estimate allows
    import trimesh

    from render2spike.render.scene import load_scene
    trimesh.creation.box(extents=[0.03, 0.03, 0.03]).export(tmp_path / "box.ply")  # 8 shared vertices: smooth normals
    p = write_scene({"objects": [
        {"name": "back", "shape": "rectangle", "size": [10, 10], "position": [0, 0, -0.5],
         "material": {"reflectance": 0.3}},
        {"name": "box", "shape": "mesh", "file": str(tmp_path / "box.ply"), "scale": [1.5, 0.8, 1.0],
         "rotation_deg": [25.0, 35.0, 0.0], "material": {"reflectance": 0.8},
         "motion": {"parametric": [{"translate": {"velocity_m_s": [0.3, 0.1, 0.0]}},
                                   {"rotate": {"axis": [0, 1, 0], "omega_rad_s": 20.0}}]}}],
        "reference": {"point": [0, 0, 0.05], "normal": [0, 0, 1]}})
    fa, fb = film_and_frozen_frames(load_scene(p), "box")
    assert_image_means_agree(fa, fb)
    assert not np.allclose(fb[0]["phi"], fb[1]["phi"])  # it moved


def test_a_mesh_whose_motion_changes_its_shape_keeps_the_film_launch(write_scene):
    from render2spike.render.frozen import frozen_obstacle
    from render2spike.render.launch import resolve_launch
    from render2spike.render.scene import load_scene
    grow = {**MOVING[1], "motion": {"keyframes": [{"time_s": 0.0, "scale": [1.0, 1.0, 1.0]},
                                                  {"time_s": 0.01, "scale": [2.0, 1.0, 1.0]}]}}
    sc = load_scene(write_scene({"objects": [MOVING[0], grow], "reference": {"point": [0, 0, 0.05],
                                                                            "normal": [0, 0, 1]}}))
    assert "changes its shape" in frozen_obstacle(sc)
    assert resolve_launch("auto", "llvm_ad_spectral", sc) == "film"
    # a blip of scale between two keyframes 10 us apart, shorter than the even check spacing: found at a keyframe
    blip = {**MOVING[1], "motion": {"keyframes": [{"time_s": 0.00401, "scale": [1.0, 1.0, 1.0]},
                                                  {"time_s": 0.00402, "scale": [3.0, 1.0, 1.0]},
                                                  {"time_s": 0.00403, "scale": [1.0, 1.0, 1.0]}]}}
    sc = load_scene(write_scene({"objects": [MOVING[0], blip], "reference": {"point": [0, 0, 0.05],
                                                                            "normal": [0, 0, 1]}}))
    assert "changes its shape" in frozen_obstacle(sc)
    # rigid keyframed motion with a constant non-uniform (even negative) scale is no obstacle
    turn = {**MOVING[1], "scale": [-1.5, 0.7, 1.0],
            "motion": {"interpolation": "spline", "keyframes": [
                {"time_s": 0.0, "position": [0, 0, 0], "rotation_deg": [0, 0, 0]},
                {"time_s": 0.005, "position": [0.01, 0, 0], "rotation_deg": [0, 40, 10]},
                {"time_s": 0.01, "position": [0.02, 0.01, 0], "rotation_deg": [10, 80, 0]}]}}
    sc = load_scene(write_scene({"objects": [MOVING[0], turn], "reference": {"point": [0, 0, 0.05],
                                                                            "normal": [0, 0, 1]}}))
    assert frozen_obstacle(sc) is None


def test_a_moving_mesh_that_emits_light_keeps_the_film_launch(write_scene):
    from render2spike.render.frozen import frozen_obstacle
    from render2spike.render.launch import resolve_launch
    from render2spike.render.renderer import SceneRenderer
    from render2spike.render.scene import load_scene
    from sensor.errors import InputError
    glow = {**MOVING[1], "emitter": {"strength": 1.0}}
    sc = load_scene(write_scene({"objects": [MOVING[0], glow], "reference": {"point": [0, 0, 0.05],
                                                                            "normal": [0, 0, 1]}}))
    assert "emits light" in frozen_obstacle(sc)
    assert resolve_launch("auto", "llvm_ad_spectral", sc) == "film"
    # nor does auto keep the frozen launch of a folder for it (one made by an older version that allowed it)
    from render2spike.render.launch import launch_taken, settings_of
    old = sc.content_hash(settings_of(sc, "llvm_ad_spectral", "frozen"))
    assert launch_taken(sc, "llvm_ad_spectral", "auto", old, "frozen") == (
        "film", sc.content_hash(settings_of(sc, "llvm_ad_spectral", "film")))
    with pytest.raises(InputError, match="--launch film"):
        SceneRenderer(sc, launch="frozen")
    still = {**glow}
    still.pop("motion")
    sc2 = load_scene(write_scene({"objects": [MOVING[0], still], "reference": {"point": [0, 0, 0.05],
                                                                             "normal": [0, 0, 1]}}))
    assert frozen_obstacle(sc2) is None and resolve_launch("auto", "llvm_ad_spectral", sc2) == "frozen"


def test_frozen_frames_estimate_what_the_film_frames_estimate(write_scene):
    # Both launches are unbiased estimates of the same channels, so with the same seeds the difference of a
    # frozen and a film render has mean 0, and the n renders' differences are independent. The same seeds draw
    # the same pixel positions and nearly the same wavelengths, so the differences are small and a paired test
    # sees small biases. Per pixel: the paired t (n - 1 degrees of freedom) within a Bonferroni bound over the
    # pixels, family-wise 1e-3; the image mean: the paired t within its two-sided 1e-3 bound.
    from render2spike.render.renderer import SceneRenderer
    sc = _scene(write_scene)
    n, spp, t_s = 16, 16, 0.013
    rf = SceneRenderer(sc, launch="film")
    cal = rf.calibration
    film = [rf.render_exact(t_s, [1000 + i], spp) for i in range(n)]
    del rf
    _collect()
    rz = SceneRenderer(sc, launch="frozen", calibration=cal)
    froz = [rz.render_exact(t_s, [1000 + i], spp) for i in range(n)]
    for k, name in enumerate(("Phi", "E")):
        d = np.stack([f[k] for f in froz]) - np.stack([f[k] for f in film])
        sd = d.std(axis=0, ddof=1)
        alike = sd == 0  # the two launches agreed to the bit in every render: the difference must be 0 there
        assert np.all(d.mean(axis=0)[alike] == 0), name
        t = d.mean(axis=0)[~alike] / (sd[~alike] / np.sqrt(n))
        bound = stats.t.isf(1e-3 / (2 * d[0].size), n - 1)
        assert np.abs(t).max() < bound, (name, np.abs(t).max(), bound)
        dm = d.mean(axis=(1, 2))
        t_img = dm.mean() / (dm.std(ddof=1) / np.sqrt(n))
        assert abs(t_img) < stats.t.isf(5e-4, n - 1), (name, t_img)


def test_render_job_records_the_launch_and_resumes_only_with_it(tmp_path, write_scene):
    from render2spike.render.job import render_scene
    from render2spike.render.scene import load_scene
    from sensor.errors import InputError
    from sensor.io.frames import read_frames
    _collect()
    sc = load_scene(write_scene(), ["render.spp=4"])
    res = render_scene(sc, tmp_path / "f", progress=False, log=lambda *a: None, launch="frozen")
    m = json.loads((res.out / "frames.json").read_text())
    assert m["launch"] == "frozen" and res.n_rendered == 3
    seq = read_frames(res.out)
    assert seq.read(0).header["launch"] == "frozen"
    again = render_scene(sc, tmp_path / "f", progress=False, log=lambda *a: None, launch="frozen")
    assert again.n_rendered == 0  # up to date: the same hash
    with pytest.raises(InputError, match="--launch frozen"):
        render_scene(sc, tmp_path / "f", progress=False, log=lambda *a: None, launch="film")
    with pytest.raises(InputError, match="film, frozen"):
        render_scene(sc, tmp_path / "g", progress=False, log=lambda *a: None, launch="thawed")
    assert not (tmp_path / "g").exists()
    # the estimator's version is in the hash: a changed estimator does not resume an older folder
    import render2spike.render.frozen as frozen_mod
    from render2spike.render.launch import settings_of
    from render2spike.render.backend import mitsuba
    v = mitsuba().variant()
    a = settings_of(sc, v, "frozen")
    assert json.loads((tmp_path / "f" / "frames.json").read_text())["launch_estimator"] == frozen_mod.ESTIMATOR_VERSION
    frozen_mod.ESTIMATOR_VERSION += 1
    try:
        assert sc.content_hash(settings_of(sc, v, "frozen")) != sc.content_hash(a)
        with pytest.raises(InputError, match="earlier version of the frozen launch"):  # and the refusal says so
            render_scene(sc, tmp_path / "f", progress=False, log=lambda *a: None, launch="frozen")
    finally:
        frozen_mod.ESTIMATOR_VERSION -= 1
    assert "launch" not in settings_of(sc, v, "film")  # folders of the film launch keep their hashes


def test_a_film_scene_left_in_a_reference_cycle_is_collected_before_recording(write_scene):
    from render2spike.render.renderer import SceneRenderer
    sc = _scene(write_scene, pan=False)
    film = SceneRenderer(sc)
    cal = film.calibration
    film.cycle = film  # garbage only the cyclic collector can free
    del film
    r = SceneRenderer(sc, launch="frozen", calibration=cal)
    p, e = r.render_exact(0.0, [3], 4)
    assert np.all(np.isfinite(p)) and p.mean() > 0


def test_a_launch_collects_garbage_only_after_a_scene_was_loaded(write_scene, monkeypatch):
    """Collecting is 30-90 ms where PyTorch is loaded, and Dr.Jit may record any launch (each new count and length,
    and at times one seen before): it is done before the first launch, and again only when a scene was loaded since
    (a film scene, garbage in a cycle, would break a recording: the test above)."""
    import gc
    from render2spike.render import backend
    from render2spike.render.renderer import SceneRenderer
    sc = _scene(write_scene, pan=False)
    r = SceneRenderer(sc, launch="frozen")
    fl = r._frozen
    collected = []
    orig = gc.collect
    monkeypatch.setattr(gc, "collect", lambda *a: collected.append(1) or orig(*a))
    fl.channels(fl.launch(1, 4, r._cam_m))
    assert len(collected) == 1  # the first launch
    fl.channels(fl.launch(2, 16, r._cam_m))
    fl.pixel_values(fl.launch_pixels(3, 9, r._cam_m, np.arange(0, 200, 2)))
    fl.channels(fl.launch(4, 4, r._cam_m))
    assert len(collected) == 1  # new counts and a list, but no scene loaded since
    backend.load_scene(r.mi, {"type": "scene"})
    fl.channels(fl.launch(5, 4, r._cam_m))
    assert len(collected) == 2  # a count seen before, but a scene was loaded since: Dr.Jit may record it again
    fl.channels(fl.launch(6, 9, r._cam_m))
    fl.block_channels(fl.launch_block(7, 4, [r._cam_m, r._cam_m]))
    assert len(collected) == 2  # nothing loaded since


def test_too_many_samples_for_one_launch_are_refused(write_scene):
    from render2spike.render.renderer import SceneRenderer
    from sensor.errors import InputError
    r = SceneRenderer(_scene(write_scene, pan=False), launch="frozen")
    with pytest.raises(InputError, match="2\\^32 or more"):
        r._frozen.launch(1, (1 << 32) // (32 * 48) + 1, r._cam_m)
    with pytest.raises(InputError, match="2\\^32 or more"):  # the sampler's rounding up crosses the limit
        r._frozen.launch(1, (1 << 32) // (32 * 48) - 1, r._cam_m)


def test_a_live_film_scene_gives_a_clear_error_not_a_wrong_frame(tmp_path, write_scene):
    # in a child process: a failed recording may leave Dr.Jit's state unusable for the tests after it
    import subprocess
    import sys
    path = write_scene({"objects": MOVING, "reference": {"point": [0, 0, 0.05], "normal": [0, 0, 1]}})
    code = (
        "import sys\n"
        "from render2spike.render.renderer import SceneRenderer\n"
        "from render2spike.render.scene import load_scene\n"
        "from sensor.errors import DependencyError\n"
        f"sc = load_scene({str(path)!r})\n"
        "film = SceneRenderer(sc, launch='film')\n"
        "r = SceneRenderer(sc, launch='frozen', calibration=film.calibration)\n"
        "try:\n"
        "    r.render_exact(0.0, [1], 4)\n"
        "except DependencyError as e:\n"
        "    print('ERROR', e)\n"
        "    sys.exit(0)\n"
        "print('NO ERROR')\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "ERROR the frozen launch failed" in out.stdout and "--launch film" in out.stdout, out.stdout


def test_cli_launch_option_reaches_the_frames_and_the_run_summary(tmp_path, write_scene, capsys):
    from render2spike.cli import main
    from render2spike.pipeline import run_pipeline
    from render2spike.render.backend import mitsuba
    from render2spike.render.launch import resolve_launch
    from sensor.errors import InputError
    path = write_scene()
    auto = resolve_launch("auto", mitsuba().variant())  # frozen on the LLVM and CUDA variants the tests run on
    assert main(["render", str(path), "--out", str(tmp_path / "f"), "--spp", "4", "--quiet"]) == 0
    assert json.loads((tmp_path / "f" / "frames.json").read_text())["launch"] == auto
    assert main(["run", str(path), "--out", str(tmp_path / "r"), "--spp", "4", "--launch", "film",
                 "--quiet", "--keep-frames"]) == 0
    assert json.loads((tmp_path / "r" / "summary.json").read_text())["launch"] == "film"
    # the default (auto) resumes the film run: nothing rendered again, the summary keeps its launch
    s = run_pipeline(path, tmp_path / "r", sets=["render.spp=4"], progress=False, log=lambda *a: None)
    assert s["launch"] == "film" and s["frames_rendered_now"] == 0
    with pytest.raises(InputError, match="--launch film to resume"):  # the run's folder names its launch
        run_pipeline(path, tmp_path / "r", sets=["render.spp=4"], progress=False, log=lambda *a: None,
                     launch="frozen")
    # the frames rendered again with the other launch since: the frames folder, not the older summary, decides
    from render2spike.render.job import render_scene
    from render2spike.render.scene import load_scene
    render_scene(load_scene(path, ["render.spp=4"]), tmp_path / "r" / "frames", overwrite=True, progress=False,
                 log=lambda *a: None, launch="frozen")
    s = run_pipeline(path, tmp_path / "r", sets=["render.spp=4"], progress=False, log=lambda *a: None,
                     launch="frozen")
    assert s["launch"] == "frozen" and s["frames_rendered_now"] == 0
    with pytest.raises(InputError, match="--launch frozen to resume"):
        run_pipeline(path, tmp_path / "r", sets=["render.spp=4"], progress=False, log=lambda *a: None,
                     launch="film")
    with pytest.raises(SystemExit):
        main(["render", str(path), "--out", str(tmp_path / "g"), "--launch", "thawed"])
    assert "invalid choice: 'thawed'" in capsys.readouterr().err


def test_auto_takes_the_frozen_launch_on_jit_variants_and_a_folder_its_own_launch(tmp_path, write_scene):
    from render2spike.render.job import render_scene
    from render2spike.render.launch import resolve_launch
    from render2spike.render.renderer import SceneRenderer
    from sensor.errors import InputError
    for v in ("llvm_ad_spectral", "cuda_ad_spectral", "llvm_ad_rgb"):
        assert resolve_launch("auto", v) == "frozen"
    assert resolve_launch("auto", "scalar_spectral") == "film"
    assert resolve_launch("film", "llvm_ad_spectral") == "film"
    assert resolve_launch("frozen", "scalar_spectral") == "frozen"  # taken as named (the renderer refuses it)
    with pytest.raises(InputError, match="auto, film, frozen"):
        resolve_launch("thawed", "llvm_ad_spectral")
    sc = _scene(write_scene, pan=False)
    r = SceneRenderer(sc)
    assert r.launch_kind == resolve_launch("auto", r.variant) and r.launch_kind == "frozen"
    del r
    _collect()
    logs = []
    film = render_scene(sc, tmp_path / "f", progress=False, log=lambda *a: None, launch="film")
    again = render_scene(sc, tmp_path / "f", progress=False, log=lambda *a: logs.append(" ".join(map(str, a))))
    assert again.n_rendered == 0 and again.scene_hash == film.scene_hash and again.manifest["launch"] == "film"
    assert any("frames of the film launch: resuming with it" in m for m in logs), logs
    with pytest.raises(InputError, match="--launch film to resume"):
        render_scene(sc, tmp_path / "f", progress=False, log=lambda *a: None, launch="frozen")
    # a folder of another scene is still refused under auto, without a launch hint that would not help
    other = _scene(write_scene, pan=True)
    with pytest.raises(InputError, match="different scene") as e:
        render_scene(other, tmp_path / "f", progress=False, log=lambda *a: None)
    assert "--launch" not in str(e.value)


def test_a_frozen_launch_too_big_for_its_memory_cap_is_split_into_seeded_parts(write_scene, monkeypatch):
    import render2spike.render.frozen as frozen_mod
    from render2spike.render.renderer import SceneRenderer
    sc = _scene(write_scene, pan=False)
    px = sc.profile.height * sc.profile.width
    monkeypatch.setattr(frozen_mod, "MAX_SAMPLES_PER_LAUNCH", 10 * px)  # at most 10 samples per pixel a launch
    r = SceneRenderer(sc, launch="frozen")
    assert r.launch_counts(36) == [9, 9, 9, 9]  # ceil(36 / 10) = 4 parts of 9 (an exact count)
    for spp in (4, 10, 17, 64, 100):
        counts = r.launch_counts(spp)
        assert sum(counts) == spp and max(counts) <= 10 and len(counts) >= -(-spp // 10), (spp, counts)
    monkeypatch.setattr(frozen_mod, "MAX_SAMPLES_PER_LAUNCH", 30 * px)
    r.__dict__.pop("_launch_cache")
    assert r.launch_counts(48) == [24, 24]  # equal parts (one recording), not [30, 16, 2]
    monkeypatch.setattr(frozen_mod, "MAX_SAMPLES_PER_LAUNCH", 10 * px)
    r.__dict__.pop("_launch_cache")
    split = r.render_frame(0.0, 11, 36, variance=True)
    assert len(set(split["seeds"])) == 4  # each part its own seed
    monkeypatch.setattr(frozen_mod, "MAX_SAMPLES_PER_LAUNCH", 1 << 26)
    whole_r = SceneRenderer(sc, launch="frozen", calibration=r.calibration)
    assert whole_r.launch_counts(36) == [36]
    whole = whole_r.render_frame(0.0, 12, 36, variance=True)
    # the split frame estimates the same irradiance: image means within the noise each frame's variance gives
    diff = split["phi"].mean() - whole["phi"].mean()
    sd = np.sqrt((split["phi_var"].sum() + whole["phi_var"].sum()) / px ** 2)
    assert abs(diff) < 4.0 * sd, (diff, sd)  # one comparison at fixed seeds: beyond 4 sd has probability 6e-5
    assert split["phi"].mean() > 0 and sd > 0


def test_a_scalar_variant_is_refused_with_the_launch_to_use(tmp_path, write_scene):
    # in a child process: the scalar variant is set for the whole process
    import subprocess
    import sys
    path = write_scene()
    code = (
        "from render2spike.render.renderer import SceneRenderer\n"
        "from render2spike.render.scene import load_scene\n"
        "from sensor.errors import InputError\n"
        "try:\n"
        f"    SceneRenderer(load_scene({str(path)!r}), variant='scalar_spectral', launch='frozen')\n"
        "except InputError as e:\n"
        "    print('ERROR', e)\n"
        f"print('AUTO', SceneRenderer(load_scene({str(path)!r}), variant='scalar_spectral').launch_kind)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "needs an LLVM or CUDA variant" in out.stdout and "--launch film" in out.stdout, out.stdout
    assert "AUTO film" in out.stdout, out.stdout  # the default falls back to the film launch there


def test_the_replay_check_reports_equal_replays_and_catches_a_wrong_one(tmp_path, monkeypatch):
    # benchmarks/frozen_replay_check.py: its verdict comes from comparing each replay with the unfrozen function
    import importlib.util
    from pathlib import Path
    from render2spike.render.frozen import FrozenLaunch
    _collect()
    spec = importlib.util.spec_from_file_location(
        "frozen_replay_check", Path(__file__).resolve().parents[2] / "benchmarks" / "frozen_replay_check.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    args = ["--scenes", "translating_object", "--frames", "3", "--spp", "4"]
    assert mod.main(args + ["--out", str(tmp_path / "a")]) == 0
    text = (tmp_path / "a" / "frozen_replay.md").read_text()
    assert "| translating_object |" in text and "cube (instance)" in text and "| 3 / 3 | 0 0 0 |" in text
    orig = FrozenLaunch.channels

    def off_when_frozen(self, launched):  # a replay that is not the recorded function
        out = orig(self, launched)
        if self._fn != self._launch:  # (bound methods: compared by ==, each access makes a new one)
            out["Phi"] = out["Phi"] * (1 + 1e-6)
        return out
    monkeypatch.setattr(FrozenLaunch, "channels", off_when_frozen)
    _collect()
    assert mod.main(args + ["--out", str(tmp_path / "b")]) == 1
    assert "| 0 / 3 |" in (tmp_path / "b" / "frozen_replay.md").read_text()


def test_instancing_keeps_an_object_whose_name_a_group_would_take():
    # a scene may name an object KEY__group or KEY__mesh: the instancing takes other keys, drops nothing
    from render2spike.render.backend import mitsuba
    from render2spike.render.frozen import instance_moving_meshes

    class Moving:
        is_static = False

        @staticmethod
        def matrix(t_s):
            return np.eye(4)
    mi = mitsuba()
    d = {"thing": {"type": "cube", "to_world": mi.ScalarTransform4f()},
         "thing__group": {"type": "sphere"}, "thing__mesh": {"type": "sphere"}}
    done = instance_moving_meshes(mi, d, {"thing": (Moving, np.eye(4))})
    assert list(done) == ["thing"] and d["thing__group"] == {"type": "sphere"} and d["thing__mesh"] == {"type": "sphere"}
    assert d["thing"]["type"] == "instance" and d["thing"]["shapegroup"]["id"] == "thing__group_2"
    assert list(d["thing__group_2"]) == ["type", "thing__mesh_2"] and d["thing__group_2"]["thing__mesh_2"]["type"] == "cube"


def test_a_camera_only_motion_updates_nothing_in_mitsuba_and_moves_the_frame(write_scene):
    # the frozen launch traces its own primary rays from the camera's pose: Mitsuba's camera is never rendered, so a
    # scene where only the camera moves leaves Mitsuba's scene as loaded, and the frame still follows the camera
    from render2spike.render.renderer import SceneRenderer
    from render2spike.render.scene import load_scene
    from tests.render.conftest import BASE
    _collect()
    cam = dict(BASE["camera"], motion={"parametric": [{"translate": {"velocity_m_s": [0.5, 0.0, 0.0]}}]})
    objects = [MOVING[0], {k: v for k, v in MOVING[1].items() if k != "motion"}]
    r = SceneRenderer(load_scene(write_scene({"objects": objects, "camera": cam,
                                              "reference": {"point": [0, 0, 0.05], "normal": [0, 0, 1]}})),
                      launch="frozen")
    assert r._moving["camera"][0] == "camera" and list(r.params.keys()) == []
    updates = []
    r.params.update = lambda *a, **k: updates.append(1)
    to_world = np.array(r.sensor.world_transform().matrix, dtype=np.float64)
    frames = {}
    for t_s in (0.0, 0.01, 0.0):
        cam_m = r._cam_m.copy()
        frames.setdefault(t_s, []).append(r.render_frame(t_s, 7, 16, variance=False)["phi"])
        if t_s:
            assert not np.allclose(r._cam_m, cam_m)  # the launch's input moved with the camera
    assert updates == []
    np.testing.assert_array_equal(np.array(r.sensor.world_transform().matrix, dtype=np.float64), to_world)
    np.testing.assert_array_equal(frames[0.0][0], frames[0.0][1])  # back at t = 0: the same frame, bit for bit
    # at 0.01 s the camera is 5 mm to the side (0.5 m/s): the cube's image moved with it, another frame
    assert not np.allclose(frames[0.0][0], frames[0.01][0])


def test_a_launch_hands_the_camera_pose_over_in_one_buffer_and_replays(write_scene):
    # A pose given as an opaque Transform4f was 32 one-value memsets a launch (its matrix and inverse transpose),
    # each an operation of its own on a GPU; one buffer of 16 float32 is one copy (4 memsets a launch in all on
    # Mitsuba 3.9.1 / Dr.Jit 1.5.0: the seed and Dr.Jit's own). The buffer is a layout drjit.freeze sees the same at
    # every launch: made from a NumPy array it was not always, and the launch was recorded again (in 5 of 40
    # processes of a 13-launch run): here 40 launches at new poses and seeds after the warm-up replay only (a guard,
    # not a proof: it caught the NumPy version in 1 of 12 runs)
    import drjit as dr
    from render2spike.render.renderer import SceneRenderer
    _collect()
    r = SceneRenderer(_scene(write_scene), launch="frozen")
    fl = r._frozen
    for k in range(6):  # recorded (once, or a few times at first), then replayed
        r.set_time(0.001 * k)
        fl.channels(fl.launch(100 + k, 16, r._cam_m))
    was = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        r.set_time(0.0065)  # (Mitsuba's update of the moved cube makes memsets of its own: not the launch's)
        dr.kernel_history()  # read = cleared
        fl.channels(fl.launch(5, 16, r._cam_m))
        hist = dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, was)
    memsets = sum(h.get("type") == dr.KernelType.Memset for h in hist)
    assert memsets < 16, (memsets, [str(h.get("type")) for h in hist])
    n = fl.n_recordings
    for k in range(40):
        r.set_time(0.0002 * k + 0.00005)
        fl.channels(fl.launch(1000 + k, 16, r._cam_m))
    assert fl.n_recordings == n, (fl.n_recordings, n)
    # and the buffer, 16 float32 row by row, is the pose: the rays of the Transform4f made from the same matrix, bit
    # for bit (that one is held against Mitsuba's camera in test_primary_rays_are_mitsubas_perspective_camera)
    mi = r.mi
    pos = mi.Vector2f(*np.random.default_rng(4).random((2, 101)))
    got = fl.primary_rays(fl.pose(mi.Float([float(x) for x in np.asarray(r._cam_m, np.float32).ravel()])), pos)
    want = fl.primary_rays(mi.Transform4f(r._cam_m.tolist()), pos)
    for a, b in zip(got, want):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_a_scene_loads_its_objects_in_one_order_so_its_kernels_hit_the_cache(write_scene):
    # The path tracer's kernel holds registry ids of the scene's objects as constants (the environment emitter's,
    # for one), so Dr.Jit's kernel cache on disk serves a later process only when its objects get the same ids.
    # Mitsuba's parallel loading made them in the order its threads happened to run (key/sky as 1/2 or 2/1 in 3 of 6
    # processes: each such run compiled the path tracer's kernels again); loaded in one thread, in the scene's order,
    # every load gives the same ids. Here four loads, each of which the parallel loader got wrong half of the time
    import drjit as dr
    from render2spike.render.renderer import SceneRenderer
    from tests.render.conftest import BASE
    lights = BASE["lights"] + [
        {"name": "fill", "type": "point", "position": [0.3, 0.2, 0.8], "strength": 0.5, "spectrum": {"blackbody_k": 4000}},
        {"name": "sky", "type": "environment", "strength": 0.02, "spectrum": {"blackbody_k": 6500}}]
    from render2spike.render.scene import load_scene
    scene = load_scene(write_scene({"lights": lights, "objects": MOVING,
                                    "reference": {"point": [0, 0, 0.05], "normal": [0, 0, 1]}}))
    seen, cal = [], None
    for _ in range(4):
        _collect()
        r = SceneRenderer(scene, launch="frozen", calibration=cal)  # the light meter once
        mi, cal = r.mi, r.calibration
        ids = [(e.id(), int(dr.reinterpret_array(mi.UInt32, mi.EmitterPtr(e))[0])) for e in r.mi_scene.emitters()]
        ids += [(s.id(), int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(s))[0])) for s in r.mi_scene.shapes()]
        seen.append(ids)
        del r, mi
    assert all(s == seen[0] for s in seen), seen


def test_a_frame_and_a_pixel_list_at_one_count_run_one_path_tracer_kernel(write_scene):
    # A first run compiles each path-tracer kernel (about 1 s each on 2 cores); the whole-frame launch goes through
    # the pixel list's gather, so the pilot's frames and the keyframes' pixel lists at one count share a kernel.
    # The whole frame's values are those of its sample index alone (the golden frames did not change)
    import drjit as dr
    from render2spike.render.renderer import SceneRenderer
    _collect()
    r = SceneRenderer(_scene(write_scene, pan=False), launch="frozen")
    fl = r._frozen
    was = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()  # read = cleared
        fl.channels(fl.launch(5, 16, r._cam_m))
        frame = dr.kernel_history()
        fl.pixel_values(fl.launch_pixels(5, 16, r._cam_m, np.arange(0, fl.height * fl.width, 3)))
        listed = dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, was)
    tracer = lambda hist: {str(h["hash"]) for h in hist if h.get("operation_count", 0) > 1000}  # noqa: E731
    assert len(tracer(frame)) == 1 and tracer(frame) == tracer(listed), (tracer(frame), tracer(listed))
