"""Lux sweep study: linear rescaling of frames, pre-roll, seed spread, noise-free row, Dask = sequential."""

import json

import numpy as np
import pytest

import sensor
from render2spike.studies import plan_lux_sweep, run_job, run_jobs, summarise, write_study
from render2spike.studies.common import (NOISE_FREE_LABEL, parse_model_spec, profile_for, seed_spread,
                                         simulate_clip)
from tests.conftest import Z


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    folder = tmp_path_factory.mktemp("study") / "frames"
    H, W = 16, 24
    t = np.arange(0, 0.0201, 0.001)
    yy, xx = np.mgrid[0:H, 0:W]
    base = np.stack([0.3 + 0.25 * np.sin(2 * np.pi * (xx - 300 * ti) / 12) * np.cos(2 * np.pi * yy / 8) for ti in t])
    prof = sensor.SensorProfile.load("vidar-default")
    # 0.45 threshold per interval at 1.0 (7,200 e-/interval with vidar-default's 16,000 e-)
    phi = base * 0.45 * prof.threshold_e / (prof.pixel_pitch_m ** 2 * prof.fill_factor * prof.interval_s)
    sensor.write_frames(folder, phi.astype(np.float32), t, manifest={"illuminance_lux": 100.0})
    return folder


def test_signal_scales_linearly_with_lux(frames):
    jobs = plan_lux_sweep(frames, [1.0, 10.0], ["ideal"], [0], window=64, n_centers=2, methods=["tfp"])
    a, b = run_job(jobs[0]), run_job(jobs[1])
    # rendering is linear in the light: 10x the lux is 10x the clean photoelectron rate, exactly
    np.testing.assert_allclose([r["signal_e_per_interval"] for r in b],
                               [10 * r["signal_e_per_interval"] for r in a], rtol=1e-5)
    assert a[0]["signal_e_per_interval"] == pytest.approx(0.45 * 16000 * 0.3 / 100, rel=0.1)
    # the noise-free window average is scored once per (lux, centre, seed) of the first model
    assert sum(r["method"] == NOISE_FREE_LABEL for r in a) == 2


def test_preroll_removes_the_phase_lock_of_the_ideal_model():
    """From zero charge every ideal pixel of one rate fires in step: TFP over the first window is floor(W lam/theta).

    After the pre-roll the phases are spread over the threshold and the mean count is W lam / theta; the count of
    a pixel is floor or ceil of it, so the mean of N pixels has sd <= 0.5 / sqrt(N) if phases were independent."""
    prof = profile_for("vidar-default", (20, 30), "ideal")
    theta = prof.threshold_e
    lam = 2.5 * theta / 64  # 2.5 spikes per 64-interval window
    rate = np.full((2, 20, 30), lam, np.float32)
    t = np.array([0.0, 64 * prof.interval_s])
    cold = simulate_clip(rate, t, prof, "ideal", 0, preroll=0)[:64].sum(0)
    warm = simulate_clip(rate, t, prof, "ideal", 0, preroll=2000)[:64].sum(0)
    assert cold.mean() == 2.0  # phase-locked: 0.8x the truth
    tol = Z * 0.5 / np.sqrt(cold.size)
    assert abs(warm.mean() - 2.5) < tol
    assert set(np.unique(warm)) <= {2, 3}


def test_more_light_reconstructs_better_and_spread_is_over_seeds(frames, tmp_path):
    jobs = plan_lux_sweep(frames, [2.0, 200.0], ["elssim"], [0, 1, 2], window=128, n_centers=2,
                          methods=["tfp-dt"])
    rows = run_jobs(jobs, progress=False)
    s = [r for r in summarise(rows) if r["model"] == "elssim"]
    assert s[1]["psnr_db"] > s[0]["psnr_db"] + 5
    # error bar = sd over seeds of the per-seed means (centres averaged inside a seed)
    sel = [r for r in rows if r["lux"] == 2.0 and r["model"] == "elssim"]
    per_seed = [np.mean([r["psnr_db"] for r in sel if r["seed"] == k]) for k in (0, 1, 2)]
    assert s[0]["psnr_sd"] == pytest.approx(np.std(per_seed, ddof=1)) and s[0]["n_seeds"] == 3
    assert s[0]["few_light_spikes"] and not s[1]["few_light_spikes"]
    write_study(tmp_path, rows, jobs, "test")
    md = (tmp_path / "summary.md").read_text()
    assert "| noise-free |" in md and "Warnings" in md and "±" in md and "e-/int" in md
    assert (tmp_path / "ssim_vs_lux.png").stat().st_size > 1000


