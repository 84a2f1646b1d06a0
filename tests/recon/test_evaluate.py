"""Metrics, the evaluation table on tiny data, and the train / evaluate / reconstruct commands end to end."""

import csv
import json

import numpy as np
import pytest

from recon.evaluate import PSNR_CAP_DB, parse_methods, psnr_ssim
from recon.synth import make_davis_like
from sensor import InputError, UnknownMethodError

torch = pytest.importorskip("torch")


@pytest.fixture
def tiny_davis(tmp_path):
    root = make_davis_like(tmp_path / "davis", ["tr-a", "tr-b", "te-a"], n_frames=3, size=(8, 8), seed=4)
    split = tmp_path / "split.json"
    split.write_text(json.dumps({"train": ["tr-a", "tr-b"], "test": ["te-a"]}))
    return f"davis:{root}:split_file={split}:res=8x8:warmup=8:frame_stride=2:lux=100"


def test_psnr_ssim_hand_cases():
    ref = np.linspace(0.0, 2.0, 64).reshape(8, 8)
    p, s = psnr_ssim(ref, ref)
    assert p == PSNR_CAP_DB and s == pytest.approx(1.0)  # exact match: capped, finite
    # all-zero prediction: MSE = mean(clip(ref / w, 0, 1)^2) with w the 99.5th percentile of ref
    w = np.percentile(ref, 99.5)
    mse = np.mean(np.clip(ref / w, 0, 1) ** 2)
    assert psnr_ssim(np.zeros_like(ref), ref)[0] == pytest.approx(-10 * np.log10(mse))
    # a gain error of the prediction is not fitted away
    assert psnr_ssim(0.5 * ref, ref)[0] < 20.0


def test_parse_methods():
    ms = parse_methods("tfp,tfp:4000,tfi,tfp-dt,rsir:runs/a/model.pt=Mine")
    assert [m.kind for m in ms] == ["tfp", "tfp", "tfi", "tfp-dt", "rsir"]
    assert ms[1].label == "TFP (M=4000)" and ms[4].label == "Mine" and ms[4].arg == "runs/a/model.pt"
    with pytest.raises(UnknownMethodError):
        parse_methods("bsf")
    with pytest.raises(InputError, match="checkpoint"):
        parse_methods("rsir")


def _cli(*argv):
    from render2spike.cli import main
    return main([str(a) for a in argv])


@pytest.mark.torch
def test_train_resume_evaluate_reconstruct_cli(tiny_davis, tmp_path, capsys):
    run = tmp_path / "run"
    net = ["--width", "8", "--res-blocks", "1", "--heads", "2", "--attn-window", "4"]
    assert _cli("train", "--data", tiny_davis, "--noise-model", "elssim", "--out", run, "--steps", 2,
                "--batch-size", 2, "--checkpoint-every", 1, "--quiet", *net) == 0
    assert (run / "checkpoints" / "last.pt").is_file() and (run / "model.pt").is_file()
    rows = list(csv.DictReader((run / "loss.csv").open()))
    assert [int(r["step"]) for r in rows] == [2]  # logged at the last step (log_every 10)
    assert (run / "loss.png").stat().st_size > 0
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["noise_model"] == "elssim" and cfg["network"]["width"] == 8
    # a second run into the same folder needs --resume
    assert _cli("train", "--data", tiny_davis, "--out", run, "--steps", 3, "--quiet", *net) == 2
    assert _cli("train", "--data", tiny_davis, "--out", run, "--steps", 3, "--resume", "--quiet") == 0
    summary = json.loads((run / "summary.json").read_text())
    assert summary["steps_done"] == 3
    ck = torch.load(run / "checkpoints" / "last.pt", weights_only=False)
    assert ck["step"] == 3

    out = tmp_path / "eval"
    assert _cli("evaluate", "--data", tiny_davis, "--methods", f"tfp,tfi,tfp-dt,rsir:{run / 'model.pt'}=tiny",
                "--out", out, "--quiet") == 0
    table = (out / "table.md").read_text().splitlines()
    assert table[0] == "| Methods | PSNR | SSIM |"
    labels = [r["Methods"] for r in csv.DictReader((out / "table.csv").open())]
    assert labels == ["TFP (M=320)", "TFI", "TFP dead-time corrected", "tiny"]
    per_item = list(csv.DictReader((out / "per_item.csv").open()))
    assert len(per_item) == 4 * 2  # te-a has 3 frames, frame_stride 2 -> 2 items
    assert all(np.isfinite(float(r["psnr_db"])) for r in per_item)
    assert (out / "grid.png").stat().st_size > 0

    # reconstruct from a spike container
    from sensor import SensorProfile, simulate, write_spikes
    prof = SensorProfile.synthetic(8, 8, threshold_e=20.0, seed=1)
    spikes = simulate(np.full((400, 8, 8), 4.0, np.float32), prof, "ideal")
    sp = write_spikes(tmp_path / "s.npz", spikes, interval_s=prof.interval_s, model="ideal", profile_id=prof.name,
                      seed=0)
    rec = tmp_path / "rec"
    assert _cli("reconstruct", sp, "--method", "tfp", "--out", rec) == 0
    img = np.load(rec / "s_tfp_0000200.npy")
    np.testing.assert_allclose(img, 0.2, atol=1 / 320 + 1e-6)  # ideal: theta / lambda = 5 intervals per spike
    assert (rec / "s_tfp_0000200.png").is_file() and (rec / "s_tfp_0000200.exr").is_file()
    assert _cli("reconstruct", sp, "--method", "rsir", "--checkpoint", run / "model.pt", "--out", rec,
                "--formats", "npy") == 2  # the folder holds the TFP results: refused without --overwrite
    assert _cli("reconstruct", sp, "--method", "rsir", "--checkpoint", run / "model.pt", "--out", rec,
                "--formats", "npy", "--overwrite") == 0
    assert (rec / "s_tfp_0000200.png").is_file()  # --overwrite replaces only what it writes
    assert np.load(rec / "s_rsir_0000200.npy").shape == (8, 8)
    assert _cli("reconstruct", sp, "--method", "rsir", "--out", rec) == 2
    capsys.readouterr()
