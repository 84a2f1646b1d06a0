"""``render2spike run`` holds the frames in memory unless ``--keep-frames``: the same spikes bit for bit, no
frames folder, nothing written when the render fails; ``--keep-frames`` writes OUT/frames and resumes."""

import json

import numpy as np
import pytest

from tests.render.conftest import needs_mitsuba

#: the golden test's window and clip (16 x 24, 10 ms = 200 intervals), spike seed 3
ARGS = ("rotating_disk", "--set", "camera.profile.window=[120,180,16,24]", "--duration", "0.01", "--spp", "8",
        "--quiet", "--seed", "3")


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory):
    from tests.conftest import run_cli
    base = tmp_path_factory.mktemp("memchain")
    for name, extra in (("memory", ()), ("kept", ("--keep-frames",))):
        r = run_cli(("run", *ARGS, "--out", str(base / name), *extra))
        assert r.returncode == 0, r.stderr
    return base / "memory", base / "kept"


@needs_mitsuba
@pytest.mark.render
def test_frames_in_memory_give_the_kept_frames_spikes(two_runs):
    from sensor.io.spikefile import read_spikes
    mem, kept = two_runs
    assert not (mem / "frames").exists() and (kept / "frames" / "frames.json").is_file()
    a, b = read_spikes(mem / "spikes.npz"), read_spikes(kept / "spikes.npz")
    assert a.any() and np.array_equal(a, b)
    sa, sb = (json.loads((p / "summary.json").read_text()) for p in two_runs)
    assert (sa["frames_kept"], sb["frames_kept"]) == (False, True)
    assert "frames" not in sa["files"] and sb["files"]["frames"] == str(kept / "frames")
    for k in ("frames", "spp", "scene_hash", "render_noise_ratio_mean", "mean_focal_plane_phi_e_per_s_m2"):
        assert sa[k] == sb[k], k  # the manifest's figures, and the previews' frames, are the same
    assert "held in memory" in (mem / "summary.md").read_text()
    assert "a rerun resumes" in (kept / "summary.md").read_text()


@needs_mitsuba
@pytest.mark.render
def test_only_kept_frames_are_resumed(two_runs, cli, tmp_path):
    import shutil
    for name in ("memory", "kept"):
        shutil.copytree(two_runs[0].parent / name, tmp_path / name)
    r = cli("run", *ARGS, "--out", tmp_path / "kept", "--keep-frames")
    assert r.returncode == 0, r.stderr
    s = json.loads((tmp_path / "kept" / "summary.json").read_text())
    assert s["frames_rendered_now"] == 0 and s["frames_kept"]
    r = cli("run", *ARGS, "--out", tmp_path / "memory")
    assert r.returncode == 0, r.stderr
    s = json.loads((tmp_path / "memory" / "summary.json").read_text())
    assert s["frames_rendered_now"] == s["frames"] > 0 and not (tmp_path / "memory" / "frames").exists()


@needs_mitsuba
@pytest.mark.render
def test_a_failure_mid_render_leaves_nothing(cli, tmp_path, monkeypatch):
    from render2spike.render import job
    real, calls = job._Keyframes.render, []

    def render(self, tick):  # the third keyframe's render fails, as a lost device or full memory would
        calls.append(tick)
        if len(calls) == 3:
            raise OSError("the render failed")
        return real(self, tick)

    monkeypatch.setattr(job._Keyframes, "render", render)
    (tmp_path / "keep.txt").write_text("mine")
    r = cli("run", *ARGS, "--out", tmp_path / "a" / "out")
    assert r.returncode != 0 and "the render failed" in r.stderr, r.stderr
    assert len(calls) == 3 and sorted(p.name for p in tmp_path.iterdir()) == ["keep.txt"]
