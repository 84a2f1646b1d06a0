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
    # without --checkpoint: the network shipped with the package
    assert _cli("reconstruct", sp, "--method", "rsir", "--out", rec, "--formats", "npy", "--overwrite") == 0
    assert np.all(np.isfinite(np.load(rec / "s_rsir_0000200.npy")))
    capsys.readouterr()


@pytest.mark.torch
def test_the_shipped_model_is_small_packaged_and_documented():
    import tomllib
    from pathlib import Path

    from recon.nets import load_checkpoint
    from recon.reconstruct import PRETRAINED, default_checkpoint
    assert default_checkpoint() == PRETRAINED and PRETRAINED.stat().st_size < 3_000_000
    model, ck = load_checkpoint(PRETRAINED)
    assert model.config.normalise == "mean" and "optimizer" not in ck
    folder = PRETRAINED.parent
    for name in ("config.json", "loss.csv", "loss.png", "evaluation.md", "summary.json"):
        assert (folder / name).is_file(), name
    cfg = json.loads((folder / "config.json").read_text())
    assert cfg["network"] == ck["config"]  # the config beside it is the model's
    root = Path(__file__).resolve().parents[2]
    data = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["recon"]
    assert "pretrained/*.pt" in data


@pytest.mark.torch
def test_train_init_adopts_scale_and_rejects_size_flags_and_presets_match(tiny_davis, tmp_path, capsys):
    from recon.nets import PRESETS, load_checkpoint
    from render2spike.commands.train import PRESETS as CLI_PRESETS
    assert tuple(CLI_PRESETS) == tuple(PRESETS)
    net = ["--width", "8", "--res-blocks", "1", "--heads", "2", "--attn-window", "4"]
    run = tmp_path / "fixed"
    assert _cli("train", "--data", tiny_davis, "--out", run, "--steps", 1, "--batch-size", 2, "--quiet",
                "--normalise", "fixed", *net) == 0
    m, _ = load_checkpoint(run / "model.pt")
    assert m.config.normalise == "fixed"
    bright = tiny_davis.replace("lux=100", "lux=10000")
    ft = tmp_path / "ft"
    assert _cli("train", "--data", bright, "--out", ft, "--init", run / "model.pt", "--width", "8", "--quiet") == 2
    assert "--init takes the network layout" in capsys.readouterr().err
    assert _cli("train", "--data", bright, "--out", ft, "--init", run / "model.pt", "--steps", 1,
                "--batch-size", 2, "--quiet") == 0
    m2, _ = load_checkpoint(ft / "model.pt")
    # the new data are 100x brighter: the adopted scale is ~100x smaller (same items, same seed)
    assert m2.config.intensity_scale == pytest.approx(m.config.intensity_scale / 100, rel=0.05)
    # two sources at once, the default (mean) normalisation
    two = tmp_path / "two"
    assert _cli("train", "--data", tiny_davis, "--data", bright, "--out", two, "--steps", 1, "--batch-size", 2,
                "--quiet", *net) == 0
    cfg = json.loads((two / "config.json").read_text())
    from recon.spec import build_dataset
    assert cfg["items"] == 2 * len(build_dataset(tiny_davis, split="train")) and cfg["network"]["normalise"] == "mean"
    capsys.readouterr()


@pytest.mark.torch
def test_reconstruct_any_size_windows_and_third_party_files(tmp_path, capsys):
    from recon.nets import RSIRConfig, RSIRNet, save_checkpoint
    from recon.reconstruct import fit_windows
    from sensor import SensorProfile, simulate, write_dat
    assert fit_windows(301, None, None, (10, 32)) == (10, 30)
    assert fit_windows(200, 5, 40, (10, 32)) == (5, 40)
    assert fit_windows(4000, None, None, (10, 32)) == (10, 32)
    with pytest.raises(InputError, match="N\\*L <= 200"):
        fit_windows(200, 10, 32, (10, 32))
    cfg = RSIRConfig.tiny(width=8, res_blocks=1, attn_depth=1, heads=2, attn_window=4, nim_width=8, mask_width=8,
                          normalise="mean")
    ck = save_checkpoint(tmp_path / "m.pt", RSIRNet(cfg))
    prof = SensorProfile.synthetic(13, 24, threshold_e=20.0, seed=1)  # odd height: padded and cropped back
    spikes = simulate(np.full((250, 13, 24), 3.0, np.float32), prof, "ideal")
    dat = write_dat(tmp_path / "clip.dat", spikes)
    rec = tmp_path / "rec"
    assert _cli("reconstruct", dat, "--height", 13, "--width", 24, "--method", "rsir", "--checkpoint", ck,
                "--out", rec, "--formats", "npy", "--overwrite") == 0
    assert np.load(rec / "clip_rsir_0000125.npy").shape == (13, 24)
    assert _cli("reconstruct", dat, "--height", 13, "--width", 24, "--method", "rsir", "--checkpoint", ck,
                "--windows", 5, "--window-length", 50, "--out", rec, "--formats", "npy", "--center", 100,
                "--overwrite") == 0
    assert _cli("reconstruct", dat, "--height", 13, "--width", 24, "--method", "rsir", "--checkpoint", ck,
                "--windows", 10, "--window-length", 32, "--out", rec, "--overwrite") == 2
    assert "N*L <= 250" in capsys.readouterr().err
    assert _cli("reconstruct", dat, "--height", 13, "--width", 24, "--method", "tfp-dt-denoised", "--out", rec,
                "--formats", "npy", "--overwrite") == 0
    img = np.load(rec / "clip_tfp-dt-denoised_0000125.npy")
    assert img.shape == (13, 24) and np.all(np.isfinite(img))


