"""The procedural scene generator (render2spike.scenegen), its CLI and its dataset spec entry."""

import math

import numpy as np
import pytest

from render2spike.scenegen import DEFAULTS, MESHES, PHOTOS, PRIMITIVES, generate_scene

N = 400  # scenes drawn for the statistics below (no rendering: generation alone)


@pytest.fixture(scope="module")
def drawn():
    return [generate_scene(0, i) for i in range(N)]


def test_a_seed_and_index_give_the_same_scene_and_others_differ():
    a, b = generate_scene(3, 5), generate_scene(3, 5)
    assert a == b
    assert generate_scene(3, 6) != a and generate_scene(4, 5) != a
    assert a["generator"] == {**a["generator"], "seed": 3, "index": 5}


def test_every_scene_is_a_valid_scene_file_with_its_meshes_found():
    from render2spike.render.scene import load_scene
    with_mesh = next(d for d in (generate_scene(1, i) for i in range(50))
                     if any(o["shape"] == "mesh" for o in d["objects"]))
    for d in (generate_scene(1, 0), with_mesh):
        sc = load_scene(d)
        assert sc.profile.height == 64 and sc.profile.width == 96 and sc.name == d["name"]
    mesh = next(o for o in with_mesh["objects"] if o["shape"] == "mesh")
    assert load_scene(with_mesh).file(mesh["file"], "f").is_file()  # the bundled mesh, by its bare name


def test_counts_speeds_light_and_textures_stay_in_their_ranges(drawn):
    lo_n, hi_n = DEFAULTS["objects"]
    vmin, vmax = DEFAULTS["speed_px_per_ms"]
    px_m = 20e-6 / 8e-3  # metres per pixel at 1 m
    still = 0
    shapes, meshes, photos, kinds = set(), set(), set(), set()
    for d in drawn:
        objs = d["objects"][1:]
        assert lo_n <= len(objs) <= hi_n
        assert DEFAULTS["lux"][0] <= d["illuminance_lux"] <= DEFAULTS["lux"][1]
        cam_z = d["camera"]["position"][2]
        assert DEFAULTS["distance_m"][0] <= cam_z <= DEFAULTS["distance_m"][1]
        still += d["generator"]["still"]
        for o in objs:
            shapes.add(o["shape"])
            if o["shape"] == "mesh":
                meshes.add(o["file"])
            refl = o["material"]["reflectance"]
            if isinstance(refl, dict):
                kinds.add(refl["texture"])
                if refl["texture"] == "skimage":
                    photos.add(refl["name"])
            if d["generator"]["still"]:
                assert "motion" not in o
                continue
            vel = np.array(o["motion"]["parametric"][1]["translate"]["velocity_m_s"])
            v_px_ms = np.linalg.norm(vel) / (1000.0 * px_m * (cam_z - o["position"][2]))
            assert vmin * (1 - 1e-4) <= v_px_ms <= vmax * (1 + 1e-4)
        if "motion" in d["camera"]:
            vel = np.array(d["camera"]["motion"]["parametric"][0]["translate"]["velocity_m_s"])
            assert vmin * (1 - 1e-4) <= np.linalg.norm(vel) / (1000.0 * px_m * cam_z) <= vmax * (1 + 1e-4)
    # the still share: binomial(N, 0.2), within 4.5 standard deviations
    assert abs(still / N - DEFAULTS["still_fraction"]) < 4.5 * math.sqrt(0.2 * 0.8 / N)
    assert shapes == set(PRIMITIVES) | {"mesh"}
    assert meshes == {f"mesh_{m}.ply" for m in MESHES}
    assert kinds == {"skimage", "checker", "stripes", "noise"} and len(photos) >= len(PHOTOS) - 3


def test_options_change_the_draws_and_bad_options_name_themselves():
    from sensor.errors import InputError
    fast = [generate_scene(0, i, {"speed_px_per_ms": [2.0, 3.0], "still_fraction": 0.0}) for i in range(20)]
    # a rim point moves at the translation and the turn's rim speed together, each drawn from [2, 3]
    assert all(4.0 * (1 - 1e-4) <= d["generator"]["fastest_px_per_ms"] <= 6.0 * (1 + 1e-4) for d in fast)
    assert all(d["render"]["adaptive"]["max_rate_hz"] >= 4000 for d in fast)
    for bad, field in (({"speed_px_per_ms": [0, 1]}, "procedural.speed_px_per_ms"),
                       ({"objects": [3, 1]}, "procedural.objects"), ({"window": [300, 96]}, "procedural.window"),
                       ({"still_fraction": 1.5}, "procedural.still_fraction"), ({"colour": 1}, "procedural")):
        with pytest.raises(InputError) as e:
            generate_scene(0, 0, bad)
        assert e.value.field == field


