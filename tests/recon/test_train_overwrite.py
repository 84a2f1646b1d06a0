"""`train --overwrite` starts a new run in place; without it an existing run is refused."""

import json

import pytest

from recon.synth import make_davis_like

torch = pytest.importorskip("torch")


def _cli(*argv):
    from render2spike.cli import main
    return main([str(a) for a in argv])


@pytest.mark.torch
def test_train_overwrite(tmp_path, capsys):
    root = make_davis_like(tmp_path / "davis", ["tr-a", "te-a"], n_frames=3, size=(8, 8), seed=4)
    split = tmp_path / "split.json"
    split.write_text(json.dumps({"train": ["tr-a"], "test": ["te-a"]}))
    data = f"davis:{root}:split_file={split}:res=8x8:warmup=8:frame_stride=2:lux=100"
    run = tmp_path / "run"
    net = ["--width", 8, "--res-blocks", 1, "--attn-depth", 1, "--heads", 1, "--attn-window", 4, "--quiet"]
    assert _cli("train", "--data", data, "--out", run, "--steps", 2, "--batch-size", 1, *net) == 0
    assert _cli("train", "--data", data, "--out", run, "--steps", 1, "--batch-size", 1, *net) == 2
    assert "--resume" in capsys.readouterr().err
    assert _cli("train", "--data", data, "--out", run, "--steps", 1, "--overwrite", "--resume", *net) == 2
    assert _cli("train", "--data", data, "--out", run, "--steps", 1, "--batch-size", 1, "--overwrite", *net) == 0
    assert torch.load(run / "checkpoints" / "last.pt", weights_only=True)["step"] == 1  # a new run, not 2 + 1
    (run / "loss.csv").write_text("step,loss\n1,abc\n")
    assert _cli("train", "--data", data, "--out", run, "--steps", 2, "--resume", "--quiet") == 2
    err = capsys.readouterr().err
    assert "loss.csv" in err and "Traceback" not in err
