"""`render2spike dataset --export spikezoo`: the Spike-Zoo / SpikeCV layout (split/spike/NAME.dat,
split/gt/NAME.png), read back bit for bit by the project's reader and by Spike-Zoo's own reader."""

import json
from pathlib import Path

import numpy as np
import pytest

import sensor
from render2spike.dataset import build_dataset
from render2spike.dataset_export import export_spikezoo

H, W = 8, 12
L = 41


def _frames(folder: Path, phase: float) -> Path:
    t = np.arange(0, 0.0181, 0.002)  # 360 intervals
    yy, xx = np.mgrid[0:H, 0:W]
    base = np.stack([0.3 + 0.25 * np.sin(2 * np.pi * (xx - 300 * ti + phase) / 12) + 0.02 * yy for ti in t])
    prof = sensor.SensorProfile.load("vidar-default")
    phi = base * 900 / (prof.pixel_pitch_m ** 2 * prof.fill_factor * prof.interval_s)
    # the manifest names the pattern: a frames source's render key is the hash of its frames.json
    sensor.write_frames(folder, phi.astype(np.float32), t, manifest={"illuminance_lux": 100.0, "pattern": phase})
    return folder


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """Two frames folders (two renders) x two lux: four samples, two centres each, no rendering."""
    base = tmp_path_factory.mktemp("zoo")
    scenes = [{"frames": str(_frames(base / f"frames{i}", 3.0 * i)), "profile": "vidar-default"} for i in range(2)]
    spec = {"scenes": scenes, "lux": [20, 80], "models": ["elssim"], "seeds": [0], "window": 64, "centers": 2,
            "preroll": 100}
    out = base / "ds"
    res = build_dataset(spec, out, workers=0, progress=False, log=lambda *a: None)
    assert res.n_done == 4 and not res.failed
    return out


def _read_png(path):
    from PIL import Image
    with Image.open(path) as im:
        assert im.mode == "L"  # 8-bit grayscale
        return np.asarray(im)


