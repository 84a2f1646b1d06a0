"""The render loop's cheaper paths: launches made before they are waited for, a pilot render reused as the first
frame's verification render, set_time at an unchanged time, the writer's on_stop, JSON in one buffer."""

import json
import os

import numpy as np
import pytest

from render2spike.render.writer import FrameWriter
from tests.render.conftest import needs_mitsuba

MOVING = [
    {"name": "back", "shape": "rectangle", "size": [10, 10], "position": [0, 0, -0.5], "material": {"reflectance": 0.3}},
    {"name": "thing", "shape": "cube", "size": [0.02, 0.02, 0.02], "position": [0, 0, 0], "material": {"reflectance": 0.8},
     "motion": {"parametric": [{"translate": {"velocity_m_s": [0.25, 0.1, 0.0]}}]}},
]


def _renderer(write_scene, objects=None):
    from render2spike.render.renderer import SceneRenderer
    from render2spike.render.scene import load_scene
    changes = {"objects": objects, "reference": {"point": [0, 0, 0.05], "normal": [0, 0, 1]}} if objects else None
    return SceneRenderer(load_scene(write_scene(changes)), launch="film")  # the film launch's own paths


@needs_mitsuba
def test_frame_with_verification_is_the_frame_without_and_both_launches_precede_the_wait(write_scene):
    r = _renderer(write_scene, MOVING)
    seen = []
    n0 = r.n_launches
    orig = r.channels

    def channels(img):  # the first wait for a kernel comes after both launches
        seen.append(r.n_launches - n0)
        return orig(img)
    r.channels = channels
    f = r.render_frame(0.004, 7, 16, variance=True)
    del r.channels
    assert seen == [2, 2] and r.n_launches - n0 == 2
    g = r.render_frame(0.004, 7, 16, variance=False)
    np.testing.assert_array_equal(f["phi"], g["phi"])
    np.testing.assert_array_equal(f["lux"], g["lux"])
    # the second render is the old path's: an independent render with the variance seeds
    from render2spike.render.photometry import to_physical
    pa, _ = r.render_raw(0.004, f["seeds"][0], 16)
    pb, _ = r.render_raw(0.004, f["variance_seeds"][0], 16)
    fp, _ = to_physical(1.0, 1.0, r.k, r.f_number, r.transmission, r.cos4)
    np.testing.assert_array_equal(f["phi_var"], (pa - pb) ** 2 / 2.0 * fp ** 2)


@needs_mitsuba
def test_the_render_call_is_bitwise_mi_render_for_the_same_seed_and_spp(write_scene):
    # the renderer calls the integrator without mi.render's differentiable wrapper: the same film, moving scene,
    # two times, two seeds, a split spp's part (1) and a stratified count
    r = _renderer(write_scene, MOVING)
    for t_s, seed, spp in ((0.0, 7, 16), (0.013, 123456789, 16), (0.013, 5, 1), (0.02, 42, 64)):
        r.set_time(t_s)
        ours = np.asarray(r._render_call(seed, spp))
        ref = np.asarray(r.mi.render(r.mi_scene, sensor=r.sensor, seed=seed, spp=spp))
        assert ours.shape == ref.shape and ours.dtype == ref.dtype
        assert np.array_equal(ours, ref), (t_s, seed, spp)
        assert ours.mean() > 0


@needs_mitsuba
def test_a_kept_pilot_render_is_the_first_verified_frames_second_render(write_scene):
    from render2spike.render.photometry import to_physical
    r = _renderer(write_scene)
    with r.keep_renders():
        kept_p, _ = r.render_raw(0.0, 12345, 16)
        r.render_raw(0.0, 999, 4)  # another spp: not used
    n0 = r.n_launches
    f = r.render_frame(0.0, 3, 16, variance=True)
    assert r.n_launches - n0 == 1 and f["variance_seeds"] == [12345]  # no launch added
    raw_a, _ = r.render_raw(0.0, f["seeds"][0], 16)
    fp, _ = to_physical(1.0, 1.0, r.k, r.f_number, r.transmission, r.cos4)
    np.testing.assert_array_equal(f["phi_var"], (raw_a - kept_p) ** 2 / 2.0 * fp ** 2)
    # only the first verified frame is offered the kept renders; later ones launch their own
    n0 = r.n_launches
    g = r.render_frame(0.0, 4, 16, variance=True)
    assert r.n_launches - n0 == 2 and g["variance_seeds"] != [12345]


