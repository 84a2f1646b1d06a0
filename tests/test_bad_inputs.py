"""Every class of bad input through the CLI: exit code 2, one line naming the file and the field, nothing written.

Each case builds a small valid input, breaks one thing, runs the command in-process and checks
(a) the exit code is 2, (b) stderr is one line without a traceback that names what the case says,
(c) no file under the test folder was created, changed or removed (inputs included).
"""

import errno
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

import sensor
from render2spike.cli import main

ROOT = Path(__file__).resolve().parents[1]


def snapshot(root: Path) -> dict:
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns, p.read_bytes() if p.is_file() else b"")
            for p in sorted(root.rglob("*"))}


def expect_refused(args, root, capsys, *names):
    capsys.readouterr()
    before = snapshot(root)
    rc = main([str(a) for a in args])
    err = capsys.readouterr().err
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert rc == 2, err
    assert len(lines) == 1 and "Traceback" not in err, err
    for n in names:
        assert str(n) in err, (n, err)
    assert snapshot(root) == before, "something was written, changed or removed"
    return err


# ------------------------------------------------------------------- frames folders
def _frames(tmp_path, n=3):
    phi = np.full((n, 8, 16), 1.5e16, np.float32)
    t = [0.0, 0.005, 0.01, 0.015][:n]
    sensor.write_frames(tmp_path / "frames", phi, t)
    return tmp_path / "frames"


def _edit_manifest(folder, fn):
    m = json.loads((folder / "frames.json").read_text())
    fn(m)
    (folder / "frames.json").write_text(json.dumps(m))


FRAME_CASES = {
    "nan_time": (lambda m: m["frames"][1].__setitem__("time_s", float("nan")), ["frames.json", "frames[1].time_s"]),
    "inf_time": (lambda m: m["frames"][2].__setitem__("time_s", float("inf")), ["frames.json", "frames[2].time_s"]),
    "out_of_order": (lambda m: m["frames"].reverse(), ["frames.json", "increase strictly", "frames[0]"]),
    "file_twice": (lambda m: m["frames"][2].__setitem__("file", m["frames"][1]["file"]),
                   ["frames.json", "frames[2].file", "listed twice"]),
    "header_lie": (lambda m: m["frames"][2].__setitem__("time_s", 0.5),
                   ["frame_000002.exr", "time_s", "0.5", "0.01"]),
    "single_keyframe": (lambda m: m.__setitem__("frames", m["frames"][:1]),
                        ["frames", "less than one whole interval"]),
    "incomplete": (lambda m: m.__setitem__("complete", False), ["frames.json", "complete"]),
    "bad_size": (lambda m: m.__setitem__("height", 0), ["frames.json", "height"]),
}


@pytest.mark.parametrize("case", sorted(FRAME_CASES))
def test_bad_frames_folder(case, tmp_path, capsys):
    folder = _frames(tmp_path)
    fn, names = FRAME_CASES[case]
    _edit_manifest(folder, fn)
    expect_refused(["simulate", folder, "--out", tmp_path / "s.npz", "--quiet"], tmp_path, capsys, *names)


def test_frame_with_nan_light_names_file_and_pixel(tmp_path, capsys):
    folder = _frames(tmp_path)
    phi = np.full((8, 16), 1.5e16, np.float32)
    phi[2, 3] = np.nan
    sensor.write_frame(folder / "frame_000001.exr", phi, time_s=0.005)
    expect_refused(["simulate", folder, "--out", tmp_path / "s.npz", "--quiet"], tmp_path, capsys,
                   "frame_000001.exr", "Phi", "(2, 3)")


def test_folder_a_render_is_writing_into(tmp_path, capsys):
    from sensor.io.lock import FolderLock
    folder = _frames(tmp_path)
    with FolderLock(folder):
        expect_refused(["simulate", folder, "--out", tmp_path / "s.npz", "--quiet"], tmp_path, capsys,
                       str(folder), f"pid {os.getpid()}")


# ------------------------------------------------------------------------ rate arrays
def _rate(tmp_path, **over):
    d = {"rate_e": np.full((4, 8, 16), 5.0, np.float32), "t_s": np.array([0.0, 0.001, 0.002, 0.003])}
    d.update(over)
    np.savez(tmp_path / "rate.npz", **d)
    return tmp_path / "rate.npz"


