"""Motion in rendered frames: an object at known speed is where the pinhole model puts it."""

import numpy as np
import pytest

from tests.render.conftest import needs_mitsuba

pytestmark = [pytest.mark.render, needs_mitsuba]

F_MM, PITCH, DIST = 8.0, 20e-6, 1.0


def predicted_px(x_m, y_m, H, W):
    """Pinhole: scene point (x, y) at distance d -> (row, col) of pixel centres (row 0 at the top)."""
    s = F_MM * 1e-3 / (DIST * PITCH)  # pixels per metre at distance d
    return H / 2 - 0.5 - y_m * s, W / 2 - 0.5 + x_m * s


def centroid(img):
    w = np.clip(img, 0, None)
    r, c = np.indices(img.shape)
    return (w * r).sum() / w.sum(), (w * c).sum() / w.sum()


@pytest.mark.parametrize("shape", ["cube", "rectangle"])  # cube: vertex updates; rectangle: to_world updates
def test_moving_object_centroid(write_scene, shape):
    from render2spike.render.renderer import SceneRenderer
    from render2spike.render.scene import load_scene
    v = np.array([0.25, 0.1, 0.0])  # m/s -> 100 px/s right, 40 px/s up
    x0 = np.array([-0.01, -0.005, 0.0])
    size = [0.02, 0.02, 0.02] if shape == "cube" else [0.02, 0.02]
    p = write_scene({
        "objects": [
            {"name": "back", "shape": "rectangle", "size": [10, 10], "position": [0, 0, -0.5],
             "material": {"reflectance": 0.0}},
            {"name": "thing", "shape": shape, "size": size, "position": x0.tolist(), "material": {"reflectance": 0.8},
             "motion": {"parametric": [{"translate": {"velocity_m_s": v.tolist()}, "start_s": 0.002}]}},
        ],
        "reference": {"point": [0, 0, 0.05], "normal": [0, 0, 1]},
    })
    r = SceneRenderer(load_scene(p))
    H, W = r.height, r.width
    for t in (0.0, 0.002, 0.012, 0.03):
        img = r.render_frame(t, 0, 16)["lux"]
        pos = x0 + v * max(0.0, t - 0.002)
        if shape == "cube":
            pos = pos + np.array([0, 0, 0.01])  # the front face is 1 cm nearer: same x, y in a centred view
        rr, cc = predicted_px(pos[0], pos[1], H, W) if shape == "rectangle" else \
            predicted_px(pos[0] * DIST / (DIST - 0.01), pos[1] * DIST / (DIST - 0.01), H, W)
        mr, mc = centroid(img)
        # box-filtered square: the intensity centroid is exact up to MC noise (< 0.05 px at 16 spp)
        assert abs(mr - rr) < 0.5 and abs(mc - cc) < 0.5, (t, (mr, mc), (rr, cc))


def test_camera_pan_moves_the_image(write_scene):
    """Yawing the camera left by omega*t shifts a static object right by f*tan(omega t)/pitch pixels."""
    from render2spike.render.renderer import SceneRenderer
    from render2spike.render.scene import load_scene
    cam = {"profile": {"synthetic": {"height": 32, "width": 48, "threshold_e": 2000.0, "seed": 0}},
           "focal_length_mm": F_MM, "f_number": 2.0, "transmission": 0.9,
           "position": [0, 0, 1.0], "look_at": [0, 0, 0], "up": [0, 1, 0],
           "motion": {"parametric": [{"rotate": {"axis": [0, 1, 0], "omega_rad_s": 0.5}}]}}
    p = write_scene({"camera": cam, "objects": [
        {"name": "back", "shape": "rectangle", "size": [10, 10], "position": [0, 0, -0.5],
         "material": {"reflectance": 0.0}},
        {"name": "tag", "shape": "rectangle", "size": [0.02, 0.02], "material": {"reflectance": 0.8}}],
        "reference": {"point": [0, 0, 0.05], "normal": [0, 0, 1]}})
    r = SceneRenderer(load_scene(p))
    t = 0.01
    img = r.render_frame(t, 0, 16)["lux"]
    _, mc = centroid(img)
    # rotating the camera by +omega t about +y (counter-clockwise seen from above) turns it to the left;
    # the object then appears right of centre at f tan(omega t) on the sensor
    expect = r.width / 2 - 0.5 + F_MM * 1e-3 * np.tan(0.5 * t) / PITCH
    assert abs(mc - expect) < 0.5, (mc, expect)


def test_moving_ply_mesh(tmp_path, write_scene):
    """A PLY mesh (checked with trimesh) lands where the pinhole model says as it moves (moved by vertex updates in
    the film launch, as an instance in the frozen one, the default on LLVM and CUDA)."""
    import trimesh

    from render2spike.render.renderer import SceneRenderer
    from render2spike.render.scene import load_scene
    trimesh.creation.box(extents=[0.02, 0.02, 0.001]).export(tmp_path / "tile.ply")
    v = [0.0, -0.25, 0.0]
    p = write_scene({"objects": [
        {"name": "back", "shape": "rectangle", "size": [10, 10], "position": [0, 0, -0.5],
         "material": {"reflectance": 0.0}},
        {"name": "tile", "shape": "mesh", "file": "tile.ply", "material": {"reflectance": 0.8},
         "motion": {"parametric": [{"translate": {"velocity_m_s": v}}]}}],
        "reference": {"point": [0, 0, 0.05], "normal": [0, 0, 1]}})
    r = SceneRenderer(load_scene(p))
    for t in (0.0, 0.02):
        mr, mc = centroid(r.render_frame(t, 0, 16)["lux"])
        d = DIST - 0.0005  # the tile's front face
        er, ec = predicted_px(0.0, v[1] * t * DIST / d, r.height, r.width)
        assert abs(mr - er) < 0.5 and abs(mc - ec) < 0.5, (t, (mr, mc), (er, ec))