@needs_mitsuba
def test_kept_render_at_another_time_or_a_split_spp_is_not_reused(write_scene):
    r = _renderer(write_scene)
    with r.keep_renders():
        r.render_raw(0.0, 12345, 16)
    n0 = r.n_launches
    r.render_frame(0.001, 3, 16, variance=True)  # another time: its own second launch
    assert r.n_launches - n0 == 2
    assert len(r.launch_counts(17)) == 2
    with r.keep_renders():
        r.render_raw(0.0, 12345, 17)
    n0 = r.n_launches
    r.render_frame(0.0, 3, 17, variance=True)  # 17 spp takes two launches: nothing kept matches
    assert r.n_launches - n0 == 4


@needs_mitsuba
def test_set_time_at_the_time_already_set_does_not_update_the_scene(write_scene, monkeypatch):
    r = _renderer(write_scene, MOVING)
    updates = []
    orig = r.params.update
    monkeypatch.setattr(r.params, "update", lambda *a, **k: (updates.append(1), orig(*a, **k))[1])
    r.set_time(0.003)
    r.set_time(0.003)
    assert len(updates) == 1
    r.set_time(0.004)
    assert len(updates) == 2
    # and a frame rendered after a skipped update is the frame rendered after a fresh one
    a = r.render_frame(0.004, 1, 16, variance=False)["phi"]
    r.set_time(0.0)
    b = r.render_frame(0.004, 1, 16, variance=False)["phi"]
    np.testing.assert_array_equal(a, b)


def test_writer_on_stop_runs_in_the_thread_after_the_last_frame(tmp_path):
    import threading
    order = []
    main = threading.get_ident()
    w = FrameWriter(on_written=lambda rec: order.append(rec),
                    on_stop=lambda: order.append(("stop", threading.get_ident() != main)))
    for i in range(3):
        w.submit(tmp_path / f"f{i}.exr", np.zeros((2, 3), np.float32), None, time_s=0.0, record=i)
    w.stop()
    with pytest.raises(RuntimeError, match="after close"):
        w.submit(tmp_path / "late.exr", np.zeros((2, 3), np.float32), None, time_s=0.0)
    w.close()
    assert order == [0, 1, 2, ("stop", True)]


def test_writer_on_stop_is_skipped_after_an_error_and_its_own_error_is_raised(tmp_path):
    calls = []

    def bad_write(*a, **k):
        raise OSError("no")
    w = FrameWriter(write=bad_write, on_stop=lambda: calls.append(1))
    w.submit(tmp_path / "f.exr", np.zeros((2, 3), np.float32), None, time_s=0.0)
    with pytest.raises(OSError, match="no"):
        w.close()
    assert calls == []
    boom = ValueError("journal")

    def stop():
        raise boom
    w = FrameWriter(on_stop=stop)
    with pytest.raises(ValueError) as err:
        w.close()
    assert err.value is boom


def test_write_json_atomic_writes_the_indented_text_with_the_usual_permissions(tmp_path):
    from sensor.io.fileio import write_json_atomic
    obj = {"a": [1, 2.5, None], "b": {"c": "é"}, "d": np.float64(0.1), "e": np.arange(3)}
    p = write_json_atomic(tmp_path / "x.json", obj)
    want = json.dumps({"a": [1, 2.5, None], "b": {"c": "é"}, "d": 0.1, "e": [0, 1, 2]}, indent=2) + "\n"
    assert p.read_bytes() == want.encode("ascii")
    umask = os.umask(0)
    os.umask(umask)
    assert (p.stat().st_mode & 0o777) == (0o666 & ~umask)
    assert [q.name for q in tmp_path.iterdir()] == ["x.json"]  # no temp file beside it


@needs_mitsuba
@pytest.mark.parametrize("spp", [16, "auto"])
def test_render_job_reuses_the_pilot_render_for_its_first_verification_only_with_a_fixed_spp(
        write_scene, tmp_path, monkeypatch, spp):
    """A fixed spp: the first frame's verification takes the pilot's t = 0 render at that spp (no launch).
    spp = auto: the snapping chose the spp on those pairs, so the verification launches its own render."""
    from render2spike.render import renderer as rmod
    from render2spike.render.job import render_scene
    from render2spike.render.scene import load_scene
    import copy
    from tests.render.conftest import BASE
    render = copy.deepcopy(BASE["render"])
    # whole keyframes (a still scene would otherwise reuse one static frame, which has no pilot render to take)
    render.update(spp=spp, adaptive={"enabled": False}, static_reuse=False)
    sc = load_scene(write_scene({"render": render, "duration_s": 0.01}))
    frames = {"n": 0}
    orig = rmod.SceneRenderer.render_frame

    def counting(self, *a, **k):
        if frames["n"] == 0:
            frames["launches0"] = self.n_launches
            frames["rnd"] = self
        frames["n"] += 1
        return orig(self, *a, **k)
    monkeypatch.setattr(rmod.SceneRenderer, "render_frame", counting)
    res = render_scene(sc, tmp_path / "out", progress=False, log=lambda *a: None)
    rnd = frames["rnd"]
    per_frame = len(rnd.launch_counts(res.spp))
    extra = (rnd.n_launches - frames["launches0"]) // per_frame - res.n_frames
    ratios = [f for f in json.loads((tmp_path / "out" / "frames.json").read_text())["frames"]]
    assert res.n_frames == frames["n"] == len(ratios) == 3
    if spp == 16:
        assert extra == 0
    else:
        assert extra == 1 and per_frame == 1
    # the first frame carries a measured ratio either way
    from sensor.io.frames import read_frame
    assert np.isfinite(read_frame(tmp_path / "out" / ratios[0]["file"]).header["render_noise_ratio"])


