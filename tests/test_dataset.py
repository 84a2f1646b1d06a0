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
    # the render records where its time went (benchmarks/dataset.py reads it): stages within its seconds
    fm = json.loads((next((tmp_path / "renders").iterdir()) / "frames.json").read_text())
    st = fm["render_stage_seconds"]
    assert set(st) == {"start", "load", "meter", "pilot", "keyframes"} and min(st.values()) >= 0
    assert st["meter"] > 0 and st["keyframes"] > 0 and sum(st.values()) <= fm["render_seconds"] * (1 + 1e-9)


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


# ------------------------------------------------------------------------------------------------ refusals
def _write_spec(tmp_path, frames, text_or_dict, name="spec.yaml"):
    p = tmp_path / name
    import yaml
    p.write_text(text_or_dict if isinstance(text_or_dict, str) else yaml.safe_dump(text_or_dict))
    return p


def _refused(cli, spec, out, *extra, field=None, contains=()):
    """Run the command; assert one error line naming the spec file (or option) and ``field``, and no --out."""
    r = cli("dataset", spec, "--out", out, "--quiet", *extra)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip() and not ln.startswith(" ")]
    assert r.returncode == 2, (r.returncode, r.stderr)
    assert "Traceback" not in r.stderr
    err = [ln for ln in lines if "error" in ln]
    assert len(err) == 1, r.stderr
    if field is not None:
        assert field in err[0], err[0]
    for c in contains:
        assert c in err[0], err[0]
    assert not Path(out).exists(), "a refusal left the output folder behind"
    return err[0]


BAD_SPECS = [  # (change to the spec, the key the error must name, a word it must hold)
    ({"lux": [5, 50, -5]}, "'lux.2'", "> 0"),
    ({"lux": [5, float("nan")]}, "'lux.1'", "nan"),
    ({"lux": 0}, "'lux'", "> 0"),
    ({"lux": [float("inf")]}, "'lux.0'", "inf"),
    ({"lux": [5, 50, 5.0]}, "'lux.2'", "twice"),
    ({"lux": []}, "'lux'", "empty"),
    ({"lux": "bright"}, "'lux'", "expected a number"),
    ({"models": ["elssim:sideways"]}, "'models.0'", "sideways"),
    ({"models": ["elssim", "isi", "elssim"]}, "'models.2'", "twice"),
    ({"models": ["davis"]}, "'models.0'", "davis"),
    ({"seeds": [0, 1, 0]}, "'seeds.2'", "twice"),
    ({"seeds": [-1]}, "'seeds.0'", "minimum"),
    ({"profiles": ["vidar-default", "no-such-profile"]}, "'profiles.1'", "no-such-profile"),
    ({"profiles": ["vidar-default", "vidar-default"]}, "'profiles.1'", "twice"),
    ({"window": 0}, "'window'", "minimum"),
    ({"preroll": -3}, "'preroll'", "minimum"),
    ({"mode": "random", "samples": 6}, "'samples'", "same sample"),  # 6 draws from 2 x 2 x 2 combinations
    ({"mode": "random", "samples": 3, "lux": {"uniform": [10, 1]}}, "'lux.uniform'", "low < high"),
    ({"mode": "random", "samples": 3, "lux": {"uniform": [0, 10]}}, "'lux.uniform.0'", "> 0"),
    ({"mode": "random", "samples": 3, "lux": {"log_uniform": [1, float("nan")]}}, "lux.log_uniform", ""),
    ({"lux": {"uniform": [1, 10]}}, "'lux'", "mode: random"),
    ({"mode": "random"}, "'samples'", "samples"),
    ({"duration_s": 0.01}, "'duration_s'", "frames"),
    ({"set": ["render.spp"]}, "'set.0'", "KEY=VALUE"),
    ({"colour": "red"}, "(top level)", "colour"),
    ({"samples": 3}, "'samples'", "random"),
    ({"lux": list(range(1, 1001)), "seeds": list(range(1000))}, "", "2,000,000 samples"),
    ({"lux": [1e300]}, "'lux.0'", "at most"),  # the scaled frames would overflow
    ({"centers": 1000000}, "'centers'", "360 intervals"),
    ({"scenes": [{"frames": "no/such/folder"}]}, "'scenes.0.frames'", "no frames.json"),
]


