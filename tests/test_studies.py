"""Lux sweep study: linear rescaling of frames, job reproducibility, and the same rows on Dask as sequentially."""

import numpy as np
import pytest

import sensor
from render2spike.studies import plan_lux_sweep, run_job, run_jobs, summarise, write_study


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    folder = tmp_path_factory.mktemp("study") / "frames"
    H, W = 16, 24
    t = np.arange(0, 0.0201, 0.001)
    yy, xx = np.mgrid[0:H, 0:W]
    base = np.stack([0.3 + 0.25 * np.sin(2 * np.pi * (xx - 300 * ti) / 12) * np.cos(2 * np.pi * yy / 8) for ti in t])
    prof = sensor.SensorProfile.load("vidar-default")
    phi = base * 900 / (prof.pixel_pitch_m ** 2 * prof.fill_factor * prof.interval_s)  # 900 e-/interval at 1.0
    sensor.write_frames(folder, phi.astype(np.float32), t, manifest={"illuminance_lux": 100.0})
    return folder


def test_signal_scales_linearly_with_lux(frames):
    jobs = plan_lux_sweep(frames, [1.0, 10.0], ["ideal"], [0], window=64, n_centers=2, methods=["tfp"])
    a, b = run_job(jobs[0]), run_job(jobs[1])
    # rendering is linear in the light: 10x the lux is 10x the clean photoelectron rate, exactly
    np.testing.assert_allclose([r["signal_e_per_interval"] for r in b],
                               [10 * r["signal_e_per_interval"] for r in a], rtol=1e-5)
    assert a[0]["signal_e_per_interval"] == pytest.approx(900 * 0.3 / 100, rel=0.1)


def test_more_light_reconstructs_better(frames):
    jobs = plan_lux_sweep(frames, [2.0, 200.0], ["elssim"], [0], window=128, n_centers=2, methods=["tfp-dt"])
    s = summarise(run_jobs(jobs, progress=False))
    assert s[1]["psnr_db"] > s[0]["psnr_db"] + 5


def test_dask_gives_the_same_rows_as_sequential(frames, tmp_path):
    distributed = pytest.importorskip("dask.distributed")
    jobs = plan_lux_sweep(frames, [5.0, 50.0], ["elssim", "isi"], [0, 1], window=64, n_centers=2,
                          methods=["tfp", "tfp-dt"])
    seq = run_jobs(jobs, progress=False)
    with distributed.Client(processes=False, n_workers=1, threads_per_worker=2, dashboard_address=None) as client:
        par = run_jobs(jobs, client, progress=False)
    strip = lambda rows: [{k: v for k, v in r.items() if k != "job_seconds"} for r in rows]  # noqa: E731
    assert strip(par) == strip(seq)
    paths = write_study(tmp_path, seq, jobs, "test")
    assert "| elssim |" in (tmp_path / "summary.md").read_text() and len(paths) == 5


def test_study_errors_are_clear(frames):
    with pytest.raises(sensor.InputError, match="window"):
        plan_lux_sweep(frames, [1.0], ["elssim"], [0], window=100000)
    with pytest.raises(sensor.UnknownMethodError, match="valid choices"):
        plan_lux_sweep(frames, [1.0], ["davis"], [0], window=64)
    with pytest.raises(sensor.InputError, match="lux"):
        plan_lux_sweep(frames, [-1.0], ["elssim"], [0], window=64)
