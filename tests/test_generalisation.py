"""Cross-noise-model generalisation study: a tiny end-to-end run (2 models, a few training steps), reuse."""

import json

import numpy as np
import pytest

import sensor

pytest.importorskip("torch")


@pytest.fixture(scope="module")
def spec(tmp_path_factory):
    root = tmp_path_factory.mktemp("gen")
    H, W = 16, 16
    t = np.arange(0, 0.0241, 0.002)  # 480 intervals: warm-up 64 + 320 + stride
    yy, xx = np.mgrid[0:H, 0:W]
    base = np.stack([0.3 + 0.25 * np.sin(2 * np.pi * (xx - 300 * ti) / 8) * np.cos(2 * np.pi * yy / 7) for ti in t])
    prof = sensor.SensorProfile.load("vidar-default")
    phi = base * 900 / (prof.pixel_pitch_m ** 2 * prof.fill_factor * prof.interval_s)
    sensor.write_frames(root / "frames", phi.astype(np.float32), t, manifest={"illuminance_lux": 100.0})
    p = root / "spec.json"
    p.write_text(json.dumps({"scenes": [{"frames": str(root / "frames"), "profile": "vidar-default"}],
                             "lux": [10, 40, 100]}))
    return p


def test_matrix_of_train_and_test_models(spec, tmp_path):
    from render2spike.studies.generalisation import run_generalisation_study
    kw = dict(train_models=["ideal", "elssim"], test_models=["ideal", "isi", "elssim"], steps=2, batch_size=2,
              width=8, warmup=64, stride=96, threads=1, progress=False, log=lambda *a: None)
    res = run_generalisation_study(spec, tmp_path, **kw)
    m = res["matrix"]
    # 2 networks + the default baselines (tfp-dt and the strongest classic, tfp-dt-denoised), each on 3 test models
    assert len(m) == 4 * 3 and {r["test_model"] for r in m} == {"ideal", "isi", "elssim"}
    assert {r["method"] for r in m} >= {"TFP dead-time corrected", "TFP-DT + Gaussian (tuned)"}
    assert all(r["n_items"] == m[0]["n_items"] > 1 and np.isfinite(r["psnr_db"]) for r in m)
    md = (tmp_path / "matrix.md").read_text()
    assert "| net trained on elssim |" in md and "±" in md
    assert (tmp_path / "heatmap.png").stat().st_size > 1000
    # the baseline sees the same test items for every model: same frames, so the same targets
    per_item = (tmp_path / "per_item.csv").read_text().splitlines()
    assert len(per_item) == 1 + 12 * m[0]["n_items"]
    # a second run reuses the trained networks
    mtime = (tmp_path / "nets" / "ideal" / "model.pt").stat().st_mtime_ns
    res2 = run_generalisation_study(spec, tmp_path, **kw)
    assert (tmp_path / "nets" / "ideal" / "model.pt").stat().st_mtime_ns == mtime
    assert [r["psnr_db"] for r in res2["matrix"]] == pytest.approx([r["psnr_db"] for r in m])


def test_errors_name_the_option(spec, tmp_path):
    from render2spike.studies.generalisation import run_generalisation_study, split_samples
    with pytest.raises(sensor.InputError, match="reuse"):
        run_generalisation_study(spec, tmp_path, reuse=["davis=x.pt"])
    with pytest.raises(sensor.InputError, match="at least 2"):
        split_samples(["a"], 0.25)
    assert split_samples(list("abcdefgh"), 0.25) == (list("abcdef"), ["g", "h"])