@pytest.mark.parametrize("change,field,word", BAD_SPECS, ids=[str(i) for i in range(len(BAD_SPECS))])
def test_bad_spec_values_are_refused_before_anything_is_made(cli, frames, tmp_path, change, field, word):
    spec = _write_spec(tmp_path, frames, _spec(frames, **change))
    msg = _refused(cli, spec, tmp_path / "out", field=field, contains=(str(spec), word))
    assert msg.startswith("render2spike: error: ")


def test_frames_without_a_sensor_are_refused(cli, frames, tmp_path):
    d = _spec(frames)
    d["scenes"] = [{"frames": str(frames)}]  # profiles default to 'scene'; these frames name no sensor
    _refused(cli, _write_spec(tmp_path, frames, d), tmp_path / "out", field="'scenes.0.profile'",
             contains=("which sensor",))
    d["scenes"] = [{"frames": str(frames)}, {"frames": str(frames), "profile": "vidar-default"}]
    d["profiles"] = ["vidar-default"]
    _refused(cli, _write_spec(tmp_path, frames, d), tmp_path / "out", field="'scenes.1'",
             contains=("scenes.0 and scenes.1 give the same samples",))


def test_spec_file_problems_are_one_line(cli, frames, tmp_path):
    good = yaml_text = (f"scenes: [{{frames: {frames}, profile: vidar-default}}]\nlux: [5, 50]\nmodels: [elssim]\n"
                        "seeds: [0]\n")
    cases = [(yaml_text.replace("lux: [5, 50]", "lux: [5, 50\nfoo: : bar"), "line 3"),
             (good + "lux: 7\n", "'lux' is given twice"),
             (good + "\tseed: 1\n", "line 5"),
             ("", "empty"),
             ("- a\n- b\n", "mapping")]
    for text, word in cases:
        spec = _write_spec(tmp_path, frames, text)
        _refused(cli, spec, tmp_path / "out", contains=(str(spec), word))
    (tmp_path / "bin.yaml").write_bytes(b"\x00\xff\xfe binary")
    _refused(cli, tmp_path / "bin.yaml", tmp_path / "out", contains=("not a text file",))
    _refused(cli, tmp_path, tmp_path / "out", contains=("is a folder",))
    _refused(cli, tmp_path / "missing.yaml", tmp_path / "out", contains=("not found",))


def test_scene_values_are_checked_with_the_scene_validators(cli, tmp_path):
    base = {"scenes": ["translating_object"], "set": ["render.spp=4"], "duration_s": 0.01, "lux": [5],
            "params": {"speed_px_per_ms": [0.1, 0.5]}, "seeds": [0]}
    cases = [({"params": {"speed_px_per_ms": [0.1, 0.1]}}, "'params.speed_px_per_ms.1'", "twice"),
             ({"params": {"warp_factor": [1.0]}}, "'params.warp_factor.0'", "warp_factor"),
             ({"duration_s": 1e-5}, "'duration_s'", "shorter than one read-out interval"),
             ({"set": ["render.spp=-4"]}, "'set.0'", "render.spp"),
             ({"set": ["render.spp=4", "render.spp=8"]}, "'set.1'", "twice"),
             ({"scenes": ["translating_object", "translating_object"]}, "'scenes.1'", "same scene"),
             ({"scenes": ["no_such_scene"]}, "'scenes.0'", "not found"),
             ({"params": {"illuminance_lux": [1.0, 2.0]}}, "'params.illuminance_lux'", "'lux' axis"),
             ({"set": ["render.spp=4", "speed_px_per_ms=1"]}, "'params.speed_px_per_ms'", "both")]
    for change, field, word in cases:
        spec = _write_spec(tmp_path, None, dict(base, **change))
        _refused(cli, spec, tmp_path / "out", field=field, contains=(word,))


