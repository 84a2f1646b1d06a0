"""Same scene and seeds -> bitwise-identical frames and spikes: two full runs, and a killed-then-resumed render.

The scene has an environment light, so the light-level measurement (the irradiance meter behind
``illuminance_lux``) is a Monte Carlo estimate. Summed by ``mi.render`` into the meter's pixel with
atomic float32 adds it depended on the thread schedule (4 different values in 8 calls on LLVM with
several threads; 5 in 6 on an H100, where the fix of the time, one Dr.Jit thread, does not apply);
it is now a float64 host sum of per-sample values.
These renders use 8 spp (32 x 48); at higher spp the frames themselves were seen to differ run to run
in a pixel's last bits (Mitsuba's LLVM backend at 121 spp, rarely; on an H100 at 64 spp and more, often:
``benchmarks/repro_check.py``), which the docs state.
"""

import copy
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from tests.render.conftest import BASE, needs_mitsuba

pytestmark = [pytest.mark.render, needs_mitsuba]

ROOT = Path(__file__).resolve().parents[2]


def _scene(tmp_path) -> Path:
    d = copy.deepcopy(BASE)
    d["lights"].append({"name": "sky", "type": "environment", "strength": 0.05})
    d["objects"].append({"name": "disk", "shape": "disk", "radius": 0.1, "position": [0, 0, 0.05],
                         "material": {"reflectance": {"texture": "checker", "squares": 4, "low": 0.1, "high": 0.8}},
                         "motion": {"parametric": [{"rotate": {"axis": [0, 0, 1], "omega_rad_s": 20.0}}]}})
    d["reference"] = {"object": "disk"}
    d["render"]["spp"] = 8
    p = tmp_path / "repro.yaml"
    p.write_text(yaml.safe_dump(d, sort_keys=False))
    return p


def _cli(*args, **kw):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "render2spike", *args], capture_output=True, text=True,
                          timeout=300, env=env, cwd=str(ROOT), **kw)


def _frames(folder):
    from sensor.io.frames import read_frames
    seq = read_frames(folder)
    return [(f["file"], f["time_s"]) for f in seq.manifest["frames"]], [seq.read(i) for i in range(len(seq))]


def _assert_same_frames(a, b):
    (la, fa), (lb, fb) = _frames(a), _frames(b)
    assert la == lb
    for x, y in zip(fa, fb):
        assert x.phi.tobytes() == y.phi.tobytes() and x.illuminance_lux.tobytes() == y.illuminance_lux.tobytes()


def test_light_measurement_is_deterministic(tmp_path):
    """Repeated measurements in one process (with several threads they used to differ in the last bits)."""
    from render2spike.render.renderer import SceneRenderer
    from render2spike.render.scene import load_scene
    r = SceneRenderer(load_scene(_scene(tmp_path)))
    vals = {json.dumps(r.measure_reference(), sort_keys=True) for _ in range(6)}
    assert len(vals) == 1


def _same_estimator(a, b):
    """Two sets of independent estimates (8 each) of one quantity: the same mean, within 5 standard errors
    of the difference, and the same spread, the variance ratio within the F(7, 7) distribution's central
    99.9 % (a wrong sample count or correlated samples change the spread, not the mean)."""
    from scipy import stats
    se = np.sqrt(a.var(ddof=1) / len(a) + b.var(ddof=1) / len(b))
    assert a.mean() > 0 and se > 0
    assert abs(a.mean() - b.mean()) < 5 * se, (a.mean(), b.mean(), se)
    ratio = a.var(ddof=1) / b.var(ddof=1)
    lo, hi = stats.f.ppf([0.0005, 0.9995], len(a) - 1, len(b) - 1)
    assert lo < ratio < hi, (ratio, lo, hi)


@pytest.mark.slow
def test_meter_host_sum_estimates_what_mitsuba_render_does(tmp_path):
    """The meter's per-sample host sum against ``mi.render`` of the same meter (atomic float32 sums).

    8 seeds each; the two means must agree within 5 standard errors of their difference, the
    standard errors taken from the spread of each method's 8 estimates.
    """
    from render2spike.render.builder import build_dict
    from render2spike.render.renderer import SceneRenderer
    from render2spike.render.scene import load_scene
    r = SceneRenderer(load_scene(_scene(tmp_path)))
    mi, n = r.mi, 2048
    r.set_time(0.0)
    d, _ = build_dict(mi, r.scene, for_meter={"point": r.reference["point"], "normal": r.reference["normal"],
                                              "spp": n})
    sc = mi.load_dict(d, optimize=False)
    sensor = sc.sensors()[-1]
    ours = np.array([r._meter_mean(sc, sensor, 100 + k, n) for k in range(8)])
    theirs = np.array([float(np.asarray(mi.render(sc, sensor=sensor, seed=200 + k, spp=n)).ravel()[0])
                       for k in range(8)])
    _same_estimator(ours, theirs)


