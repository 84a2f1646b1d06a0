"""render2spike dataset: spec validation, seeded plans, byte-identical samples on 1 and 2 Dask workers,
resume after a kill, failures reported, one render per scene for every lux, rendered:DIR for training."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import sensor
from render2spike.dataset import build_dataset, load_spec, plan

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    folder = tmp_path_factory.mktemp("ds") / "frames"
    H, W = 8, 12
    t = np.arange(0, 0.0181, 0.002)  # 360 intervals
    yy, xx = np.mgrid[0:H, 0:W]
    base = np.stack([0.3 + 0.25 * np.sin(2 * np.pi * (xx - 300 * ti) / 12) for ti in t]) + 0 * yy
    prof = sensor.SensorProfile.load("vidar-default")
    phi = base * 900 / (prof.pixel_pitch_m ** 2 * prof.fill_factor * prof.interval_s)
    sensor.write_frames(folder, phi.astype(np.float32), t, manifest={"illuminance_lux": 100.0})
    return folder


def _spec(frames, **kw):
    d = {"scenes": [{"frames": str(frames), "profile": "vidar-default"}], "lux": [5, 50],
         "models": ["elssim", "isi"], "seeds": [0, 1], "window": 64, "centers": 2, "preroll": 100}
    d.update(kw)
    return d


def _contents(root: Path) -> dict:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted((root / "samples").rglob("*")) if p.is_file()}


def test_same_spec_same_bytes_on_1_and_2_workers(frames, tmp_path):
    distributed = pytest.importorskip("dask.distributed")
    got = {}
    for n in (1, 2):
        with distributed.Client(processes=False, n_workers=n, threads_per_worker=1, dashboard_address=None) as c:
            res = build_dataset(_spec(frames), tmp_path / f"w{n}", client=c, progress=False, log=lambda *a: None)
        assert res.n_done == res.n_samples == 8 and not res.failed
        got[n] = _contents(tmp_path / f"w{n}")
    assert len(got[1]) >= 8 * 4 and got[1] == got[2]
    # and without Dask, in this process
    build_dataset(_spec(frames), tmp_path / "w0", workers=0, progress=False, log=lambda *a: None)
    assert _contents(tmp_path / "w0") == got[1]


def test_killed_run_resumes_without_redoing_finished_samples(frames, tmp_path):
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps(_spec(frames)))
    out = tmp_path / "out"
    env = dict(os.environ, PYTHONPATH=str(ROOT), RENDER2SPIKE_DATASET_KILL_AFTER="3")
    p = subprocess.run([sys.executable, "-m", "render2spike", "dataset", str(spec), "--out", str(out), "--workers",
                        "0", "--quiet"], env=env, capture_output=True, text=True, timeout=120)
    assert p.returncode == -9, p.stderr[-2000:]  # SIGKILL
    man = json.loads((out / "manifest.json").read_text())
    done = [sid for sid, r in man["samples"].items() if r["status"] == "done"]
    assert len(done) == 3
    stamps = {sid: (out / "samples" / sid / "spikes.npz").stat().st_mtime_ns for sid in done}
    res = build_dataset(str(spec), out, workers=0, progress=False, log=lambda *a: None)
    assert (res.n_skipped, res.n_made, res.n_done) == (3, 5, 8)
    assert {sid: (out / "samples" / sid / "spikes.npz").stat().st_mtime_ns for sid in done} == stamps
    fresh = tmp_path / "fresh"
    build_dataset(str(spec), fresh, workers=0, progress=False, log=lambda *a: None)
    assert _contents(out) == _contents(fresh)
    assert not list((out / "samples").glob(".tmp-*"))


def test_failures_are_retried_then_reported(frames, tmp_path):
    import shutil
    broken = tmp_path / "broken"
    shutil.copytree(frames, broken)
    exr = sorted(broken.glob("*.exr"))[3]
    exr.write_bytes(exr.read_bytes()[:100])  # the spec checks pass; reading this frame fails in the sample
    res = build_dataset(_spec(broken, models=["elssim"], seeds=[0], lux=[5]), tmp_path / "out", workers=0, retries=1,
                        progress=False, log=lambda *a: None)
    assert res.n_done == 0 and len(res.failed) == 1 and exr.name in res.failed[0]["error"]
    man = json.loads((tmp_path / "out" / "manifest.json").read_text())
    rec = next(iter(man["samples"].values()))
    assert rec["status"] == "failed" and rec["attempts"] == 2
    assert (man["n_done"], man["n_failed"], man["n_pending"]) == (0, 1, 0)
    assert not list((tmp_path / "out" / "samples").iterdir())
    assert "Failed samples" in (tmp_path / "out" / "summary.md").read_text()


def test_samples_hold_truth_and_train_reads_the_folder(frames, tmp_path):
    from recon.spec import build_dataset as recon_data
    build_dataset(_spec(frames, lux=[50], models=["elssim"], seeds=[3], window=320), tmp_path, workers=0,
                  progress=False, log=lambda *a: None)
    (sample,) = [p for p in (tmp_path / "samples").iterdir()]
    info = json.loads((sample / "sample.json").read_text())
    assert info["illuminance_lux"] == 50 and info["seed"] == 3 and info["preroll_intervals"] == 100
    with np.load(sample / "truth.npz") as z:
        clean, rate, centers = z["clean"], z["rate_e"], z["centers"]
    spikes, meta = sensor.read_spikes_with_meta(sample / "spikes.npz")
    assert spikes.shape == (360, 8, 12) and meta["model"] == "elssim" and clean.shape == (len(centers), 8, 12)
    # 50 of the 100 lux the frames were rendered at: half the rate
    assert float(rate.mean()) == pytest.approx(0.5 * 900 * 0.3, rel=1e-5)
    ds = recon_data(f"rendered:{tmp_path}:spikes=spikes.npz:profile=vidar-default")
    item = ds.sample(0)
    assert len(ds) == 1 and np.array_equal(item.windows.sum(0) * 32, spikes[0:320].sum(0).astype(np.float32))


def test_spec_errors_name_the_key(frames, tmp_path):
    cases = [({"lux": "bright"}, "lux"), ({"colour": 1}, "colour"), ({"mode": "random"}, "samples"),
             ({"lux": {"uniform": [1, 10]}}, "lux"), ({"models": ["elssim", "davis"]}, "models.1"),
             ({"scenes": ["no_such_scene"]}, "scenes.0"), ({"seeds": [-1]}, "seeds")]
    for extra, key in cases:
        with pytest.raises(sensor.InputError, match=key.replace(".", r"\.")):
            load_spec(_spec(frames, **extra))


def test_random_draws_are_seeded(frames):
    spec, _ = load_spec(_spec(frames, mode="random", samples=6, lux={"log_uniform": [1, 100]}, seed=4))
    a, b = plan(spec), plan(spec)
    assert a == b and all(1 <= s.lux <= 100 for s in a) and len({s.lux for s in a}) == 6
    spec2, _ = load_spec(_spec(frames, mode="random", samples=6, lux={"log_uniform": [1, 100]}, seed=5))
    assert [s.lux for s in plan(spec2)] != [s.lux for s in a]


def test_one_render_serves_every_lux(tmp_path):
    pytest.importorskip("mitsuba")
    spec = {"scenes": [{"scene": "lambertian_plane", "set": [
        "camera.profile.synthetic.height=6", "camera.profile.synthetic.width=8", "render.spp=4",
        "render.meter_spp=256", "render.adaptive.enabled=false"]}],
        "duration_s": 0.004, "lux": [10, 100], "seeds": [0], "window": 16, "centers": 1, "preroll": 0}
    res = build_dataset(spec, tmp_path, workers=0, progress=False, log=lambda *a: None)
    assert res.n_done == 2 and not res.failed
    assert len(list((tmp_path / "renders").iterdir())) == 1
    a, b = sorted((tmp_path / "samples").iterdir(), key=lambda p: json.loads((p / "sample.json").read_text())["index"])
    pa, pb = sensor.read_frames(a).phi_stack(), sensor.read_frames(b).phi_stack()
    np.testing.assert_allclose(pb, 10 * pa, rtol=1e-6)


def test_crossing_reset_is_a_model_axis(frames, tmp_path):
    res = build_dataset(_spec(frames, lux=[50], models=["elssim:interval", "elssim:crossing"], seeds=[0]), tmp_path,
                        workers=0, progress=False, log=lambda *a: None)
    assert res.n_done == 2
    infos = [json.loads((p / "sample.json").read_text()) for p in (tmp_path / "samples").iterdir()]
    assert sorted(i["reset"] for i in infos) == ["crossing", "interval"]
    a, b = (sensor.read_spikes(p / "spikes.npz") for p in (tmp_path / "samples").iterdir())
    assert (a != b).any()  # same seed, different reset: different streams
    for p in (tmp_path / "samples").iterdir():
        meta = sensor.read_spikes_meta(p / "spikes.npz")
        assert meta["model"] == "elssim" and meta["reset"] == json.loads((p / "sample.json").read_text())["reset"]
