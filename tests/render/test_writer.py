"""The background frame writer: order, atomic files, journal after the file, errors in the main thread, kills."""

import copy
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from render2spike.render.writer import FrameWriter
from tests.render.conftest import BASE, needs_mitsuba

ROOT = Path(__file__).resolve().parents[2]


def _arrays(i, shape=(4, 6)):
    return np.full(shape, float(i), np.float32), np.full(shape, 2.0 * i, np.float32)


def test_frames_written_in_order_and_journalled_after_the_file(tmp_path):
    from sensor.io.frames import read_frame
    seen = []

    def journal(rec):  # writer thread: the file must already be complete under its final name
        fr = read_frame(tmp_path / rec["file"])
        seen.append((rec["i"], float(fr.phi[0, 0])))
    with FrameWriter(on_written=journal, max_pending=2) as w:
        for i in range(7):
            w.submit(tmp_path / f"f{i}.exr", *_arrays(i), time_s=i * 1e-3, attrs={"k": i},
                     record={"i": i, "file": f"f{i}.exr"})
    assert seen == [(i, float(i)) for i in range(7)] and w.n_written == 7
    assert not [p for p in tmp_path.iterdir() if ".part" in p.name]  # no temp file left behind
    with pytest.raises(RuntimeError, match="after close"):
        w.submit(tmp_path / "late.exr", *_arrays(0), time_s=0.0)


def test_an_error_in_the_writer_surfaces_in_the_calling_thread(tmp_path):
    """The first failure stops the writer; later frames are neither written nor journalled; the caller gets it."""
    from sensor.errors import DiskFullError
    from sensor.io.fileio import atomic_path
    journal = []
    boom = DiskFullError("disk full while writing f2.exr", path=tmp_path / "f2.exr")

    def write(path, phi, lux, *, time_s, attrs=None):
        with atomic_path(path) as tmp:
            tmp.write_bytes(b"half a frame")
            if path.name == "f2.exr":
                raise boom
    w = FrameWriter(on_written=journal.append, max_pending=1, write=write)
    with pytest.raises(DiskFullError) as err:
        for i in range(50):  # the error reaches a later submit (or close)
            w.submit(tmp_path / f"f{i}.exr", *_arrays(i), time_s=0.0, record=i)
        w.close()
    assert err.value is boom  # the same exception object, with its message naming the file
    w.close(raise_error=False)
    assert journal == [0, 1]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f0.exr", "f1.exr"]  # no temp file, nothing after


def test_exiting_on_the_callers_error_finishes_queued_frames(tmp_path):
    journal = []
    with pytest.raises(KeyboardInterrupt):
        with FrameWriter(on_written=journal.append, max_pending=3) as w:
            for i in range(3):
                w.submit(tmp_path / f"f{i}.exr", *_arrays(i), time_s=0.0, record=i)
            raise KeyboardInterrupt
    assert journal == [0, 1, 2] and sorted(p.name for p in tmp_path.iterdir()) == ["f0.exr", "f1.exr", "f2.exr"]


# ------------------------------------------------------------------------------------------ with Mitsuba
def _scene(tmp_path, duration_s=0.02) -> Path:
    d = copy.deepcopy(BASE)
    d["duration_s"] = duration_s
    d["objects"].append({"name": "disk", "shape": "disk", "radius": 0.02, "position": [0, 0, 0.05],
                         "material": {"reflectance": {"texture": "checker", "squares": 4, "low": 0.1, "high": 0.8}},
                         "motion": {"parametric": [{"rotate": {"axis": [0, 0, 1], "omega_rad_s": 20.0}}]}})
    d["reference"] = {"object": "disk"}
    d["render"]["spp"] = 4
    d["render"]["adaptive"] = {"enabled": False}
    p = tmp_path / "w.yaml"
    p.write_text(yaml.safe_dump(d, sort_keys=False))
    return p


def _same(a: Path, b: Path):
    from sensor.io.frames import read_frames
    sa, sb = read_frames(a), read_frames(b)
    assert [f["file"] for f in sa.manifest["frames"]] == [f["file"] for f in sb.manifest["frames"]]
    for i in range(len(sa)):
        assert sa.read(i).phi.tobytes() == sb.read(i).phi.tobytes()