def test_each_scene_variant_is_loaded_once_and_the_plan_is_told(frames, tmp_path, monkeypatch):
    import render2spike.render.scene as scene_mod
    from render2spike.dataset import prepare
    calls = []
    real = scene_mod.load_scene
    monkeypatch.setattr(scene_mod, "load_scene", lambda *a, **k: calls.append(a) or real(*a, **k))
    spec, path = load_spec({"scenes": ["translating_object"], "duration_s": 0.01, "lux": list(range(1, 41)),
                            "params": {"speed_px_per_ms": [0.1, 0.2, 0.3]}, "seeds": [0, 1]})
    said = []
    pl = prepare(spec, path, log=said.append)
    assert len(pl.samples) == 240 and pl.n_renders == 3 and len(calls) == 3  # not once per sample
    assert pl.description.startswith("240 samples = 1 scenes x 40 lux x 3 speed_px_per_ms x 1 models x 2 seeds")
    spec, path = load_spec(_spec(frames, lux=list(range(1, 201)), seeds=list(range(20))))
    prepare(spec, path, log=said.append)
    assert any("planning 8000 samples" in s for s in said)


def test_run_options_are_checked(cli, frames, tmp_path):
    spec = _write_spec(tmp_path, frames, _spec(frames))
    for args, word in [(["--workers", "-1"], "--workers"), (["--workers", "two"], "--workers"),
                       (["--retries", "-1"], "--retries")]:
        r = cli("dataset", spec, "--out", tmp_path / "out", *args)
        assert r.returncode == 2 and word in r.stderr and "whole number" in r.stderr and "Traceback" not in r.stderr
        assert not (tmp_path / "out").exists()
    for args, field in [(["--retries", "1000"], "--retries"), (["--resources", "GPU=1", "--workers", "0"],
                                                                "--resources"),
                        (["--resources", "GPU=-1"], "--resources"), (["--resources", "GPU"], "--resources"),
                        (["--scheduler", "tcp://127.0.0.1:1", "--workers", "2"], "--workers"),
                        (["--workers", "100000"], "--workers")]:
        _refused(cli, spec, tmp_path / "out", *args, field=f"'{field}'")


def test_scheduler_that_does_not_answer_is_refused_in_one_line(cli, frames, tmp_path, monkeypatch):
    pytest.importorskip("dask.distributed")
    import socket
    import threading
    import render2spike.dataset as ds
    monkeypatch.setattr(ds, "SCHEDULER_TIMEOUT_S", 1.0)
    spec = _write_spec(tmp_path, frames, _spec(frames))
    with socket.socket() as closed:
        closed.bind(("127.0.0.1", 0))
        free_port = closed.getsockname()[1]
    _refused(cli, spec, tmp_path / "out", "--scheduler", f"tcp://127.0.0.1:{free_port}", field="'--scheduler'",
             contains=("connection refused",))
    for bad in ("http://head:8786", "tcp://head", "tcp://head:99999"):
        _refused(cli, spec, tmp_path / "out", "--scheduler", bad, field="'--scheduler'", contains=("expected",))
    with socket.socket() as srv, socket.socket() as silent:
        srv.bind(("127.0.0.1", 0))
        srv.listen(4)
        silent.bind(("127.0.0.1", 0))
        silent.listen(4)  # accepts connections (the kernel does) and never says a word

        def serve():  # an HTTP server, not Dask: its bytes read as an absurd message length
            while True:
                try:
                    c, _ = srv.accept()
                    c.sendall(b"HTTP/1.1 200 OK\r\nContent-Length: 5\r\n\r\n" + b"\xff" * 64)
                except OSError:
                    return
        threading.Thread(target=serve, daemon=True).start()
        _refused(cli, spec, tmp_path / "out", "--scheduler", f"tcp://127.0.0.1:{srv.getsockname()[1]}",
                 field="'--scheduler'", contains=("not a Dask scheduler",))
        _refused(cli, spec, tmp_path / "out", "--scheduler", f"tcp://127.0.0.1:{silent.getsockname()[1]}",
                 field="'--scheduler'", contains=("within 1 s",))


# ------------------------------------------------------------------------------------------------ the folder
def _tiny(frames, **kw):
    return _spec(frames, lux=[50], models=["elssim"], seeds=[0], **kw)


def test_a_second_run_into_a_locked_folder_is_refused_at_once(cli, frames, tmp_path):
    import socket
    from sensor.io.lock import LOCK_NAME, FolderLock
    spec = _write_spec(tmp_path, frames, _tiny(frames))
    out = tmp_path / "out"
    out.mkdir()
    with FolderLock(out, "a dataset run"):
        r = cli("dataset", spec, "--out", out, "--quiet")
        assert r.returncode == 2 and "Traceback" not in r.stderr
        assert f"pid {os.getpid()} on {socket.gethostname()}" in r.stderr and "already writing" in r.stderr
        assert sorted(p.name for p in out.iterdir()) == [LOCK_NAME]  # nothing written, the other's lock kept
    # the lock of a process that is gone is taken over
    (out / LOCK_NAME).write_text(json.dumps({"pid": 2 ** 22 + 12345, "host": socket.gethostname()}))
    r = cli("dataset", spec, "--out", out, "--quiet", "--workers", "0")
    assert r.returncode == 0 and "taking over the stale lock" in r.stdout + r.stderr
    assert not (out / LOCK_NAME).exists()


