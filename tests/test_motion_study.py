"""Motion sweep: blur width of known blurs (straight and polar), parameter checks, and a tiny end-to-end sweep."""

import numpy as np
import pytest

import sensor
from render2spike.studies.motion import edge_spread, parse_param


def _box_blur_x(img, w):
    from scipy.ndimage import convolve1d
    return convolve1d(img, np.ones(w) / w, axis=1, mode="nearest")


@pytest.mark.parametrize("w", [1, 4, 9])
def test_blur_width_of_a_box_blurred_moving_edge(w):
    H, W = 24, 64
    xx = np.arange(W)[None, :].repeat(H, 0).astype(float)
    edge = 30 + (np.arange(H)[:, None] % 3)  # edges at slightly different places per row
    clean = (xx >= edge).astype(float) * 0.8 + 0.1
    moved = ((xx >= edge + 2).astype(float) - (xx >= edge - 2)) * 0.8  # the edge moves along x
    out = edge_spread({"blurred": _box_blur_x(clean, w), "clean": clean}, clean, moved, "x")
    # a box of w pixels rises from 10 % to 90 % over 0.8 w, sampled at whole pixels: within half a pixel
    assert out["lines_used"] == H
    assert abs(out["blurred"] - 0.8 * w) <= 0.5 + 1e-9 and out["clean"] <= 1.0


def test_blur_width_along_circles():
    H = W = 64
    yy, xx = np.mgrid[0:H, 0:W] - (H - 1) / 2
    ang = np.arctan2(yy, xx)
    clean = 0.1 + 0.8 * (np.mod(ang, 2 * np.pi / 4) < np.pi / 4)  # 8 sectors
    # rotation blur: average over angles +-da, i.e. an arc of r * 2 da pixels at radius r
    da = 0.15
    avg = np.mean([0.1 + 0.8 * (np.mod(ang + d, 2 * np.pi / 4) < np.pi / 4) for d in np.linspace(-da, da, 61)], 0)
    shifted = 0.1 + 0.8 * (np.mod(ang + 0.05, 2 * np.pi / 4) < np.pi / 4)
    out = edge_spread({"avg": avg, "clean": clean}, clean, shifted - clean, "polar", radius=8)
    assert out["lines_used"] > 10
    assert out["avg"] > out["clean"] + 2 and out["clean"] < 2


def test_parameter_errors():
    assert parse_param("speed_px_per_ms=0.1,0.5") == ("speed_px_per_ms", [0.1, 0.5])
    for bad in ("speed", "speed=", "speed=fast"):
        with pytest.raises(sensor.InputError, match="param"):
            parse_param(bad)


def test_tiny_sweep_end_to_end(tmp_path):
    pytest.importorskip("mitsuba")
    from render2spike.studies.motion import run_motion_study
    sets = ["camera.profile.window=[110,160,16,24]", "render.spp=4", "render.meter_spp=256",
            "render.adaptive.enabled=false", "render.keyframe_rate_hz=500"]
    with pytest.raises(sensor.InputError, match="neither a named parameter"):
        run_motion_study("translating_object", "camera.profile", [1], tmp_path, sets=sets)
    res = run_motion_study("translating_object", "speed_px_per_ms", [0.1, 0.8], tmp_path, methods="tfp",
                           seeds=(0, 1), duration_s=0.012, sets=sets, window=160, preroll=200, progress=False,
                           log=lambda *a: None)
    text = (tmp_path / "summary.md").read_text()
    assert "noise-free window average" in text and "TFP (M=160)" in text
    for name in ("psnr", "ssim", "blur"):
        assert (tmp_path / f"{name}_vs_speed_px_per_ms.png").stat().st_size > 1000
    assert (tmp_path / "strip.png").is_file() and len(list((tmp_path / "renders").iterdir())) == 2
    rows = [r for r in res["summary"] if r["method"] == "TFP (M=160)"]
    assert len(rows) == 2 and all(r["n_seeds"] == 2 for r in rows)