#: moving objects whose names share a prefix with each other and with a static one, whose name an unescaped pattern
#: of the first one's parameter ("thing.to_world") would match
PREFIXED = [
    {"name": "back", "shape": "rectangle", "size": [10, 10], "position": [0, 0, -0.5], "material": {"reflectance": 0.3}},
    {"name": "thing", "shape": "cube", "size": [0.02, 0.02, 0.02], "position": [0, 0, 0], "material": {"reflectance": 0.8},
     "motion": {"parametric": [{"translate": {"velocity_m_s": [0.25, 0.1, 0.0]}}]}},
    {"name": "thing2", "shape": "rectangle", "size": [0.02, 0.02], "position": [0.03, 0, 0],
     "material": {"reflectance": 0.6}, "motion": {"parametric": [{"translate": {"velocity_m_s": [0.0, 0.2, 0.0]}}]}},
    {"name": "thing_to_world", "shape": "cube", "size": [0.02, 0.02, 0.02], "position": [-0.03, 0, 0],
     "material": {"reflectance": 0.5}},
]


@needs_mitsuba
@pytest.mark.parametrize("launch", ["film", "frozen"])
def test_set_time_keeps_and_writes_exactly_the_moving_objects_parameters(write_scene, launch):
    # Mitsuba's update walks every parameter the renderer holds: it holds exactly those set_time writes (names that
    # share a prefix, or that a regular expression would read otherwise, kept or dropped by their whole name)
    from render2spike.render.renderer import SceneRenderer
    from render2spike.render.scene import load_scene
    sc = load_scene(write_scene({"objects": PREFIXED, "reference": {"point": [0, 0, 0.05], "normal": [0, 0, 1]}}))
    r = SceneRenderer(sc, launch=launch)
    want = {"thing.vertex_positions", "thing.vertex_normals", "thing2.to_world"} if launch == "film" else \
        {"thing.to_world", "thing2.to_world"}  # the frozen launch moves the cube as an instance
    assert set(r.params.keys()) == want
    def value(k, r=r):  # a transform's matrix or a buffer, as float64 numbers
        v = r.params[k]
        return np.array(v.matrix if hasattr(v, "matrix") else v, dtype=np.float64).ravel()
    before = {k: value(k) for k in want if k.endswith(("positions", "to_world"))}
    r.set_time(0.008)
    for k, v in before.items():  # the new poses reached the kept parameters (a translation keeps the normals)
        assert not np.array_equal(value(k), v), k
    # each moving object is where its motion puts it: the frame at 0.008 s is the frame of a fresh renderer at that time
    a = r.render_frame(0.008, 5, 16, variance=False)["phi"]
    del r
    import gc
    gc.collect()
    fresh = SceneRenderer(sc, launch=launch)
    b = fresh.render_frame(0.008, 5, 16, variance=False)["phi"]
    np.testing.assert_array_equal(a, b)


@needs_mitsuba
def test_a_parameter_read_at_load_but_not_written_is_dropped_safely(write_scene, monkeypatch):
    # Mitsuba checks every parameter read since its last update at the next one: a mesh whose loaded normals were
    # read but are not carried (their key dropped from the kept parameters) must not make set_time look for them
    from render2spike.render import renderer as rmod
    orig = rmod._mesh_local_frame

    def read_normals_carry_none(params, key, m0, carry):
        params[f"{key}.vertex_normals"]  # read, as when a mesh's normals do not fit its vertices
        return orig(params, key, m0, False)
    monkeypatch.setattr(rmod, "_mesh_local_frame", read_normals_carry_none)
    r = _renderer(write_scene, MOVING)
    assert set(r.params.keys()) == {"thing.vertex_positions"}
    r.set_time(0.004)  # no KeyError for the dropped normals
    assert np.isfinite(r.render_frame(0.004, 1, 16, variance=False)["phi"]).all()
