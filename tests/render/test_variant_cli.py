"""``--variant`` on `render` and `run`: the asked variant renders (over $RENDER2SPIKE_VARIANT), is recorded, and a
folder rendered by one back end is not resumed by another. The renders run in child processes: Mitsuba's variant
is set for the whole process."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.render.conftest import needs_mitsuba

pytestmark = [pytest.mark.render, needs_mitsuba]

ROOT = Path(__file__).resolve().parents[2]


def _cli(*args, env_variant=None):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env.pop("RENDER2SPIKE_VARIANT", None)
    if env_variant:
        env["RENDER2SPIKE_VARIANT"] = env_variant
    return subprocess.run([sys.executable, "-m", "render2spike", *args], capture_output=True, text=True,
                          timeout=300, env=env, cwd=str(ROOT))


@pytest.mark.slow
def test_run_with_variant_wins_over_the_environment_and_is_recorded(tmp_path, write_scene):
    scene = write_scene()
    out = tmp_path / "run"
    r = _cli("run", str(scene), "--out", str(out), "--quiet", "--spp", "4", "--variant", "scalar_spectral",
             "--keep-frames", env_variant="llvm_ad_spectral")
    assert r.returncode == 0, r.stderr
    manifest = json.loads((out / "frames" / "frames.json").read_text())
    summary = json.loads((out / "summary.json").read_text())
    assert manifest["variant"] == "scalar_spectral" and summary["variant"] == "scalar_spectral"
    assert "`scalar_spectral`" in (out / "summary.md").read_text()
    again = _cli("run", str(scene), "--out", str(out), "--quiet", "--spp", "4", "--variant", "scalar_spectral")
    assert again.returncode == 0, again.stderr  # the same back end resumes: nothing rendered again
    assert json.loads((out / "summary.json").read_text())["frames_rendered_now"] == 0


def _llvm_works():
    from render2spike.render.backend import PREFERRED_VARIANT, find_libllvm, probe_variant
    return probe_variant(PREFERRED_VARIANT, find_libllvm())[0]


needs_llvm = pytest.mark.skipif(not _llvm_works(), reason="Mitsuba's LLVM variant does not work here")


@pytest.mark.slow
@needs_llvm
def test_explicit_auto_ignores_the_environment(tmp_path, write_scene):
    scene = write_scene()
    r = _cli("render", str(scene), "--out", str(tmp_path / "a"), "--quiet", "--spp", "4", "--variant", "auto",
             env_variant="scalar_spectral")
    assert r.returncode == 0, r.stderr
    assert json.loads((tmp_path / "a" / "frames.json").read_text())["variant"] != "scalar_spectral"
    r = _cli("render", str(scene), "--out", str(tmp_path / "b"), "--quiet", "--spp", "4", env_variant="auto")
    assert r.returncode == 0, r.stderr  # RENDER2SPIKE_VARIANT=auto: the automatic choice, not an error


@needs_llvm
def test_another_back_end_does_not_resume_a_folder(tmp_path, write_scene):
    scene = write_scene()
    out = tmp_path / "frames"
    first = _cli("render", str(scene), "--out", str(out), "--quiet", "--spp", "4", "--variant", "scalar_spectral")
    assert first.returncode == 0, first.stderr
    assert "scalar_spectral" in first.stdout
    again = _cli("render", str(scene), "--out", str(out), "--quiet", "--spp", "4", "--variant", "llvm_ad_spectral")
    assert again.returncode != 0
    assert "--overwrite" in again.stderr  # the refusal says how to replace the folder
    assert "--variant scalar_spectral" in again.stderr  # and how to resume it
    assert json.loads((out / "frames.json").read_text())["variant"] == "scalar_spectral"  # left as it was


def test_unknown_variant_lists_the_choices(tmp_path, write_scene, cli):
    r = cli("render", str(write_scene()), "--out", str(tmp_path / "x"), "--variant", "cuda_ad_rgb")
    assert r.returncode == 2
    for name in ("auto", "cuda_ad_spectral", "llvm_ad_spectral", "scalar_spectral"):
        assert name in r.stderr