def test_another_spec_or_a_foreign_manifest_is_refused_unless_overwrite(cli, frames, tmp_path):
    out = tmp_path / "out"
    a = _write_spec(tmp_path, frames, _tiny(frames), "a.yaml")
    b = _write_spec(tmp_path, frames, _tiny(frames, window=32), "b.yaml")
    assert cli("dataset", a, "--out", out, "--quiet", "--workers", "0").returncode == 0
    before = (out / "manifest.json").read_bytes()
    (old_sample,) = list((out / "samples").iterdir())
    r = cli("dataset", b, "--out", out, "--quiet", "--workers", "0")
    assert r.returncode == 2 and "another spec" in r.stderr and "--overwrite" in r.stderr
    assert (out / "manifest.json").read_bytes() == before and old_sample.is_dir()
    r = cli("dataset", b, "--out", out, "--quiet", "--workers", "0", "--overwrite")
    assert r.returncode == 0, r.stderr
    man = json.loads((out / "manifest.json").read_text())
    on_disk = {p.name for p in (out / "samples").iterdir()}
    assert not old_sample.exists() and set(man["samples"]) == on_disk and man["n_done"] == 1 == len(on_disk)
    # the same spec again: resumed, nothing made
    r = cli("dataset", b, "--out", out, "--quiet", "--workers", "0")
    assert r.returncode == 0 and "1 of 1 samples already done" in r.stdout
    # a manifest.json of the user's own, or other files
    for name, text in [("manifest.json", '{"mine": true}'), ("notes.txt", "keep")]:
        own = tmp_path / f"own-{name}"
        own.mkdir()
        (own / name).write_text(text)
        r = cli("dataset", a, "--out", own, "--quiet", "--workers", "0")
        assert r.returncode == 2 and "--overwrite" in r.stderr and (own / name).read_text() == text
        assert sorted(p.name for p in own.iterdir()) == [name]
    own = tmp_path / "own-manifest.json"
    assert cli("dataset", a, "--out", own, "--quiet", "--workers", "0", "--overwrite").returncode == 0
    assert json.loads((own / "manifest.json").read_text())["format"] == "render2spike-dataset"


def test_an_interrupted_run_cleans_up_before_it_lets_go_of_the_lock(frames, tmp_path, monkeypatch):
    import render2spike.dataset as ds
    from sensor.io.lock import LOCK_NAME
    out = tmp_path / "new" / "deep" / "out"
    seen = []
    real_clear = ds._clear_dataset

    def clear(folder):
        seen.append((folder / LOCK_NAME).exists())  # the lock is still held during the clean-up
        real_clear(folder)

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(ds, "_clear_dataset", clear)
    monkeypatch.setattr(ds, "sample_task", interrupted)
    with pytest.raises(KeyboardInterrupt):
        build_dataset(_tiny(frames), out, workers=0, progress=False, log=lambda *a: None)
    assert seen == [True] and not (tmp_path / "new").exists()  # nor the folders made for it


def test_an_output_that_cannot_be_made_is_one_line(cli, frames, tmp_path):
    (tmp_path / "file").write_text("x")
    spec = _write_spec(tmp_path, frames, _tiny(frames))
    _refused(cli, spec, tmp_path / "file" / "out", "--workers", "0", field="'--out'", contains=("cannot make",))
    r = cli("dataset", spec, "--out", tmp_path / "file", "--quiet")
    assert r.returncode == 2 and "not a folder" in r.stderr and (tmp_path / "file").read_text() == "x"