def test_rate_array_cases(tmp_path, capsys):
    out = tmp_path / "s.npz"
    p = _rate(tmp_path, t_s=np.array([0.0, np.nan, 0.002, 0.003]))
    expect_refused(["simulate", p, "--out", out, "--quiet"], tmp_path, capsys, "rate.npz", "t_s[1]", "finite")
    p = _rate(tmp_path, t_s=np.array([0.0, 0.002, 0.001, 0.003]))
    expect_refused(["simulate", p, "--out", out, "--quiet"], tmp_path, capsys, "rate.npz", "t_s[1]", "increase")
    r = np.full((4, 8, 16), 5.0, np.float32)
    r[1, 2, 3] = np.inf
    p = _rate(tmp_path, rate_e=r)
    expect_refused(["simulate", p, "--out", out, "--quiet"], tmp_path, capsys, "rate.npz", "rate_e", "[1, 2, 3]")
    r[1, 2, 3] = -1.0
    p = _rate(tmp_path, rate_e=r)
    expect_refused(["simulate", p, "--out", out, "--quiet"], tmp_path, capsys, "rate.npz", "rate_e", "[1, 2, 3]")
    p = _rate(tmp_path, rate_e=np.zeros((0, 8, 16), np.float32), t_s=np.zeros(0))
    expect_refused(["simulate", p, "--out", out, "--quiet"], tmp_path, capsys, "rate.npz", "rate_e", "empty")
    p = _rate(tmp_path)
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])  # truncated
    expect_refused(["simulate", p, "--out", out, "--quiet"], tmp_path, capsys, "rate.npz")
    (tmp_path / "x.npy").write_bytes(b"\x93NUMPY garbage")
    expect_refused(["simulate", tmp_path / "x.npy", "--out", out, "--quiet"], tmp_path, capsys, "x.npy")


# ---------------------------------------------------------------------------- outputs
def test_output_protection(tmp_path, capsys):
    p = _rate(tmp_path)
    expect_refused(["simulate", p, "--out", p, "--quiet"], tmp_path, capsys, "rate.npz", "input")
    out = tmp_path / "s.npz"
    assert main(["simulate", str(p), "--out", str(out), "--quiet", "--model", "ideal"]) == 0
    expect_refused(["simulate", p, "--out", out, "--quiet"], tmp_path, capsys, "s.npz", "--overwrite")
    assert main(["simulate", str(p), "--out", str(out), "--quiet", "--overwrite", "--seed", "3"]) == 0
    assert sensor.read_spikes_meta(out)["seed"] == 3
    expect_refused(["reconstruct", out, "--out", out], tmp_path, capsys, "s.npz")
    (tmp_path / "rec").mkdir()
    (tmp_path / "rec" / "keep.txt").write_text("mine")
    expect_refused(["reconstruct", out, "--out", tmp_path / "rec"], tmp_path, capsys, "rec", "--overwrite")
    expect_refused(["calibrate", "--dark", p, "--flat", p, p, "--out", p], tmp_path, capsys, "rate.npz", "input")


def test_stale_temp_files_of_a_killed_writer_are_swept(tmp_path, capsys):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    part = tmp_path / f".s.part-{dead.pid}-x1y2.npz"
    part.write_bytes(b"\0" * 1000)
    p = _rate(tmp_path)
    assert main(["simulate", str(p), "--out", str(tmp_path / "s.npz"), "--quiet"]) == 0
    assert not part.exists()


def test_disk_full_is_one_line_naming_the_file(tmp_path, capsys, monkeypatch):
    import sensor.io.fileio as fio
    p = _rate(tmp_path)

    def full(src, dst):
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(fio.os, "replace", full)
    expect_refused(["simulate", p, "--out", tmp_path / "s.npz", "--quiet"], tmp_path, capsys,
                   "disk full while writing", "s.npz")


# --------------------------------------------------------------------------- profiles
def _profile(tmp_path):
    return sensor.SensorProfile.synthetic(8, 16, threshold_e=50.0, seed=1).save(tmp_path / "cam.npz")


def _rewrite_npz(path, fn):
    with np.load(path, allow_pickle=False) as z:
        d = {k: z[k] for k in z.files}
    fn(d)
    with open(path, "wb") as f:
        np.savez(f, **d)


