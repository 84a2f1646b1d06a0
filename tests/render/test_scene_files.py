"""Scene files: schema validation, clear errors, overrides, bundled scenes (no rendering)."""


import pytest

from render2spike.render.scene import SCENES_DIR, apply_overrides, load_scene
from sensor.errors import InputError


def test_bundled_scenes_validate():
    names = sorted(p.stem for p in SCENES_DIR.glob("*.yaml"))
    assert {"rotating_disk", "translating_object", "room_pan", "lambertian_plane"} <= set(names)
    for n in names:
        sc = load_scene(n)
        assert sc.illuminance_lux > 0 and sc.duration_s > 0
        assert sc.profile.height > 0


def test_bundled_moving_scenes_move():
    from render2spike.render.builder import camera_motion, object_motion
    for n, key in (("rotating_disk", "disk"), ("translating_object", "cube")):
        sc = load_scene(n)
        i = [o["name"] for o in sc.data["objects"]].index(key)
        assert not object_motion(sc.data["objects"][i], "").is_static
    assert not camera_motion(load_scene("room_pan").camera).is_static


@pytest.mark.parametrize("changes, field, words", [
    ({"colour": 3}, "(top level)", "Additional properties"),
    ({"illuminance_lux": "bright"}, "illuminance_lux", "not of type"),
    ({"illuminance_lux": -1}, "illuminance_lux", "minimum"),
    ({"lights": [{"type": "laser"}]}, "lights.0.type", "not one of"),
    ({"lights": [{"type": "directional"}]}, "lights.0", "direction"),
    ({"reference": {"point": [0, 0]}}, "reference.point", "too short"),
    ({"objects": [{"name": "p", "shape": "rectangle", "material": {"reflectance": 2}}]},
     "objects.0.material.reflectance", ""),
])
def test_bad_scene_names_file_and_key(write_scene, changes, field, words):
    p = write_scene(changes)
    with pytest.raises(InputError) as ei:
        load_scene(p)
    msg = str(ei.value)
    assert str(p) in msg, msg
    assert f"field '{field}'" in msg, msg
    assert words in msg, msg


def test_missing_camera_and_reference(write_scene):
    from tests.render.conftest import BASE
    base = dict(BASE)
    base.pop("camera")
    with pytest.raises(InputError, match="'camera' is required"):
        load_scene(write_scene(base=base))
    base = dict(BASE)
    base.pop("reference")
    with pytest.raises(InputError, match="reference"):
        load_scene(write_scene(base=base))


def test_invalid_yaml_and_missing_file(tmp_path):
    p = tmp_path / "broken.yaml"
    p.write_text("camera: [1, 2\n  oops: {")
    with pytest.raises(InputError, match="not valid YAML at line"):
        load_scene(p)
    with pytest.raises(InputError, match="scene file not found"):
        load_scene(tmp_path / "nope.yaml")


def test_missing_mesh_file_and_unknown_reference(write_scene):
    p = write_scene({"objects": [{"name": "m", "shape": "mesh", "file": "nothere.ply"}]})
    with pytest.raises(InputError, match="nothere.ply"):
        load_scene(p)
    p = write_scene({"reference": {"object": "ghost"}})
    with pytest.raises(InputError, match="no object named 'ghost'"):
        load_scene(p)


def test_overrides_by_index_and_name():
    d = {"render": {"spp": 4}, "objects": [{"name": "a", "position": [0, 0, 0]}, {"name": "b"}]}
    out = apply_overrides(d, ["render.spp=32", "objects.b.position=[1, 2, 3]", "objects.0.name=c"])
    assert out["render"]["spp"] == 32 and out["objects"][1]["position"] == [1, 2, 3] and out["objects"][0]["name"] == "c"
    assert d["render"]["spp"] == 4  # the input is not modified
    with pytest.raises(InputError, match="no list item 'zz'"):
        apply_overrides(d, ["objects.zz.position=[0,0,0]"])
    with pytest.raises(InputError, match="key=value"):
        apply_overrides(d, ["render.spp"])


def test_set_then_validate(write_scene):
    p = write_scene()
    with pytest.raises(InputError, match="render.spp"):
        load_scene(p, ["render.spp=many"])
    sc = load_scene(p, ["render.spp=16"], lux=3.0)
    assert sc.render["spp"] == 16 and sc.illuminance_lux == 3.0


def test_hash_changes_with_scene_and_settings(write_scene):
    p = write_scene()
    h = load_scene(p).content_hash({"variant": "x"})
    assert h == load_scene(p).content_hash({"variant": "x"})
    assert h != load_scene(p, lux=5).content_hash({"variant": "x"})
    assert h != load_scene(p).content_hash({"variant": "y"})