def test_the_manifest_counts_what_is_on_disk(frames, tmp_path):
    import shutil
    out = tmp_path / "out"
    spec = _spec(frames, models=["elssim"], seeds=[0, 1])
    build_dataset(spec, out, workers=0, progress=False, log=lambda *a: None)
    man = json.loads((out / "manifest.json").read_text())
    assert man["n_done"] == 4 == len(list((out / "samples").iterdir())) and man["n_failed"] == 0
    gone = sorted((out / "samples").iterdir())[0]
    shutil.rmtree(gone)  # a sample lost on disk is made again, and counted as the disk has it
    res = build_dataset(spec, out, workers=0, progress=False, log=lambda *a: None)
    man = json.loads((out / "manifest.json").read_text())
    assert (res.n_made, res.n_skipped, man["n_done"]) == (1, 3, 4) and gone.is_dir()


def test_a_real_scheduler_is_accepted(cli, frames, tmp_path):
    distributed = pytest.importorskip("dask.distributed")
    spec = _write_spec(tmp_path, frames, _tiny(frames))
    with distributed.LocalCluster(n_workers=1, processes=False, threads_per_worker=1, dashboard_address=None,
                                  protocol="tcp://") as lc:
        r = cli("dataset", spec, "--out", tmp_path / "out", "--quiet", "--scheduler", lc.scheduler_address)
    assert r.returncode == 0, r.stderr
    assert json.loads((tmp_path / "out" / "manifest.json").read_text())["n_done"] == 1


def test_frames_folders_with_a_broken_manifest_are_refused(cli, frames, tmp_path):
    import shutil
    cases = [(lambda m: m["frames"][0].pop("time_s"), "no finite time_s"), (lambda m: m.pop("height"), "'height'"),
             (lambda m: [f.__setitem__("time_s", 0.0) for f in m["frames"]], "span no time"),
             (lambda m: m.pop("illuminance_lux"), "illuminance"), (lambda m: m["frames"].__delitem__(slice(1, None)),
                                                                  "fewer than two")]
    for i, (change, word) in enumerate(cases):
        d = tmp_path / f"frames{i}"
        shutil.copytree(frames, d)
        man = json.loads((d / "frames.json").read_text())
        change(man)
        (d / "frames.json").write_text(json.dumps(man))
        _refused(cli, _write_spec(tmp_path, frames, _tiny(d)), tmp_path / "out", field="'scenes.0.frames'",
                 contains=(word,))
    (d / "frames.json").write_text("{not json")
    _refused(cli, _write_spec(tmp_path, frames, _tiny(d)), tmp_path / "out", field="'scenes.0.frames'",
             contains=("not a readable frames manifest",))


def test_a_frames_folders_key_covers_its_pixels_not_only_its_manifest(tmp_path):
    """Two frames folders with the same manifest but other pixels are two renders (two sample ids)."""
    import shutil

    from render2spike.dataset import _frames_key
    a, c = tmp_path / "a", tmp_path / "c"
    sensor.write_frames(a, np.full((2, 4, 6), 1e15, np.float32), [0.0, 0.001])
    sensor.write_frames(c, np.full((2, 4, 6), 2e15, np.float32), [0.0, 0.001])
    b = tmp_path / "b"
    shutil.copytree(a, b)
    man = (a / "frames.json").read_bytes()
    assert _frames_key(a, man) == _frames_key(b, man)  # a copy is the same render
    first = sorted(p.name for p in a.glob("*.exr"))[0]
    shutil.copy(c / first, b / first)
    assert (b / "frames.json").read_bytes() == man and _frames_key(a, man) != _frames_key(b, man)


# ------------------------------------------------------------------------------------------------ timings
def test_each_sample_records_where_its_time_went(frames, tmp_path):
    out = tmp_path / "out"
    build_dataset(_tiny(frames), out, workers=0, progress=False, log=lambda *a: None)
    recs = json.loads((out / "manifest.json").read_text())["samples"]
    assert len(recs) == 1
    for rec in recs.values():
        tm = rec["timing"]
        assert set(tm) == {"read", "simulate", "truth", "write"}
        assert all(v > 0 for v in tm.values()), tm  # every stage ran, and was timed
        assert sum(tm.values()) <= rec["seconds"], (tm, rec["seconds"])


def test_the_dataset_benchmark_has_a_help():
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "dataset.py"), "--help"], capture_output=True,
                         text=True, cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)), timeout=120)
    assert out.returncode == 0, out.stderr
    assert "camera-seconds" in out.stdout and "--spec" in out.stdout and "--out" in out.stdout