def test_corrupt_profiles(tmp_path, capsys):
    rate = _rate(tmp_path)
    out = tmp_path / "s.npz"
    cam = _profile(tmp_path)
    data = cam.read_bytes()
    cam.write_bytes(data[: len(data) // 3])
    expect_refused(["simulate", rate, "--out", out, "--profile", cam, "--quiet"], tmp_path, capsys, "cam.npz")
    cam.write_bytes(b"PK\x03\x04" + b"\0" * 50)
    expect_refused(["simulate", rate, "--out", out, "--profile", cam, "--quiet"], tmp_path, capsys, "cam.npz")
    cam.write_bytes(b"garbage")
    expect_refused(["simulate", rate, "--out", out, "--profile", cam, "--quiet"], tmp_path, capsys, "cam.npz")
    cam.unlink()
    cam = _profile(tmp_path)
    _rewrite_npz(cam, lambda d: d.__setitem__("dark_rate", np.zeros((3, 3), np.float32)))
    expect_refused(["simulate", rate, "--out", out, "--profile", cam, "--quiet"], tmp_path, capsys,
                   "cam.npz", "dark_rate")
    cam.unlink()
    cam = _profile(tmp_path)

    def drop_threshold(d):
        meta = json.loads(bytes(d["meta_json"]).decode())
        del meta["threshold_e"]
        d["meta_json"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    _rewrite_npz(cam, drop_threshold)
    expect_refused(["simulate", rate, "--out", out, "--profile", cam, "--quiet"], tmp_path, capsys,
                   "cam.npz", "threshold_e")
    cam.unlink()
    cam = _profile(tmp_path)
    _rewrite_npz(cam, lambda d: d.pop("meta_json"))
    expect_refused(["simulate", rate, "--out", out, "--profile", cam, "--quiet"], tmp_path, capsys,
                   "cam.npz", "meta_json")


# ------------------------------------------------------------------------ checkpoints
def test_corrupt_checkpoints(tmp_path, capsys):
    torch = pytest.importorskip("torch")
    from recon.nets import RSIRConfig, RSIRNet, save_checkpoint
    spikes = tmp_path / "s.npz"
    sensor.write_spikes(spikes, np.zeros((400, 8, 8), bool), interval_s=50e-6, model="ideal", profile_id="x", seed=0)
    cfg = RSIRConfig.tiny()
    cfg.width = 8
    ck = save_checkpoint(tmp_path / "ck.pt", RSIRNet(cfg))
    args = ["reconstruct", spikes, "--method", "rsir", "--checkpoint", ck, "--out", tmp_path / "rec"]
    good = ck.read_bytes()
    ck.write_bytes(good[: len(good) // 2])
    expect_refused(args, tmp_path, capsys, "ck.pt", "truncated")
    torch.save({"a": 1}, ck)
    expect_refused(args, tmp_path, capsys, "ck.pt", "format")
    state = torch.load(tmp_path / "ck.pt", weights_only=True)
    ck.write_bytes(good)
    state = torch.load(ck, weights_only=True)
    state["model"] = {k: v[..., :1] if v.ndim else v for k, v in state["model"].items()}
    torch.save(state, ck)
    expect_refused(args, tmp_path, capsys, "ck.pt", "model")
    state["config"] = {"width": "wide"}
    torch.save(state, ck)
    expect_refused(args, tmp_path, capsys, "ck.pt", "config")


# ----------------------------------------------------------------------------- scenes
SCENE = {
    "format": "render2spike-scene", "name": "tiny", "duration_s": 0.01, "illuminance_lux": 100.0,
    "reference": {"point": [0, 0, 0], "normal": [0, 0, 1]},
    "camera": {"profile": {"synthetic": {"height": 8, "width": 16, "threshold_e": 2000.0}},
               "focal_length_mm": 8.0, "f_number": 2.0},
    "lights": [{"name": "sun", "type": "directional", "direction": [0, 0, -1], "strength": 1.0}],
    "objects": [{"name": "plane", "shape": "rectangle", "size": [10, 10], "material": {"reflectance": 0.5}}],
    "render": {"keyframe_rate_hz": 200, "spp": 4},
}


def _scene(tmp_path, text=None, **changes):
    d = json.loads(json.dumps(SCENE))
    d.update(changes)
    p = tmp_path / "scene.yaml"
    p.write_text(text if text is not None else yaml.safe_dump(d))
    return p


def test_bad_scenes_are_refused_before_anything_is_written(tmp_path, capsys):
    out = tmp_path / "out"
    p = _scene(tmp_path)
    for lux in ("nan", "inf", "-3"):
        expect_refused(["render", p, "--out", out, "--lux", lux], tmp_path, capsys, "scene.yaml", "illuminance_lux")
        expect_refused(["run", p, "--out", out, "--lux", lux], tmp_path, capsys, "scene.yaml", "illuminance_lux")
    text = p.read_text().replace("strength: 1.0", "strength: .nan")
    p = _scene(tmp_path, text=text)
    expect_refused(["render", p, "--out", out], tmp_path, capsys, "scene.yaml", "lights.0.strength", "finite")
    p = _scene(tmp_path, objects=[])
    expect_refused(["run", p, "--out", out], tmp_path, capsys, "scene.yaml", "objects", "nothing to see")
    expect_refused(["render", "no_such_scene", "--out", out], tmp_path, capsys, "no_such_scene", "bundled scenes")
    expect_refused(["render", p, "--out", out, "--seed", "3"], tmp_path, capsys, "--seed", "--render-seed")


@pytest.mark.render
def test_scene_whose_lights_never_reach_the_reference(tmp_path, capsys):
    pytest.importorskip("mitsuba")
    p = _scene(tmp_path, lights=[{"name": "sun", "type": "directional", "direction": [0, 0, 1], "strength": 1.0}])
    expect_refused(["render", p, "--out", tmp_path / "out", "--quiet"], tmp_path, capsys, "scene.yaml",
                   "reference")
    expect_refused(["run", p, "--out", tmp_path / "out", "--quiet"], tmp_path, capsys, "scene.yaml", "reference")


# ---------------------------------------------------------------------------- SIGTERM
def test_sigterm_is_a_clean_abort(tmp_path):
    """SIGTERM during `simulate` to .dat: exit 143, one line, no temp file and no output left."""
    rate = np.full((2, 64, 64), 300.0, np.float32)
    np.savez(tmp_path / "rate.npz", rate_e=rate, t_s=np.array([0.0, 200.0]))  # 4 million intervals
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "render2spike", "simulate", str(tmp_path / "rate.npz"),
                             "--out", str(tmp_path / "s.dat"), "--quiet", "--model", "ideal"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    deadline = time.time() + 60
    # wait until spikes are being written (a non-empty temp file), so that the signal lands mid-stream
    while time.time() < deadline and not any(p.stat().st_size for p in tmp_path.glob(".s.part-*")):
        time.sleep(0.05)
    assert list(tmp_path.glob(".s.part-*")), "the writer never started"
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143, err
    assert "terminated" in err and "Traceback" not in err
    assert not list(tmp_path.glob(".*part*")) and not (tmp_path / "s.dat").exists()


def test_bad_study_light_levels(tmp_path, capsys):
    folder = _frames(tmp_path, n=4)
    _edit_manifest(folder, lambda m: m.__setitem__("illuminance_lux", float("nan")))
    out = tmp_path / "st"
    expect_refused(["study", folder, "--out", out, "--window", "20", "--quiet"], tmp_path, capsys,
                   "frames.json", "illuminance_lux")
    expect_refused(["study", folder, "--out", out, "--window", "20", "--lux", "nan", "--reference-lux", "10",
                    "--quiet"], tmp_path, capsys, "--lux")
    expect_refused(["study", folder, "--out", out, "--window", "20", "--reference-lux", "inf", "--quiet"],
                   tmp_path, capsys, "--reference-lux")


def test_python_simulate_refuses_less_than_one_interval():
    """sensor.simulate with keyframes spanning less than one interval (or a single keyframe) is an error, not []."""
    import sensor
    from sensor.errors import InputError
    prof = sensor.SensorProfile.synthetic(4, 5, threshold_e=100.0, seed=0)
    with pytest.raises(InputError, match="less than one whole interval"):
        sensor.simulate(np.ones((1, 4, 5)), prof, t_s=[0.0])
    with pytest.raises(InputError, match="less than one whole interval"):
        sensor.simulate(np.ones((2, 4, 5)), prof, t_s=[0.0, 1e-5])
    with pytest.raises(InputError, match="t_s"):
        sensor.simulate(np.ones((2, 4, 5)), prof, t_s=[0.0, float("nan")])


def test_temp_file_of_a_write_cut_short_inside_mkstemp_is_removed(tmp_path, monkeypatch):
    """A signal landing between the temp file's creation and its registration still leaves nothing behind."""
    import tempfile

    from sensor.io import fileio
    real = tempfile.mkstemp

    def cut_short(*a, **kw):
        real(*a, **kw)  # the file exists ...
        raise KeyboardInterrupt  # ... and the signal lands before mkstemp returns
    monkeypatch.setattr(tempfile, "mkstemp", cut_short)
    with pytest.raises(KeyboardInterrupt):
        with fileio.atomic_path(tmp_path / "x.dat"):
            pass
    assert list(tmp_path.glob(".x.part-*"))
    fileio.remove_live_temps()
    assert not list(tmp_path.iterdir())