@pytest.mark.render
@pytest.mark.slow
@needs_mitsuba
def test_render_stops_on_a_write_error_and_resumes_exactly(tmp_path, monkeypatch):
    """A write failing mid-render: render_scene raises it; the journal lists only complete frames; a rerun
    renders only the rest and gives the frames of an uninterrupted render."""
    from render2spike.render import writer as wmod
    from render2spike.render.folder import load_state
    from render2spike.render.job import render_scene
    from render2spike.render.scene import load_scene
    from sensor.io.frames import write_frame
    p = _scene(tmp_path)
    log = lambda *a: None  # noqa: E731
    ref = render_scene(load_scene(p), tmp_path / "ref", progress=False, log=log)
    n = {"k": 0}

    def failing(path, *a, **k):
        n["k"] += 1
        if n["k"] == 3:
            raise OSError(28, "No space left on device")
        return write_frame(path, *a, **k)
    orig_init = wmod.FrameWriter.__init__
    monkeypatch.setattr(wmod.FrameWriter, "__init__", lambda self, *a, **k: orig_init(self, *a, **k, write=failing))
    out = tmp_path / "out"
    with pytest.raises(OSError, match="No space left"):
        render_scene(load_scene(p), out, progress=False, log=log)
    state = load_state(out)
    assert len(state["frames"]) == 2 and not (out / "frames.json").exists()
    assert not [q for q in out.iterdir() if ".part" in q.name]
    monkeypatch.setattr(wmod.FrameWriter, "__init__", orig_init)
    res = render_scene(load_scene(p), out, progress=False, log=log)
    assert res.n_rendered == ref.n_frames - 2
    _same(tmp_path / "ref", out)


_DRIVER = textwrap.dedent("""
    import sys, time
    from render2spike.render import renderer as rmod
    orig = rmod.SceneRenderer.render_frame
    def slow(self, *a, **k):  # frames slow enough to be killed among them
        time.sleep(0.05)
        return orig(self, *a, **k)
    rmod.SceneRenderer.render_frame = slow
    from render2spike.cli import main
    sys.exit(main(["render", sys.argv[1], "--out", sys.argv[2], "--quiet"]))
""")


def _start(scene, out):
    env = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONWARNINGS="ignore")
    return subprocess.Popen([sys.executable, "-c", _DRIVER, str(scene), str(out)], cwd=str(ROOT), env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_journal(proc, out, lines=3, timeout=120):
    j = out / "render_journal.jsonl"
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if j.exists() and len(j.read_text().splitlines()) >= lines:
            return
        if proc.poll() is not None:
            pytest.fail(f"the render ended before it could be stopped: {proc.communicate()}")
        time.sleep(0.005)
    proc.kill()
    pytest.fail("no journal lines in time")


@pytest.mark.render
@pytest.mark.slow
@needs_mitsuba
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM])
def test_killed_render_leaves_complete_journalled_frames_and_resumes(tmp_path, sig):
    """SIGKILL or SIGTERM with frames in the writer's queue: each journal line names a complete frame file,
    SIGTERM also leaves no temp file and exits 143, and the rerun gives the uninterrupted render's frames."""
    from render2spike.render.folder import load_state
    from render2spike.render.job import render_scene
    from render2spike.render.scene import load_scene
    from sensor.io.frames import read_frame
    p = _scene(tmp_path, duration_s=0.1)  # 21 frames
    ref = render_scene(load_scene(p), tmp_path / "ref", progress=False, log=lambda *a: None)
    out = tmp_path / "out"
    proc = _start(p, out)
    _wait_journal(proc, out)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    state = load_state(out)
    n_done = len(state["frames"])
    assert 3 <= n_done < ref.n_frames and not (out / "frames.json").exists()
    for rec in state["frames"].values():
        read_frame(out / rec["file"])  # complete and readable
    visible = sorted(q.name for q in out.iterdir() if q.name.endswith(".exr"))
    assert visible == sorted(rec["file"] for rec in state["frames"].values())  # no unjournalled frame
    if sig == signal.SIGTERM:
        assert proc.returncode == 143 and "terminated" in err, err
        assert not [q for q in out.iterdir() if ".part" in q.name]
        assert not (out / ".render2spike.lock").exists()
    res = render_scene(load_scene(p), out, progress=False, log=lambda *a: None)
    assert res.n_rendered == ref.n_frames - n_done
    assert not [q for q in out.iterdir() if ".part" in q.name]  # a killed writer's temp file is swept
    _same(tmp_path / "ref", out)
    assert json.loads((out / "frames.json").read_text())["complete"]
