"""The real-data score (recon.realscore, ``evaluate --data real:FILE``) on a simulated recording of known light."""

import json

import numpy as np
import pytest

from recon.evaluate import parse_methods
from recon.profiles import uniform_profile
from recon.realscore import clip_bounds, real_score, reference_intervals
from recon.spec import build_dataset, parse_data_spec
from sensor import InputError, simulate

H, W, T, WARM = 24, 32, 200, 64
MOVING = (slice(3, 21), slice(24, W))  # the rows the moving edge crosses, in the moving columns


def _recording(seed: int, level: float = 0.1):
    """A static texture (columns < 24) and an edge sweeping down columns 24.. once; light in thresholds/interval.

    Returns (spikes bool (T, H, W), profile, true light at the clip centre [ideal spikes per interval]).
    """
    prof = uniform_profile(H, W)
    th = prof.threshold_e
    y, x = np.mgrid[0:H, 0:W]
    img = level * (0.4 + 0.6 * (0.5 + 0.5 * np.sin(x / 3.0) * np.cos(y / 4.0)))
    lam = np.repeat((img * th)[None], T + WARM, 0).astype(np.float32)
    t = np.arange(T + WARM)[:, None, None]
    bright = y[None, :, 24:] < 2 + (H - 4) * (t - WARM) / T  # rows 0-1 always bright, rows 22-23 never
    lam[:, :, 24:] = (th * level * (0.3 + 1.2 * bright)).astype(np.float32)
    # a running camera: every pixel starts at a random phase (warm-up to a uniform random charge, then dropped)
    u = np.random.default_rng(100 + seed).uniform(0.0, 1.0, (H, W))
    lam[:WARM] = (u * th / WARM).astype(np.float32)
    spikes = simulate(lam, prof, "elssim", seed=seed)[WARM:]
    return spikes, prof, lam[WARM + T // 2] / th


def test_reference_intervals_leave_the_clip_out():
    a, b = clip_bounds(200, 64)
    assert (a, b) == (68, 132)
    out = reference_intervals(200, a, b, "outside")
    assert out.size == 136 and not np.any((out >= a) & (out < b))
    assert reference_intervals(200, a, b, "whole").size == 200


@pytest.mark.parametrize("seed", [1, 2])
def test_real_score_on_a_recording_of_known_light(seed):
    spikes, prof, truth = _recording(seed)
    methods = [("exact", lambda smp: truth)] + parse_methods("tfp-dt,tfp:8")
    res = real_score(spikes, prof, methods, clip=64)
    keep = res["images"]["stationary"]
    # the stationarity filter keeps the static texture and drops the edge's path (alpha = 0.01, 3x3 dilation)
    assert keep[:, :22].mean() > 0.9 and keep[MOVING].mean() < 0.15
    assert res["pixels"] == int(keep.sum()) and res["overlap_clip_reference"] == 0
    assert res["reference_intervals"] == 136 and res["clip"] == [68, 132]
    ps = {r["method"]: r["psnr_db"] for r in res["rows"]}
    floor = res["floor"]["floor_psnr_db"]
    # an exact reconstruction scores the reference's own noise: the floor. The MSEs are means over ~600 pixels
    # (relative s.d. ~ sqrt(2 / 600) = 6 %, 0.25 dB each); the dead-time inversion of the shorter halves adds a
    # small bias: 1.5 dB is about 4 s.d.
    assert abs(ps["exact"] - floor) < 1.5
    # the clip's own estimates have their own noise and score below; a short window far below
    assert ps["TFP dead-time corrected"] < ps["exact"] - 3.0
    assert ps["TFP (M=8)"] < ps["TFP dead-time corrected"] - 6.0
    exact = res["rows"][0]
    assert exact["limited_by_reference"] and exact["gain"] == pytest.approx(1.0, abs=0.05)
    dt = res["rows"][1]
    assert not dt["limited_by_reference"] and dt["psnr_own_db"] > dt["psnr_db"]


def test_real_score_whole_reference_shares_the_clip():
    spikes, prof, truth = _recording(3)
    res = real_score(spikes, prof, parse_methods("tfp-dt"), clip=32, reference="whole")
    assert res["overlap_clip_reference"] == 32 and res["reference_intervals"] == T
    assert res["rows"][0]["psnr_own_db"] is None  # not independent of the reference: no noise-corrected PSNR


def test_real_spec_options_and_errors():
    spec = parse_data_spec("real:rec.npz:clip=32:reference=whole:profile=vidar-default")
    assert spec.kind == "real" and spec.options == {"clip": 32, "reference": "whole", "profile": "vidar-default"}
    with pytest.raises(InputError, match="unknown option 'split'"):
        parse_data_spec("real:rec.npz:split=test")
    with pytest.raises(InputError, match="only render2spike evaluate"):
        build_dataset(spec)


def test_evaluate_real_command(cli, tmp_path):
    spikes, prof, _ = _recording(4)
    rec = tmp_path / "rec.npz"
    np.savez(rec, spk=spikes.astype(np.uint8))  # the Spike-Zoo / UHSR layout
    out = tmp_path / "eval"
    res = cli("evaluate", "--data", f"real:{rec}:clip=32", "--methods", "tfp,tfp-dt-denoised:1", "--out", str(out))
    assert res.returncode == 0, res.stderr
    assert "reference floor" in res.stdout and "TFP (M=32)" in res.stdout
    summary = json.loads((out / "summary.json").read_text())
    assert summary["kind"] == "real" and summary["clip"] == [84, 116] and summary["reference_intervals"] == 168
    assert summary["pixels"] > 0.5 * H * W and np.isfinite(summary["floor"]["floor_psnr_db"])
    table = (out / "table.md").read_text()
    assert "| reference floor |" in table and f"{summary['pixels']} of {H * W} pixels" in table
    assert (out / "table.csv").is_file() and (out / "grid.png").is_file()
    assert np.load(out / "reference.npy").shape == (H, W)
    bad = cli("evaluate", "--data", f"real:{rec}:clip=199", "--methods", "tfp", "--out", str(tmp_path / "e2"))
    assert bad.returncode != 0 and "clip" in bad.stderr and "Traceback" not in bad.stderr


def test_real_score_runs_a_network_on_the_clip():
    torch = pytest.importorskip("torch")
    from recon.evaluate import Method
    from recon.nets import RSIRConfig, RSIRNet
    torch.manual_seed(0)
    cfg = RSIRConfig.tiny(width=8, res_blocks=1, attn_depth=1, heads=2, attn_window=4, nim_width=8, mask_width=8,
                          normalise="mean")
    spikes, prof, _ = _recording(5)
    m = Method("rsir", None, "net", model=RSIRNet(cfg).eval())
    res = real_score(spikes, prof, [m], clip=64)
    row = res["rows"][0]
    assert row["windows"] == f"{cfg.n_windows}x{64 // cfg.n_windows}"  # the clip, cut into the trained N windows
    assert res["images"]["net"].shape == (H, W) and np.isfinite(row["psnr_db"])