def test_the_cli_writes_scenes_that_load_and_refuses_bad_input(cli, tmp_path):
    from render2spike.render.scene import load_scene
    out = tmp_path / "gen"
    r = cli("scenegen", "--count", "3", "--seed", "7", "--speed", "1", "2", "--out", str(out))
    assert r.returncode == 0, r.stderr
    files = sorted(out.glob("*.yaml"))
    assert [f.name for f in files] == [f"procedural_7_{i:04d}.yaml" for i in range(3)]
    assert load_scene(files[1]).data["generator"] == generate_scene(7, 1, {"speed_px_per_ms": [1.0, 2.0]})["generator"]
    assert cli("scenegen", "--count", "3", "--seed", "7", "--out", str(out)).returncode == 2  # exists
    r = cli("scenegen", "--count", "2", "--speed", "0", "2", "--out", str(tmp_path / "x"))
    assert r.returncode == 2 and "--speed" in r.stderr and not (tmp_path / "x").exists()
    r = cli("scenegen", "--count", "0", "--out", str(tmp_path / "y"))
    assert r.returncode == 2 and "--count" in r.stderr


def test_a_dataset_spec_expands_a_procedural_entry_into_its_scenes():
    from render2spike.dataset import load_spec, plan
    from sensor.errors import InputError
    spec, _ = load_spec({"scenes": [{"procedural": {"count": 4, "seed": 2, "window": [16, 24]}}, "rotating_disk"],
                         "lux": [5, 50], "models": ["elssim"]})
    assert len(spec["scenes"]) == 5 and spec["scenes"][3]["procedural"] == {
        "seed": 2, "index": 3, "options": {"window": [16, 24]}}
    assert len(plan(spec)) == 10
    with pytest.raises(InputError) as e:
        load_spec({"scenes": [{"procedural": {"count": 2, "speed_px_per_ms": [3, 1]}}]})
    assert e.value.field == "scenes.0.procedural.speed_px_per_ms"
    with pytest.raises(InputError) as e:
        load_spec({"scenes": [{"procedural": {"count": 0}}]})
    assert e.value.field == "scenes.0.procedural.count"


@pytest.mark.slow
@pytest.mark.render
def test_a_dataset_of_generated_scenes_renders_and_simulates(tmp_path):
    pytest.importorskip("mitsuba")
    from render2spike.dataset import build_dataset
    spec = {"scenes": [{"procedural": {"count": 2, "seed": 5, "window": [16, 24], "still_fraction": 0.0}}],
            "duration_s": 0.004, "lux": [5], "models": ["elssim"], "window": 20, "centers": 1, "preroll": 50}
    res = build_dataset(spec, tmp_path / "ds", workers=0, progress=False, log=lambda *a: None)
    assert res.n_done == 2 and not res.failed, res
    import json
    for sample in (tmp_path / "ds" / "samples").iterdir():
        made = json.loads((sample / "sample.json").read_text())
        assert "procedural" in json.dumps(made)  # the sample says which generated scene it is


def test_objects_move_at_the_drawn_speed_and_turn_in_place():
    """The object's own motion (builder.object_motion), sampled over the clip: its centre crosses the image at the
    drawn translation speed, in a straight line (turning about its own centre), never faster than
    generator.fastest_px_per_ms."""
    from render2spike.render.builder import object_motion
    px_m = 20e-6 / 8e-3
    checked = 0
    for i in range(60):
        d = generate_scene(2, i)
        if d["generator"]["still"]:
            continue
        cam_z = d["camera"]["position"][2]
        for j, o in enumerate(d["objects"][1:], 1):
            m = object_motion(o, f"objects.{j}.")
            ts = np.linspace(0.0, d["duration_s"], 6)
            c = np.array([m.matrix(t)[:3, 3] for t in ts])
            step = np.linalg.norm(np.diff(c[:, :2], axis=0), axis=1)
            v_img = step / np.diff(ts) / (1000.0 * px_m * (cam_z - o["position"][2]))  # px/ms
            v_drawn = np.linalg.norm(o["motion"]["parametric"][1]["translate"]["velocity_m_s"]) / (
                1000.0 * px_m * (cam_z - o["position"][2]))
            assert np.allclose(v_img, v_drawn, rtol=1e-6, atol=1e-9)
            assert np.allclose(c[:, 2], c[0, 2])  # no drift in depth
            assert v_drawn <= d["generator"]["fastest_px_per_ms"] * (1 + 1e-6)
            checked += 1
    assert checked > 50


def test_spec_errors_name_the_entry_in_the_file_and_a_loaded_spec_loads_again():
    from render2spike.dataset import _hash, load_spec
    from sensor.errors import InputError
    with pytest.raises(InputError) as e:  # entries after a procedural one keep their own numbers
        load_spec({"scenes": [{"procedural": {"count": 3}}, "rotating_disk", "rotating_disk"]})
    assert e.value.field == "scenes.2" and "scenes.1 is the same scene" in str(e.value)
    with pytest.raises(InputError) as e:
        load_spec({"scenes": [{"procedural": {"count": 2, "seed": 1}}, {"procedural": {"count": 2, "seed": 1}}]})
    assert e.value.field == "scenes.1" and "(generated scene 0)" in str(e.value)
    a, _ = load_spec({"scenes": [{"procedural": {"count": 2}}, "rotating_disk"], "duration_s": [0.02, 0.05]})
    assert a["scenes"][0]["procedural"]["options"] == {"duration_s": 0.05}  # the longest clip sizes the scene
    b, _ = load_spec(a)
    assert _hash(a) == _hash(b) and b["scene_entries"] == [[0, 0], [0, 1], [1, None]]


def test_every_generated_scene_has_its_own_render_seed():
    seeds = {generate_scene(0, i)["render"]["seed"] for i in range(50)}
    assert len(seeds) == 50