_SCALAR_METER = """
import json, sys
from pathlib import Path
from render2spike.render.builder import build_dict
from render2spike.render.renderer import SceneRenderer
from render2spike.render.scene import load_scene
r = SceneRenderer(load_scene(Path(sys.argv[1])))
a, b = r.measure_reference(), r.measure_reference()
r.set_time(0.0)
d, _ = build_dict(r.mi, r.scene, for_meter={"point": r.reference["point"], "normal": r.reference["normal"], "spp": 1024})
sc = r.mi.load_dict(d, optimize=False)
print(json.dumps({"variant": r.variant, "same": a == b,
                  "means": [r._meter_mean(sc, sc.sensors()[-1], 300 + k, 1024) for k in range(8)]}))
"""


@pytest.mark.slow
def test_meter_on_the_scalar_variant_is_deterministic_and_agrees(tmp_path):
    """The scalar fallback evaluates the meter one sample per call: the same value twice, and the same
    estimate as the JIT variant's (8 seeds each, within 5 standard errors of the difference)."""
    from render2spike.render.builder import build_dict
    from render2spike.render.renderer import SceneRenderer
    from render2spike.render.scene import load_scene
    scene = _scene(tmp_path)
    env = dict(os.environ, PYTHONPATH=str(ROOT), RENDER2SPIKE_VARIANT="scalar_spectral")
    out = subprocess.run([sys.executable, "-c", _SCALAR_METER, str(scene)], capture_output=True, text=True,
                         timeout=300, env=env, cwd=str(ROOT))
    assert out.returncode == 0, out.stderr[-2000:]
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got["variant"] == "scalar_spectral" and got["same"]
    r = SceneRenderer(load_scene(scene))
    r.set_time(0.0)
    d, _ = build_dict(r.mi, r.scene, for_meter={"point": r.reference["point"], "normal": r.reference["normal"],
                                                "spp": 1024})
    sc = r.mi.load_dict(d, optimize=False)
    jit = np.array([r._meter_mean(sc, sc.sensors()[-1], 400 + k, 1024) for k in range(8)])
    _same_estimator(jit, np.array(got["means"]))


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("repro")
    scene = _scene(tmp)
    outs = []
    for name in ("a", "b"):
        r = _cli("run", str(scene), "--out", str(tmp / name), "--quiet", "--seed", "5", "--keep-frames")
        assert r.returncode == 0, r.stderr
        outs.append(tmp / name)
    return scene, outs


@pytest.mark.slow
def test_two_runs_give_identical_frames_and_spikes(two_runs):
    from sensor.io.spikefile import read_spikes
    _, (a, b) = two_runs
    ma = json.loads((a / "frames" / "frames.json").read_text())
    mb = json.loads((b / "frames" / "frames.json").read_text())
    assert ma["reference"] == mb["reference"] and ma["emitter_scale_w_per_raw"] == mb["emitter_scale_w_per_raw"]
    assert ma["reference"]["raw_e_meter"] > 0  # the environment light really goes through the meter
    _assert_same_frames(a / "frames", b / "frames")
    sa = read_spikes(a / "spikes.npz")
    sb = read_spikes(b / "spikes.npz")
    assert sa.any() and np.array_equal(sa, sb)
    names = [f for f, _ in _frames(a / "frames")[0]]
    assert names == sorted(names)  # file names sort in time order


@pytest.mark.slow
def test_killed_and_resumed_render_is_byte_identical(two_runs, tmp_path, monkeypatch):
    from render2spike.pipeline import simulate_frames
    from render2spike.render import renderer as rmod
    from render2spike.render.folder import load_state
    from render2spike.render.job import render_scene
    from render2spike.render.scene import load_scene
    from sensor.io.spikefile import read_spikes

    scene, (a, _) = two_runs
    out = tmp_path / "frames"
    orig = rmod.SceneRenderer.render_frame
    calls = {"n": 0}

    def killed(self, *args, **kw):
        calls["n"] += 1
        if calls["n"] > 2:
            raise KeyboardInterrupt  # the render dies after two finished frames
        return orig(self, *args, **kw)

    monkeypatch.setattr(rmod.SceneRenderer, "render_frame", killed)
    with pytest.raises(KeyboardInterrupt):
        render_scene(load_scene(scene), out, progress=False, log=lambda *x: None)
    assert len(load_state(out)["frames"]) == 2 and not (out / "frames.json").exists()
    assert not (out / ".render2spike.lock").exists()  # the lock went with the dead render
    # a journal line cut short by the kill is ignored, not fatal
    with open(out / "render_journal.jsonl", "a") as f:
        f.write('{"tick": 9, "fi')
    monkeypatch.setattr(rmod.SceneRenderer, "render_frame", orig)
    # the resumed render must reuse the stored light-level measurement, never measure again
    monkeypatch.setattr(rmod.SceneRenderer, "measure_reference",
                        lambda self: pytest.fail("light level measured again on resume"))
    res = render_scene(load_scene(scene), out, progress=False, log=lambda *x: None)
    assert res.n_rendered == res.n_frames - 2
    _assert_same_frames(a / "frames", out)
    sc = load_scene(scene)
    spikes, _ = simulate_frames(out, sc.profile, "elssim", 5, progress=False)
    ref = read_spikes(a / "spikes.npz")
    assert np.array_equal(spikes.window(0, spikes.shape[0]), ref)


