"""Refusals found by an audit of the CLI: one line naming the file/option, exit code 2, nothing left behind."""

import numpy as np
import pytest


def _tree(root):
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


def _refused(cli, root, *argv, names=()):
    before = _tree(root)
    r = cli(*argv)
    lines = [ln for ln in r.stderr.strip().splitlines() if ln.strip()]
    assert r.returncode == 2, r.stderr
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    for n in names:
        assert n in r.stderr, (n, r.stderr)
    assert _tree(root) == before, "a refusal left something behind"
    return r.stderr


@pytest.mark.parametrize("value", [3e38, 2e9])
@pytest.mark.parametrize("model", ["isi", "elssim"])
def test_simulate_refuses_absurd_rates(cli, tmp_path, value, model):
    np.savez(tmp_path / "rate.npz", rate_e=np.full((20, 8, 8), value, np.float32))
    err = _refused(cli, tmp_path, "simulate", tmp_path / "rate.npz", "--out", tmp_path / "sim" / "x" / "e.npz",
                   "--quiet", "--model", model, names=("rate.npz", "rate_e", "1e+09"))
    assert "above" in err


def test_simulate_refuses_complex_rates(cli, tmp_path):
    np.savez(tmp_path / "rate.npz", rate_e=np.full((20, 8, 8), 3 + 1j, np.complex64))
    _refused(cli, tmp_path, "simulate", tmp_path / "rate.npz", "--out", tmp_path / "sim" / "e.npz", "--quiet",
             names=("rate.npz", "rate_e", "complex64"))


def test_rate_checks_refuse_absurd_and_complex_rates():
    from sensor.errors import InputError
    from sensor.io.reader import ArraySource
    from sensor.rates import RateSchedule, check_rates
    with pytest.raises(InputError, match="above"):
        check_rates(np.full((2, 2, 2), 1.5e9, np.float32))
    check_rates(np.full((2, 2, 2), 1e9, np.float32))  # the bound itself is accepted
    with pytest.raises(InputError, match="complex"):
        RateSchedule(per_interval=True).add(np.ones((2, 2, 2), np.complex128))
    with pytest.raises(InputError, match="complex"):
        ArraySource(np.ones((2, 2, 2), np.complex64))


def test_calibrate_out_without_suffix_is_the_npz_and_is_not_overwritten(cli, tmp_path):
    from tests.sensor.test_from_rsir import synth_maps
    np.savez(tmp_path / "maps.npz", **synth_maps(2))
    assert cli("calibrate", "--from-rsir", tmp_path / "maps.npz", "--out", tmp_path / "keep").returncode == 0
    assert (tmp_path / "keep.npz").is_file()
    _refused(cli, tmp_path, "calibrate", "--from-rsir", tmp_path / "maps.npz", "--out", tmp_path / "keep",
             names=("keep.npz", "--out", "exists"))
    _refused(cli, tmp_path, "calibrate", "--from-rsir", tmp_path / "maps.npz", "--out", tmp_path / "r.txt",
             names=("r.txt", "--out", ".npz"))
    _refused(cli, tmp_path, "calibrate", "--dark", tmp_path / "maps.npz", "--flat", tmp_path / "maps.npz",
             "--out", tmp_path / "q6.txt", names=("q6.txt", "--out", ".npz"))


def _container(path, T=8, H=8, W=8):
    import sensor
    sensor.write_spikes(path, np.zeros((T, H, W), bool), interval_s=50e-6, model="ideal", profile_id="t", seed=0,
                        source="test")


def test_convert_writes_an_empty_recording_to_dat_and_refuses_a_folder_output(cli, tmp_path):
    _container(tmp_path / "spk0.npz", T=0)
    r = cli("convert", tmp_path / "spk0.npz", tmp_path / "newdir" / "x" / "t0.dat")
    assert r.returncode == 0 and "0 intervals" in r.stdout, r.stderr
    assert (tmp_path / "newdir" / "x" / "t0.dat").stat().st_size == 0
    _container(tmp_path / "c1.npz")
    (tmp_path / "adir.npz").mkdir()
    _refused(cli, tmp_path, "convert", tmp_path / "c1.npz", tmp_path / "adir.npz", "--overwrite",
             names=("adir.npz", "folder"))


