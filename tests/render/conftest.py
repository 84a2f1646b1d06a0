"""Helpers for the render-stage tests: tiny scenes written on the fly."""

import copy

import pytest
import yaml

#: a 32 x 48 camera 1 m above/in front of the origin, 20 um pixels, f = 8 mm (2.5 mm per pixel at 1 m)
BASE = {
    "format": "render2spike-scene",
    "name": "tiny",
    "duration_s": 0.01,
    "illuminance_lux": 100.0,
    "reference": {"point": [0, 0, 0], "normal": [0, 0, 1]},
    "camera": {"profile": {"synthetic": {"height": 32, "width": 48, "threshold_e": 2000.0, "seed": 0}},
               "focal_length_mm": 8.0, "f_number": 2.0, "transmission": 0.9,
               "position": [0, 0, 1.0], "look_at": [0, 0, 0], "up": [0, 1, 0]},
    "lights": [{"name": "sun", "type": "directional", "direction": [0, 0, -1], "strength": 1.0,
                "spectrum": {"blackbody_k": 5000}}],
    "objects": [{"name": "plane", "shape": "rectangle", "size": [10, 10], "material": {"reflectance": 0.5}}],
    "render": {"keyframe_rate_hz": 200, "max_depth": 2},
}


@pytest.fixture
def write_scene(tmp_path):
    """write_scene(changes: dict | None, name) -> path of a YAML scene based on BASE with top-level changes."""
    def _write(changes=None, name="scene.yaml", base=None):
        d = copy.deepcopy(BASE if base is None else base)
        for k, v in (changes or {}).items():
            d[k] = v
        p = tmp_path / name
        p.write_text(yaml.safe_dump(d, sort_keys=False))
        return p
    return _write


def have_mitsuba():
    try:
        import mitsuba  # noqa: F401
        return True
    except ImportError:
        return False


needs_mitsuba = pytest.mark.skipif(not have_mitsuba(), reason="Mitsuba 3 not installed")


def film_and_frozen_frames(scene, key, times=(0.0, 0.006), spp=64):
    """Frames of ``scene`` at ``times`` from the film launch (seed 1) and then the frozen launch (seed 2, the
    film's light-level measurement), each with its per-pixel variance estimate; checks that the frozen launch
    moves object ``key`` as an instance. The film renderer is let go of (and collected) before the frozen one
    records: a live film scene breaks ``drjit.freeze`` (test_frozen_launch)."""
    import gc

    from render2spike.render.renderer import SceneRenderer
    film = SceneRenderer(scene, launch="film")
    cal = film.calibration
    fa = [film.render_frame(t, 1, spp, variance=True) for t in times]
    del film
    gc.collect()
    r = SceneRenderer(scene, launch="frozen", calibration=cal)
    assert r._moving[key][0] == "instance"
    return fa, [r.render_frame(t, 2, spp, variance=True) for t in times]


def assert_image_means_agree(fa, fb, z_max=4.5):
    """Pairs of frames (same times, independent seeds) whose image means of ``phi`` agree.

    z: a difference of two image means, in units of its standard deviation estimated from one per-pixel
    variance estimate per pixel of each frame (over the whole image: near normal); |z| > 4.5 has probability
    7e-6 if they agree."""
    import numpy as np
    for a, b in zip(fa, fb):
        n = a["phi"].size
        sd = np.sqrt((a["phi_var"].sum() + b["phi_var"].sum()) / n ** 2)
        z = (a["phi"].mean() - b["phi"].mean()) / sd
        assert abs(z) < z_max, (a["time_s"], z)