@pytest.mark.slow
def test_second_render_into_a_locked_folder_is_refused(two_runs, tmp_path, monkeypatch):
    """Two renders at once: the second (another process) is refused, naming the holder; nothing is mixed."""
    from render2spike.render import renderer as rmod
    from render2spike.render.job import render_scene
    from render2spike.render.scene import load_scene

    scene, _ = two_runs
    out = tmp_path / "frames"
    orig = rmod.SceneRenderer.render_frame
    seen = {}

    def with_rival(self, *args, **kw):
        if "rc" not in seen:  # while this render holds the folder, a second one starts
            r = _cli("render", str(scene), "--out", str(out), "--lux", "7", "--overwrite", "--quiet")
            seen["rc"], seen["err"] = r.returncode, r.stderr
        return orig(self, *args, **kw)

    monkeypatch.setattr(rmod.SceneRenderer, "render_frame", with_rival)
    render_scene(load_scene(scene), out, progress=False, log=lambda *x: None)
    assert seen["rc"] == 2, seen["err"]
    assert f"pid {os.getpid()}" in seen["err"] and "already writing" in seen["err"]
    assert "Traceback" not in seen["err"] and len(seen["err"].strip().splitlines()) == 1
    from sensor.io.frames import read_frames
    seq = read_frames(out)
    assert {seq.read(i).header["target_lux"] for i in range(len(seq))} == {100.0}


def test_stale_lock_of_a_dead_process_is_taken_over(tmp_path):
    from sensor.io.lock import LOCK_NAME, FolderLock, holder, sweep_parts
    import socket
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    (tmp_path / LOCK_NAME).write_text(json.dumps({"pid": dead.pid, "host": socket.gethostname(),
                                                  "started_utc": "2026-01-01T00:00:00+00:00"}))
    assert holder(tmp_path) is None
    notes = []
    with FolderLock(tmp_path, log=notes.append):
        assert holder(tmp_path)["pid"] == os.getpid()
    assert "stale lock" in notes[0] and not (tmp_path / LOCK_NAME).exists()
    # temp files of the dead writer are swept, those of a live one (this process) kept
    (tmp_path / f".spikes.part-{dead.pid}-abc.npz").write_bytes(b"x" * 10)
    (tmp_path / f".spikes.part-{os.getpid()}-abc.npz").write_bytes(b"x")
    old = tmp_path / ".frame.part-xyz.exr"  # no pid in the name: removed once old
    old.write_bytes(b"x")
    os.utime(old, (time.time() - 7200, time.time() - 7200))
    gone = sweep_parts(tmp_path)
    assert sorted(p.name for p in gone) == sorted([f".spikes.part-{dead.pid}-abc.npz", old.name])


def test_run_into_a_folder_of_another_seed_is_refused(rendered_run, cli):
    a = rendered_run.out  # the session's run, spike seed 3
    argv = list(rendered_run.argv)
    assert argv[-2:] == ["--seed", "3"]
    before = sorted((p.name, p.stat().st_mtime_ns) for p in a.rglob("*"))
    r = cli(*argv[:-1], "6")
    assert r.returncode == 2 and "seed" in r.stderr and "--overwrite" in r.stderr, r.stderr
    assert sorted((p.name, p.stat().st_mtime_ns) for p in a.rglob("*")) == before


def test_render_into_a_folder_of_other_files_is_refused(tmp_path, tmp_path_factory):
    from render2spike.render.job import render_scene
    from render2spike.render.scene import load_scene
    from sensor.errors import InputError
    scene = _scene(tmp_path_factory.mktemp("scene"))  # (outside the folder under test)
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match="holds no render2spike frames"):
        render_scene(load_scene(scene), tmp_path, progress=False, log=lambda *x: None)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


@pytest.mark.slow
def test_progress_bar_never_goes_backwards(tmp_path, monkeypatch):
    """The bar counts camera time: its total is fixed and its position only grows, refinements included."""
    import tqdm.auto

    from render2spike.render.job import render_scene
    from render2spike.render.scene import load_scene
    record = []

    class Recorder(tqdm.auto.tqdm):
        def update(self, n=1):
            out = super().update(n)
            record.append((self.n, self.total))
            return out
    monkeypatch.setattr(tqdm.auto, "tqdm", Recorder)
    p = _scene(tmp_path)
    # a fast disk and a loose base rate: adaptive refinement adds frames between base keyframes (64 spp: the
    # criterion never refines on a change it cannot tell from the Monte Carlo noise of the checker's edges)
    sc = load_scene(p, ["objects.disk.motion.parametric.0.rotate.omega_rad_s=200", "render.keyframe_rate_hz=400",
                        "render.spp=64", "render.adaptive.max_rate_hz=800", "render.adaptive.tolerance=0.05"])
    res = render_scene(sc, tmp_path / "frames", progress=True, log=lambda *x: None)
    assert res.manifest["temporal_sampling"]["n_refined"] > 0
    ns = [n for n, _ in record]
    assert len({t for _, t in record}) == 1 and ns == sorted(ns) and ns[-1] == pytest.approx(record[0][1])