def test_evaluate_on_a_spikezoo_style_pairs_folder(tmp_path, capsys):
    from PIL import Image

    from sensor import SensorProfile, simulate, write_dat
    prof = SensorProfile.synthetic(16, 24, threshold_e=20.0, seed=2)
    yy, xx = np.mgrid[0:16, 0:24]
    (tmp_path / "zoo" / "spike").mkdir(parents=True)
    (tmp_path / "zoo" / "gt").mkdir()
    for i in range(2):
        ref = ((xx + 2 * yy + 5 * i) % 24 / 23.0).astype(np.float32)
        write_dat(tmp_path / "zoo" / "spike" / f"s{i}.dat",
                  simulate(np.repeat((ref * 8.0 + 0.5)[None], 301, axis=0), prof, "ideal", seed=i))
        Image.fromarray(np.round(ref * 255).astype(np.uint8)).save(tmp_path / "zoo" / "gt" / f"s{i}.png")
    out = tmp_path / "ev"
    spec = f"pairs:{tmp_path / 'zoo'}:height=16:width=24:windows=10:window=30"
    assert _cli("evaluate", "--data", spec, "--methods", "tfp,tfp-dt,tfp-dt-denoised", "--out", out, "--quiet") == 0
    rows = list(csv.DictReader((out / "table.csv").open()))
    assert [r["Methods"] for r in rows] == ["TFP (M=300)", "TFP dead-time corrected", "TFP-DT + Gaussian (tuned)"]
    assert all(np.isfinite(float(r["PSNR"])) for r in rows)
    # 301 intervals cannot hold the default 10 x 32: a clear error
    assert _cli("evaluate", "--data", f"pairs:{tmp_path / 'zoo'}:height=16:width=24", "--methods", "tfp",
                "--out", out, "--quiet", "--overwrite") == 2
    assert "windows=N:window=L" in capsys.readouterr().err


UHSR = __import__("pathlib").Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "real" / "uhsr.npz"


@pytest.mark.torch
@pytest.mark.skipif(not UHSR.is_file(), reason="../shared/data/real/uhsr.npz not present")
def test_reconstruct_and_evaluate_the_uhsr_recording(tmp_path, capsys):
    """The real UHSR clip (Spike-Zoo 'spk' layout, 200 intervals of 250 x 250) through both commands."""
    from PIL import Image

    from recon.classic import tfp
    from recon.nets import RSIRConfig, RSIRNet, save_checkpoint
    from sensor.io.spikefile import read_spikes
    cfg = RSIRConfig.tiny(width=8, res_blocks=1, attn_depth=1, heads=2, attn_window=4, nim_width=8, mask_width=8,
                          normalise="mean", cumulative=True, linearise=True)
    ck = save_checkpoint(tmp_path / "m.pt", RSIRNet(cfg))
    rec = tmp_path / "rec"
    assert _cli("reconstruct", UHSR, "--method", "rsir", "--checkpoint", ck, "--out", rec, "--formats", "npy") == 0
    img = np.load(rec / "uhsr_rsir_0000100.npy")  # 10 windows of 20 intervals (200 // 10)
    assert img.shape == (250, 250) and np.all(np.isfinite(img))
    # a pairs folder around the real clip (reference: the TFP of all 200 intervals, a stand-in)
    (tmp_path / "p" / "spike").mkdir(parents=True)
    (tmp_path / "p" / "gt").mkdir()
    (tmp_path / "p" / "spike" / "uhsr.npz").symlink_to(UHSR.resolve())
    ref = tfp(read_spikes(UHSR))
    Image.fromarray(np.round(np.clip(ref / ref.max(), 0, 1) * 65535).astype(np.uint16)).save(
        tmp_path / "p" / "gt" / "uhsr.png")
    out = tmp_path / "ev"
    assert _cli("evaluate", "--data", f"pairs:{tmp_path / 'p'}:windows=10:window=20",
                "--methods", f"tfp,tfp-dt-denoised,rsir:{ck}=net", "--out", out, "--quiet") == 0
    rows = list(csv.DictReader((out / "table.csv").open()))
    assert [r["Methods"] for r in rows] == ["TFP (M=200)", "TFP-DT + Gaussian (tuned)", "net"]
    capsys.readouterr()