@pytest.mark.parametrize("drop", [24, 30])
def test_reconstruct_refuses_dropping_the_whole_width(cli, tmp_path, drop):
    (tmp_path / "d.dat").write_bytes(bytes(16 * 24 // 8 * 5))
    _refused(cli, tmp_path, "reconstruct", tmp_path / "d.dat", "--out", tmp_path / "rc" / "dc", "--height", 16,
             "--width", 24, "--drop-columns", drop, names=("d.dat", "--drop-columns", "24"))


@pytest.mark.parametrize("spec, words", [("tfp-dt-denoised:inf", "finite"), ("tfp-dt-denoised:nan", "finite"),
                                         ("tfp-dt-denoised:-1", "above 0"), ("tfp-dt-denoised:1e300", "at most"),
                                         ("tfp:0", "1 or more"), ("tfp:-3", "1 or more")])
def test_method_arguments_checked_when_parsed(spec, words):
    from recon.evaluate import parse_methods
    from sensor.errors import InputError
    with pytest.raises(InputError, match="--methods") as e:
        parse_methods(spec)
    assert words in str(e.value) and "\n" not in str(e.value)
    assert parse_methods("tfp:4,tfp-dt-denoised:1.5")[1].arg == "1.5"


def test_evaluate_refusal_leaves_no_output_folder(cli, tmp_path):
    _refused(cli, tmp_path, "evaluate", "--data", "real:" + str(tmp_path / "uhsr.npz"), "--methods",
             "tfp-dt-denoised:inf", "--out", tmp_path / "ev" / "s", names=("--methods",))


@pytest.mark.parametrize("argv, flag", [
    (["simulate", "rate.npz", "--out", "sim/l.npz", "--seed", "-1"], "--seed"),
    (["run", "translating_object", "--out", "sc/s", "--seed", "-1"], "--seed"),
    (["run", "translating_object", "--out", "sc/s", "--render-seed", "-2"], "--render-seed"),
    (["render", "translating_object", "--out", "sc/s", "--render-seed", "-2"], "--render-seed"),
    (["evaluate", "--data", "real:x.npz", "--out", "ev", "--seed", "-1"], "--seed"),
    (["realism", "x.npz", "--seed", "-1"], "--seed"),
    (["train", "--data", "x", "--out", "tr", "--seed", "-5"], "--seed"),
    (["study", "motion", "translating_object", "--param", "speed_px_per_ms=1,2", "--out", "st", "--seeds", "0,-1"],
     "--seeds"),
    (["study", "motion", "translating_object", "--param", "speed_px_per_ms=1,2", "--out", "st", "--seeds", "1,1"],
     "--seeds"),
])
def test_negative_or_repeated_seeds_refused_at_parsing(cli, tmp_path, monkeypatch, argv, flag):
    monkeypatch.chdir(tmp_path)
    np.savez(tmp_path / "rate.npz", rate_e=np.ones((4, 8, 8), np.float32))
    before = _tree(tmp_path)
    r = cli(*argv)
    assert r.returncode == 2, r.stderr
    assert flag in r.stderr and "seed" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert _tree(tmp_path) == before


@pytest.mark.parametrize("flag, value", [("--attn-window", 1000), ("--width", 100000)])
def test_train_refuses_network_sizes_that_cannot_be_allocated(cli, tmp_path, flag, value):
    _refused(cli, tmp_path, "train", "--data", "davis:dv:crop=32x32:res=48x64:lux=5-50:split=all", "--out",
             tmp_path / "tr" / "aw", flag, value, names=(flag, "at most"))


def test_outputs_below_a_file_are_refused_naming_the_option(cli, tmp_path):
    (tmp_path / "d.dat").write_bytes(bytes(16 * 24 // 8 * 5))
    (tmp_path / "victim.npz").write_bytes(b"keep")
    err = _refused(cli, tmp_path, "reconstruct", tmp_path / "d.dat", "--out", tmp_path / "victim.npz" / "sub",
                   "--height", 16, "--width", 24, names=("victim.npz", "--out", "not a folder"))
    assert "NotADirectoryError" not in err
    np.savez(tmp_path / "rate.npz", rate_e=np.ones((4, 8, 8), np.float32))
    _refused(cli, tmp_path, "simulate", tmp_path / "rate.npz", "--out", tmp_path / "victim.npz" / "e.npz",
             names=("victim.npz", "--out"))


def _with_meta(src, dst, **changes):
    import json
    with np.load(src) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(bytes(arrays["meta_json"]).decode())
    meta.update(changes)
    arrays["meta_json"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    np.savez(dst, **arrays)


@pytest.mark.parametrize("bad", [-1, 0, float("nan"), "fast", True])
@pytest.mark.parametrize("command", [["info"], ["convert", "{}", "out.h5"], ["reconstruct", "{}", "--out", "rc"]])
def test_bad_interval_in_spike_file_metadata_refused(cli, tmp_path, monkeypatch, bad, command):
    monkeypatch.chdir(tmp_path)
    _container(tmp_path / "ok.npz")
    _with_meta(tmp_path / "ok.npz", tmp_path / "bad.npz", interval_s=bad)
    argv = [a.format(tmp_path / "bad.npz") for a in command]
    if command == ["info"]:
        argv.append(str(tmp_path / "bad.npz"))
    _refused(cli, tmp_path, *argv, names=("bad.npz", "interval_s"))


def test_not_a_zip_named_npz_says_so(cli, tmp_path):
    (tmp_path / "garbage.npz").write_bytes(b"this is not an archive at all")
    err = _refused(cli, tmp_path, "info", tmp_path / "garbage.npz", names=("garbage.npz", "not a zip"))
    assert "pickle" not in err


def test_container_with_bad_meta_json_names_the_field(cli, tmp_path):
    _container(tmp_path / "ok.npz")
    with np.load(tmp_path / "ok.npz") as z:
        arrays = {k: z[k] for k in z.files}
    arrays["meta_json"] = np.frombuffer(b"{not json", np.uint8)
    np.savez(tmp_path / "bad.npz", **arrays)
    err = _refused(cli, tmp_path, "info", tmp_path / "bad.npz", names=("bad.npz", "meta_json"))
    assert "not a readable" not in err


def test_garbage_checkpoint_is_named_without_pointing_to_an_unsafe_load(tmp_path):
    pytest.importorskip("torch")
    from recon.nets.checkpoint import load_checkpoint
    from sensor.errors import InputError
    (tmp_path / "garbage.npz").write_bytes(b"\x00\x01 not a checkpoint" * 10)
    np.savez(tmp_path / "arrays.npz", a=np.zeros(3))  # a zip archive, but not torch's
    for name in ("garbage.npz", "arrays.npz"):
        with pytest.raises(InputError) as e:
            load_checkpoint(tmp_path / name)
        msg = str(e.value)
        assert name in msg and "weights_only" not in msg and "Re-running" not in msg and "\n" not in msg, msg


@pytest.mark.parametrize("argv, words", [
    (["--spp", "0"], ["--spp", ">= 1", "got 0"]),
    (["--keyframe-rate", "-5"], ["--keyframe-rate", "above 0"]),
    (["--set", "render.spp=0"], ["render.spp", "'auto' or an integer >= 1", "got 0"]),
    (["--set", "camera.profile.window=[-1,0,16,24]"], ["camera.profile.window.0", "minimum of 0"]),
])
def test_scene_option_messages_say_what_is_expected(cli, tmp_path, argv, words):
    pytest.importorskip("jsonschema")
    err = _refused(cli, tmp_path, "render", "translating_object", "--out", tmp_path / "r", *argv, names=words)
    assert "allowed forms" not in err and "max_rate_hz" not in err


def test_study_motion_refuses_a_window_longer_than_the_clip_before_rendering(cli, tmp_path):
    pytest.importorskip("jsonschema")
    _refused(cli, tmp_path, "study", "motion", "translating_object", "--param", "speed_px_per_ms=1,2", "--out",
             tmp_path / "st", "--window", 100000, "--duration", 0.001, "--quiet", names=("--window", "100000"))


def test_vidar_raw_layout_with_another_width_is_refused(cli, tmp_path):
    (tmp_path / "d.dat").write_bytes(bytes(16 * 8 // 8 * 600))
    _refused(cli, tmp_path, "convert", tmp_path / "d.dat", tmp_path / "r4.npz", "--layout", "vidar-raw",
             "--height", 16, "--width", 8, names=("d.dat", "--width", "416"))
    assert cli("convert", tmp_path / "d.dat", tmp_path / "r4.npz", "--layout", "dat", "--height", 16,
               "--width", 8).returncode == 0


def test_repeated_spec_keys_and_param_values_refused():
    from recon.spec import parse_data_spec
    from render2spike.studies.motion import parse_param
    from sensor.errors import InputError
    with pytest.raises(InputError, match="twice"):
        parse_data_spec("real:uhsr.npz:clip=32:clip=64")
    assert parse_data_spec("real:uhsr.npz:clip=32") is not None
    with pytest.raises(InputError, match="--param"):
        parse_param("speed_px_per_ms=1,1")
    assert parse_param("speed_px_per_ms=1,2") == ("speed_px_per_ms", [1.0, 2.0])


@pytest.mark.parametrize("argv, flag", [(["--checkpoint", "nonexist.pt"], "--checkpoint"), (["--sigma", "3"], "--sigma"),
                                        (["--windows", "4"], "--windows")])
def test_reconstruct_refuses_options_of_other_methods(cli, tmp_path, argv, flag):
    (tmp_path / "d.dat").write_bytes(bytes(16 * 24 // 8 * 5))
    _refused(cli, tmp_path, "reconstruct", tmp_path / "d.dat", "--out", tmp_path / "rc", "--height", 16, "--width",
             24, "--method", "tfp", *argv, names=(flag, "applies only"))


def test_convert_refuses_options_that_do_not_apply(cli, tmp_path):
    _container(tmp_path / "x.npz")
    _refused(cli, tmp_path, "convert", tmp_path / "x.npz", tmp_path / "x.dat", "--h5-uint8",
             names=("--h5-uint8", "x.dat"))
    _refused(cli, tmp_path, "convert", tmp_path / "x.npz", tmp_path / "y.h5", "--height", 7,
             names=("--height", "x.npz"))


def test_ideal_model_with_a_reset_is_refused():
    from sensor.errors import InputError
    from sensor.models.spec import parse_model_spec
    for spec in ("ideal:crossing", "ideal:interval"):
        with pytest.raises(InputError, match="no reset"):
            parse_model_spec(spec)
    assert parse_model_spec("ideal").reset is None and parse_model_spec("elssim:crossing").reset == "crossing"


def test_run_refuses_a_preview_window_below_one(cli, tmp_path):
    _refused(cli, tmp_path, "run", "translating_object", "--out", tmp_path / "r", "--preview-window", 0,
             names=("--preview-window", ">= 1"))


def test_info_raw_with_another_width_and_realism_dark_mode_without_fit_refused(cli, tmp_path):
    (tmp_path / "d.dat").write_bytes(bytes(1 * 416 // 8 * 3))
    _refused(cli, tmp_path, "info", tmp_path / "d.dat", "--height", 1, "--width", 8, "--raw", names=("--width",))
    assert cli("info", tmp_path / "d.dat", "--height", 1, "--width", 416, "--raw").returncode == 0
    _container(tmp_path / "rec.npz", T=64)
    _refused(cli, tmp_path, "realism", tmp_path / "rec.npz", "--out", tmp_path / "re", "--fit-dark-mode", "events",
             names=("--fit-dark-mode", "--fit"))
    _refused(cli, tmp_path, "realism", tmp_path / "rec.npz", "--out", tmp_path / "rec.npz" / "x",
             names=("rec.npz", "--out"))


def test_synth_refuses_fewer_sequences_than_it_writes(tmp_path, capsys):
    from recon.synth import main
    with pytest.raises(SystemExit) as e:
        main([str(tmp_path / "dv"), "--sequences", "3", "--frames", "2", "--size", "8x8"])
    assert e.value.code == 2 and "--sequences" in capsys.readouterr().err
    assert not (tmp_path / "dv").exists()


@pytest.mark.parametrize("command", [["render", "translating_object"], ["run", "translating_object"],
                                     ["dataset", "spec.yaml"]])
def test_render_run_dataset_refuse_an_output_below_a_file(cli, tmp_path, monkeypatch, command):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "victim.npz").write_bytes(b"keep")
    err = _refused(cli, tmp_path, *command, "--out", tmp_path / "victim.npz" / "sub", names=("victim.npz", "--out"))
    assert "NotADirectoryError" not in err


def test_simulate_refuses_frames_whose_rate_is_absurd(cli, tmp_path):
    import sensor
    sensor.write_frames(tmp_path / "frames", np.full((3, 8, 16), 1e30, np.float32), [0.0, 0.005, 0.01])
    _refused(cli, tmp_path, "simulate", tmp_path / "frames", "--out", tmp_path / "s" / "e.npz", "--quiet",
             "--model", "isi", names=("frames", "Phi", "1e+09"))


def test_sigterm_ends_a_simulation_stuck_in_a_kernel_at_once(tmp_path):
    """At the rate bound the isi kernel runs for minutes per block; SIGTERM must still end the process at once
    (exit code 143, nothing left behind), not after the block that a worker thread is computing."""
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path
    np.savez(tmp_path / "r.npz", rate_e=np.full((2000, 32, 32), 1e9, np.float32))
    root = Path(__file__).resolve().parents[1]
    env = dict(os.environ, PYTHONPATH=str(root), RENDER2SPIKE_THREADS="2")
    p = subprocess.Popen([sys.executable, "-m", "render2spike", "simulate", str(tmp_path / "r.npz"), "--out",
                          str(tmp_path / "s" / "e.npz"), "--quiet", "--model", "isi"], env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        t0 = time.time()
        while not list((tmp_path / "s").glob(".e.part-*")) and time.time() - t0 < 120 and p.poll() is None:
            time.sleep(0.05)
        time.sleep(1.0)  # the kernel is running its first block
        assert p.poll() is None, p.communicate()
        p.send_signal(signal.SIGTERM)
        t1 = time.time()
        _, err = p.communicate(timeout=60)
        assert p.returncode == 143 and "terminated" in err, err
        assert time.time() - t1 < 10
        assert not (tmp_path / "s").exists()
    finally:
        if p.poll() is None:
            p.kill()
