"""Resume after an interrupted render, refusal of a changed scene, the CLI, and the backend probe."""

import json
from pathlib import Path

import pytest

from tests.render.conftest import needs_mitsuba


@pytest.mark.render
@needs_mitsuba
def test_resume_after_interrupt(tmp_path, write_scene, monkeypatch):
    from render2spike.render import renderer as rmod
    from render2spike.render.folder import load_state
    from render2spike.render.job import render_scene
    from render2spike.render.scene import load_scene
    from sensor.errors import InputError

    p = write_scene({"duration_s": 0.02}, name="s.yaml")
    out = tmp_path / "frames"
    calls = {"n": 0}
    orig = rmod.SceneRenderer.render_frame

    def flaky(self, *a, **k):
        calls["n"] += 1
        if calls["n"] > 2:
            raise KeyboardInterrupt
        return orig(self, *a, **k)
    monkeypatch.setattr(rmod.SceneRenderer, "render_frame", flaky)
    with pytest.raises(KeyboardInterrupt):
        render_scene(load_scene(p, ["render.spp=8", "render.static_reuse=false"]), out, progress=False, log=lambda *a: None)
    state = load_state(out)
    assert len(state["frames"]) == 2 and not (out / "frames.json").exists()
    done = {rec["file"]: (out / rec["file"]).read_bytes() for rec in state["frames"].values()}
    monkeypatch.setattr(rmod.SceneRenderer, "render_frame", orig)

    res = render_scene(load_scene(p, ["render.spp=8", "render.static_reuse=false"]), out, progress=False, log=lambda *a: None)
    assert res.n_frames == 5 and res.n_rendered == 3  # only the missing frames were rendered
    for name, data in done.items():
        assert (out / name).read_bytes() == data  # finished frames kept untouched
    again = render_scene(load_scene(p, ["render.spp=8", "render.static_reuse=false"]), out, progress=False, log=lambda *a: None)
    assert again.up_to_date and again.n_rendered == 0

    with pytest.raises(InputError, match="different scene or settings"):
        render_scene(load_scene(p, ["render.spp=8", "render.static_reuse=false"], lux=7.0), out, progress=False, log=lambda *a: None)
    res2 = render_scene(load_scene(p, ["render.spp=8", "render.static_reuse=false"], lux=7.0), out, overwrite=True, progress=False,
                        log=lambda *a: None)
    assert res2.n_rendered == 5
    from sensor.io.frames import read_frames
    seq = read_frames(out)
    assert {seq.read(i).header["target_lux"] for i in range(len(seq))} == {7.0}  # never mixed


def test_cli_help_teaches(cli):
    for cmd in (["--help"], ["render", "--help"], ["run", "--help"]):
        r = cli(*cmd)
        assert r.returncode == 0, r.stderr
    assert "lux" in cli("render", "--help").stdout and "e-/(s m^2)" in cli("run", "--help").stdout


def test_cli_bad_scene_is_one_line(tmp_path, cli):
    p = tmp_path / "bad.yaml"
    p.write_text("camera: {profile: x, focal_length_mm: -1, f_number: 2}\n")
    r = cli("render", str(p), "--out", str(tmp_path / "o"))
    assert r.returncode == 2
    assert "Traceback" not in r.stderr and "camera.focal_length_mm" in r.stderr and str(p) in r.stderr


@pytest.mark.render
@needs_mitsuba
def test_cli_run_end_to_end(rendered_run):
    out = rendered_run.out  # the session's run, made in-process by the CLI (exit code 0):
    assert rendered_run.argv == ("run", "lambertian_plane", "--out", str(out), "--duration", "0.01", "--spp", "8",
                                 "--quiet", "--keep-frames", "--seed", "3")
    s = json.loads((out / "summary.json").read_text())
    assert s["intervals"] == 200 and s["frames"] == 3 and s["illuminance_lux"] == 100
    for f in ("spikes.npz", "preview.png", "preview.gif", "summary.md", "frames/frames.json"):
        assert (out / f).is_file(), f
    # spike rate vs the flat field's expected photoelectrons / threshold (ideal counting; dark 0 in the
    # plane's profile is 0.0047/interval): within 10 % -- a units check, not a noise-model test
    expected = s["mean_photoelectrons_per_interval"] / 2000.0 + 0.0047
    assert abs(s["spike_rate_per_interval"] / expected - 1) < 0.1, (s["spike_rate_per_interval"], expected)


def test_backend_probe_survives_a_bad_libllvm():
    from render2spike.render.backend import probe_variant
    bad = Path("/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1")
    if not bad.exists():
        pytest.skip("no LLVM 15 here to provoke the abort")
    ok, msg = probe_variant("llvm_ad_spectral", str(bad))
    assert not ok and msg  # the child died, we did not


@pytest.mark.render
@needs_mitsuba
def test_resumed_render_writes_the_same_files_as_an_uninterrupted_one(tmp_path, write_scene, monkeypatch):
    """Which frames carry a measured render_noise_ratio depends on their place in the clip, not on the run:
    a render interrupted after 2 frames and resumed writes every frame file byte for byte as one run does."""
    from render2spike.render import renderer as rmod
    from render2spike.render.job import render_scene
    from render2spike.render.scene import load_scene
    from sensor.io.frames import read_frames

    p = write_scene({"duration_s": 0.02}, name="s.yaml")
    quiet = dict(progress=False, log=lambda *a: None)
    whole = render_scene(load_scene(p, ["render.spp=8", "render.static_reuse=false"]), tmp_path / "whole", **quiet)
    orig = rmod.SceneRenderer.render_frame
    calls = {"n": 0}

    def flaky(self, *a, **k):
        calls["n"] += 1
        if calls["n"] > 2:
            raise KeyboardInterrupt
        return orig(self, *a, **k)
    monkeypatch.setattr(rmod.SceneRenderer, "render_frame", flaky)
    with pytest.raises(KeyboardInterrupt):
        render_scene(load_scene(p, ["render.spp=8", "render.static_reuse=false"]), tmp_path / "resumed", **quiet)
    monkeypatch.setattr(rmod.SceneRenderer, "render_frame", orig)
    res = render_scene(load_scene(p, ["render.spp=8", "render.static_reuse=false"]), tmp_path / "resumed", **quiet)
    assert res.n_rendered == whole.n_frames - 2 and res.n_frames == whole.n_frames
    names = sorted(f.name for f in (tmp_path / "whole").glob("*.exr"))
    assert len(names) == whole.n_frames
    assert sorted(f.name for f in (tmp_path / "resumed").glob("*.exr")) == names
    for name in names:
        assert (tmp_path / "resumed" / name).read_bytes() == (tmp_path / "whole" / name).read_bytes(), name
    ratios = [read_frames(tmp_path / "resumed").read(i).header["render_noise_ratio"] for i in range(res.n_frames)]
    assert ratios[0] == ratios[0] and all(r != r for r in ratios[1:])  # tick 0 measured, the others NaN
