"""`train --overwrite` starts a new run in place; without it an existing run is refused."""

import json

import pytest

from recon.synth import make_davis_like

torch = pytest.importorskip("torch")


def _cli(*argv):
    from render2spike.cli import main
    return main([str(a) for a in argv])


#: a network small enough for a test
NET = ["--width", 8, "--res-blocks", 1, "--attn-depth", 1, "--heads", 1, "--attn-window", 4, "--quiet"]


def _tiny_data(tmp_path) -> str:
    """A DAVIS-layout data spec with one 8x8 training sequence."""
    root = make_davis_like(tmp_path / "davis", ["tr-a", "te-a"], n_frames=3, size=(8, 8), seed=4)
    split = tmp_path / "split.json"
    split.write_text(json.dumps({"train": ["tr-a"], "test": ["te-a"]}))
    return f"davis:{root}:split_file={split}:res=8x8:warmup=8:frame_stride=2:lux=100"


@pytest.mark.torch
def test_train_overwrite(tmp_path, capsys):
    data = _tiny_data(tmp_path)
    run = tmp_path / "run"
    net = NET
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


@pytest.mark.torch
def test_train_head_from_init_on_the_cli(tmp_path, capsys):
    """--init CKPT --head --train-only head: the checkpoint's network is kept, a head is added and trained."""
    from recon.nets import load_checkpoint
    data = _tiny_data(tmp_path)
    net = NET
    assert _cli("train", "--data", data, "--out", tmp_path / "a", "--steps", 1, "--batch-size", 1, *net) == 0
    base, _ = load_checkpoint(tmp_path / "a" / "model.pt")
    assert base.head is None
    assert _cli("train", "--data", data, "--out", tmp_path / "b", "--steps", 2, "--batch-size", 1, "--quiet",
                "--init", tmp_path / "a" / "model.pt", "--head", "--train-only", "head") == 0
    model, ckpt = load_checkpoint(tmp_path / "b" / "model.pt")
    assert model.head is not None and ckpt["train"]["train_only"] == "head"
    for k, v in base.state_dict().items():  # everything but the head unchanged
        torch.testing.assert_close(model.state_dict()[k], v)
    assert "head" in (tmp_path / "b" / "loss.csv").read_text().splitlines()[0]
    # --train-only head without a head is refused with a message; --resume cannot add one
    assert _cli("train", "--data", data, "--out", tmp_path / "c", "--steps", 1, "--quiet",
                "--init", tmp_path / "a" / "model.pt", "--train-only", "head") == 2
    assert "output head" in capsys.readouterr().err
    assert _cli("train", "--data", data, "--out", tmp_path / "b", "--steps", 3, "--resume", "--head", "--quiet") == 2
    assert "--head" in capsys.readouterr().err
    assert _cli("train", "--data", data, "--out", tmp_path / "b", "--steps", 3, "--resume", "--train-only", "head",
                "--quiet") == 2
    assert "--train-only" in capsys.readouterr().err
    # a head alone on an untrained network is refused; resuming the head-only run works and keeps it head-only
    assert _cli("train", "--data", data, "--out", tmp_path / "d", "--steps", 1, "--head", "--train-only", "head",
                "--quiet", *NET[:-1]) == 2
    assert "--init" in capsys.readouterr().err
    assert _cli("train", "--data", data, "--out", tmp_path / "b", "--steps", 3, "--resume", "--quiet") == 0
    resumed, ck3 = load_checkpoint(tmp_path / "b" / "model.pt")
    assert ck3["step"] == 3 and ck3["train"]["train_only"] == "head"
    for k, v in base.state_dict().items():
        torch.testing.assert_close(resumed.state_dict()[k], v)
    # a run without a head leaves the head columns of its loss log empty (not 0)
    row = (tmp_path / "a" / "loss.csv").read_text().splitlines()[1].split(",")
    header = (tmp_path / "a" / "loss.csv").read_text().splitlines()[0].split(",")
    assert row[header.index("head")] == "" and row[header.index("refine")] != ""


@pytest.mark.torch
def test_a_run_that_fails_before_its_first_checkpoint_leaves_nothing(tmp_path, monkeypatch, capsys):
    """No config.json (nor an empty run folder) from a run that stopped before its first checkpoint."""
    import recon.nets as nets
    data = _tiny_data(tmp_path)
    run = tmp_path / "run"

    def broken(*a, **k):
        raise ValueError("boom in the first step")
    monkeypatch.setattr(nets, "rsir_loss", broken)
    assert _cli("train", "--data", data, "--out", run, "--steps", 2, "--batch-size", 1, *NET) == 2
    assert "boom" in capsys.readouterr().err
    assert not run.exists()
    run.mkdir()  # a folder the user made is kept, empty again
    assert _cli("train", "--data", data, "--out", run, "--steps", 2, "--batch-size", 1, *NET) == 2
    assert run.is_dir() and list(run.iterdir()) == []


@pytest.mark.torch
def test_resume_refuses_other_data_or_noise_model_and_a_file_as_out(tmp_path, capsys):
    data = _tiny_data(tmp_path)
    run = tmp_path / "run"
    assert _cli("train", "--data", data, "--out", run, "--steps", 1, "--batch-size", 1, *NET) == 0
    capsys.readouterr()
    other = data.replace("lux=100", "lux=50")
    assert _cli("train", "--data", other, "--out", run, "--steps", 2, "--resume", "--quiet") == 2
    err = capsys.readouterr().err
    assert "--data" in err and "config.json" in err and "lux=50" in err and len(err.strip().splitlines()) == 1, err
    assert _cli("train", "--data", data, "--out", run, "--steps", 2, "--resume", "--noise-model", "ideal",
                "--quiet") == 2
    assert "--noise-model" in capsys.readouterr().err
    assert torch.load(run / "checkpoints" / "last.pt", weights_only=True)["step"] == 1
    (tmp_path / "victim.npz").write_bytes(b"keep")
    for out in (tmp_path / "victim.npz", tmp_path / "victim.npz" / "sub"):
        assert _cli("train", "--data", data, "--out", out, "--steps", 1, *NET) == 2
        err = capsys.readouterr().err
        assert "victim.npz" in err and "--out" in err and "Error" not in err, err
    assert (tmp_path / "victim.npz").read_bytes() == b"keep"


@pytest.mark.torch
def test_train_temporal_head_on_the_cli(tmp_path, capsys):
    """--head-windows / --head-motion: a temporal bank started from the checkpoint's head; refused without --head."""
    from recon.nets import load_checkpoint
    data = _tiny_data(tmp_path)
    assert _cli("train", "--data", data, "--out", tmp_path / "a", "--steps", 1, "--batch-size", 1, "--head",
                *NET) == 0
    assert _cli("train", "--data", data, "--out", tmp_path / "b", "--steps", 1, "--batch-size", 1, "--quiet",
                "--init", tmp_path / "a" / "model.pt", "--head", "--head-windows", "1,4,0", "--head-motion",
                "--train-only", "head") == 0
    model, ckpt = load_checkpoint(tmp_path / "b" / "model.pt")
    assert model.config.head_windows == (1, 4, 0) and model.config.head_motion and model.n_cues == 2 + 1  # light level
    assert json.loads((tmp_path / "b" / "config.json").read_text())["network"]["head_windows"] == [1, 4, 0]
    assert _cli("train", "--data", data, "--out", tmp_path / "c", "--steps", 1, "--quiet",
                "--init", tmp_path / "a" / "model.pt", "--head-windows", "1,0") == 2
    assert "--head" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        _cli("train", "--data", data, "--out", tmp_path / "c", "--head", "--head-windows", "1,1")