def test_dask_gives_the_same_rows_as_sequential(frames, tmp_path):
    distributed = pytest.importorskip("dask.distributed")
    jobs = plan_lux_sweep(frames, [5.0, 50.0], ["elssim", "isi"], [0, 1], window=64, n_centers=2,
                          methods=["tfp", "tfp-dt"])
    seq = run_jobs(jobs, progress=False)
    with distributed.Client(processes=False, n_workers=1, threads_per_worker=2, dashboard_address=None) as client:
        par = run_jobs(jobs, client, progress=False)
    strip = lambda rows: json.dumps([{k: v for k, v in r.items() if k != "job_seconds"} for r in rows])  # noqa: E731
    assert strip(par) == strip(seq)
    paths = write_study(tmp_path, seq, jobs, "test")
    assert "| elssim |" in (tmp_path / "summary.md").read_text() and len(paths) == 6


def test_seed_spread_groups():
    rows = [{"g": "a", "seed": s, "v": v} for s, v in ((0, 1.0), (0, 3.0), (1, 4.0))]
    (r,) = seed_spread(rows, ("g",), "v")
    assert r["mean"] == pytest.approx(3.0) and r["sd"] == pytest.approx(np.std([2.0, 4.0], ddof=1))


def test_study_errors_are_clear(frames):
    with pytest.raises(sensor.InputError, match="window"):
        plan_lux_sweep(frames, [1.0], ["elssim"], [0], window=100000)
    with pytest.raises(sensor.UnknownMethodError, match="valid choices"):
        plan_lux_sweep(frames, [1.0], ["davis"], [0], window=64)
    with pytest.raises(sensor.InputError, match="lux"):
        plan_lux_sweep(frames, [-1.0], ["elssim"], [0], window=64)
    with pytest.raises(sensor.UnknownMethodError):
        plan_lux_sweep(frames, [1.0], ["elssim"], [0], window=64, methods=["nope"])
    assert parse_model_spec("elssim:crossing") == ("elssim", "crossing")


def test_cli_old_and_new_forms(frames, tmp_path):
    from render2spike.cli import main
    args = ["--out", str(tmp_path / "a"), "--lux", "5,50", "--models", "ideal", "--seeds", "0", "--window", "64",
            "--preroll", "50", "--quiet"]
    assert main(["study", str(frames)] + args) == 0  # the old form: study FRAMES ...
    assert (tmp_path / "a" / "ssim_vs_lux.png").is_file()
    args[1] = str(tmp_path / "b")
    assert main(["study", "lux", str(frames)] + args) == 0
    assert (tmp_path / "a" / "summary.csv").read_text() == (tmp_path / "b" / "summary.csv").read_text()
    assert main(["study", "nonsense"]) == 2


def test_a_network_checkpoint_is_a_method(frames, tmp_path):
    torch = pytest.importorskip("torch")
    from recon.nets import RSIRConfig, RSIRNet, save_checkpoint
    torch.manual_seed(0)
    ckpt = tmp_path / "net.pt"
    save_checkpoint(ckpt, RSIRNet(RSIRConfig.tiny(width=8)), None, step=0)
    jobs = plan_lux_sweep(frames, [50.0], ["elssim"], [0], window=320, n_centers=1,
                          methods=["tfp", f"rsir:{ckpt}=tiny net"], preroll=100)
    rows = run_job(jobs[0])
    assert {r["method"] for r in rows} == {"TFP (M=320)", "tiny net", NOISE_FREE_LABEL}
    with pytest.raises(sensor.InputError, match="window 320"):
        plan_lux_sweep(frames, [50.0], ["elssim"], [0], window=64, methods=[f"rsir:{ckpt}"])


def test_the_ideal_models_profile_is_the_one_its_spikes_obey():
    """ideal spikes have no dark floor: the dead-time correction must not take one off (nor PRNU, hot pixels)."""
    from recon.classic import deadtime_correct
    prof = profile_for("vidar-default", (6, 8), "ideal")
    assert prof.reset == "interval" and not prof.dark_spike_rate.any() and not prof.hot_mask.any()
    assert np.all(prof.prnu_gain == 1.0) and not np.any(prof.refractory_s)
    assert profile_for("vidar-default", (6, 8), "elssim").dark_spike_rate.min() > 0
    lam = prof.threshold_e / 9.5  # fires every ceil(9.5) = 10 intervals
    spikes = sensor.simulate(np.full((400, 6, 8), lam, np.float32), prof, "ideal")
    est = deadtime_correct(spikes.mean(axis=0, dtype=np.float32), prof)
    # the interval-reset law of a rate of 1/10: any light in (theta / 10, theta / 9] gives it
    assert np.all(est > prof.threshold_e / 10.5) and np.all(est <= prof.threshold_e / 9 * 1.001)