def test_export_layout_bits_and_images(dataset, tmp_path):
    from sensor.io.dat import read_dat
    folder = tmp_path / "zoo"
    meta = export_spikezoo(dataset, folder, intervals=L, test_fraction=0.5, log=lambda *a: None)
    assert meta["n_train"] == 4 and meta["n_test"] == 4  # 2 renders: one to each split, 2 samples x 2 centres each
    for split in ("train", "test"):
        dats = sorted(p.stem for p in (folder / split / "spike").iterdir())
        pngs = sorted(p.stem for p in (folder / split / "gt").iterdir())
        assert dats == pngs and len(dats) == 4
        assert all((folder / split / "spike" / f"{n}.dat").stat().st_size == L * H * W // 8 for n in dats)
    # one render never straddles the splits
    by_render = {}
    for p in meta["pairs"]:
        by_render.setdefault(p["render_key"], set()).add(p["split"])
    assert len(by_render) == 2 and all(len(s) == 1 for s in by_render.values())
    on_disk = json.loads((folder / "export.json").read_text())
    assert on_disk["pairs"] == meta["pairs"] and on_disk["intervals"] == L and (on_disk["height"], on_disk["width"]) == (H, W)

    for p in meta["pairs"]:
        sdir = dataset / "samples" / p["sample"]
        spikes = sensor.read_spikes(sdir / "spikes.npz")
        c = p["center_interval"]
        got = read_dat(folder / p["split"] / "spike" / f"{p['name']}.dat", H, W)
        np.testing.assert_array_equal(got, spikes[c - L // 2:c - L // 2 + L])
        assert got[L // 2].tolist() == spikes[c].tolist()  # the middle frame is the centre interval
        with np.load(sdir / "truth.npz") as z:
            clean = z["clean"]
            k = list(z["centers"]).index(c)
        white = np.percentile(clean.astype(np.float64), 99.5)
        assert p["white_spikes_per_interval"] == pytest.approx(white, rel=1e-6)
        img = _read_png(folder / p["split"] / "gt" / f"{p['name']}.png")
        assert img.shape == (H, W) and img.dtype == np.uint8
        # linear 8-bit: within half a code value of the clipped, normalised clean image
        expect = np.clip(clean[k] / white, 0, 1) * 255
        assert np.abs(img - expect).max() <= 0.5 + 1e-4
        assert img.max() == 255 and img.min() < 200
        side = json.loads((folder / p["split"] / f"{p['name']}.json").read_text())
        assert side["transfer"] == "linear" and side["center"] == L // 2


def test_export_refusals_are_one_line_and_leave_nothing(dataset, tmp_path):
    from sensor.errors import InputError
    folder = tmp_path / "zoo"
    export_spikezoo(dataset, folder, intervals=L, log=lambda *a: None)
    stamp = (folder / "export.json").read_bytes()
    with pytest.raises(InputError, match="not empty.*--overwrite"):
        export_spikezoo(dataset, folder, intervals=L, log=lambda *a: None)
    # a window longer than the clip allows names the most that fits; nothing is written
    with pytest.raises(InputError, match="--export-intervals") as e:
        export_spikezoo(dataset, tmp_path / "long", intervals=10_000, log=lambda *a: None)
    assert "\n" not in str(e.value) and not (tmp_path / "long").exists()
    with pytest.raises(InputError, match="export folder would hold"):
        export_spikezoo(dataset, dataset, intervals=L, log=lambda *a: None)
    assert (folder / "export.json").read_bytes() == stamp
    meta = export_spikezoo(dataset, folder, intervals=21, overwrite=True, log=lambda *a: None)
    first = meta["pairs"][0]
    assert meta["intervals"] == 21
    assert (folder / first["split"] / "spike" / f"{first['name']}.dat").stat().st_size == 21 * H * W // 8
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_cli_exports_after_the_run_and_refuses_before_it(dataset, tmp_path, cli):
    spec = json.loads((dataset / "manifest.json").read_text())["spec"]
    spec_path = tmp_path / "spec.json"
    spec_path.write_text(json.dumps(spec))
    folder = tmp_path / "zoo"
    folder.mkdir()
    (folder / "other.txt").write_text("x")
    r = cli("dataset", str(spec_path), "--out", str(dataset), "--workers", "0", "--quiet",
            "--export", f"spikezoo={folder}", "--export-intervals", str(L))
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "--overwrite" in r.stderr
    r = cli("dataset", str(spec_path), "--out", str(dataset), "--workers", "0", "--quiet", "--export", "zoo")
    assert r.returncode == 2 and "spikezoo" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    for bad, word in ((("--export", "spikezoo="), "folder"), (("--export", "spikezoo", "--export-test-fraction", "2"),
                                                              "--export-test-fraction")):
        r = cli("dataset", str(spec_path), "--out", str(dataset), "--workers", "0", "--quiet", *bad)
        assert r.returncode == 2 and word in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert not (dataset / "spikezoo").exists()
    r = cli("dataset", str(spec_path), "--out", str(dataset), "--workers", "0", "--quiet",
            "--export", f"spikezoo={tmp_path / 'new'}", "--export-intervals", str(L))
    assert r.returncode == 0, r.stderr
    assert "Spike-Zoo export" in r.stdout and (tmp_path / "new" / "export.json").is_file()


def test_the_project_reads_an_export_split_as_pairs(dataset, tmp_path):
    """Each split folder is a `pairs:` data spec; NAME.json makes the reference linear and calibrated."""
    from recon.datasets import PairsDataset
    folder = tmp_path / "zoo"
    meta = export_spikezoo(dataset, folder, intervals=L, log=lambda *a: None)
    split = meta["pairs"][0]["split"]
    ds = PairsDataset(folder / split, height=H, width=W, n_windows=1, window=L)
    item = ds.sample(0)
    p = next(q for q in meta["pairs"] if q["name"] == ds.items[0])
    with np.load(dataset / "samples" / p["sample"] / "truth.npz") as z:
        clean = z["clean"][list(z["centers"]).index(p["center_interval"])]
    white = p["white_spikes_per_interval"]
    # the reference back in ideal spikes per interval, to within 8-bit quantisation
    assert np.abs(item.target[0] - np.minimum(clean, white)).max() <= 0.5 / 255 * white + 1e-6


def test_spike_zoo_reads_the_export(dataset, tmp_path):
    """Spike-Zoo's own reader (PyPI `spikezoo`): the reds_base dataset class on the export, both splits."""
    pytest.importorskip("torch")
    pytest.importorskip("cv2")
    pytest.importorskip("spikezoo")
    from spikezoo.datasets.base_dataset import BaseDatasetConfig
    from spikezoo.datasets.reds_base_dataset import REDS_BASE
    folder = tmp_path / "zoo"
    meta = export_spikezoo(dataset, folder, intervals=L, log=lambda *a: None)
    for split, length in (("train", 21), ("test", L)):
        cfg = BaseDatasetConfig(dataset_name="reds_base", root_dir=folder, height=H, width=W,
                                spike_length_train=21, spike_length_test=L)
        ds = REDS_BASE(cfg)
        ds.build_source(split)
        pairs = sorted((p for p in meta["pairs"] if p["split"] == split), key=lambda p: p["name"])
        assert len(ds) == len(pairs) == 4
        for i, p in enumerate(pairs):
            batch = ds[i]
            spk = batch["spike"].numpy()
            assert spk.shape == (length, H, W)
            s = sensor.read_spikes(dataset / "samples" / p["sample"] / "spikes.npz")
            c = p["center_interval"]
            np.testing.assert_array_equal(spk.astype(bool), s[c - length // 2:c - length // 2 + length])
            gt = batch["gt_img"].numpy()[0]
            png = _read_png(folder / split / "gt" / f"{p['name']}.png")
            np.testing.assert_allclose(gt, png / 255.0, atol=1e-6)
