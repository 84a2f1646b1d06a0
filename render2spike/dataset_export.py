"""Export a ``render2spike dataset`` folder in the layout Spike-Zoo and SpikeCV train from.

``render2spike dataset SPEC --out DIR --export spikezoo[=FOLDER]`` (or :func:`export_spikezoo`) writes, for
every finished sample and each of its window centres, one pair::

    FOLDER/train/spike/NAME.dat    FOLDER/train/gt/NAME.png    FOLDER/train/NAME.json
    FOLDER/test/spike/NAME.dat     FOLDER/test/gt/NAME.png     FOLDER/test/NAME.json
    FOLDER/export.json             units, scale, split rule, and which sample / centre each pair came from

``NAME`` is ``<sample id>_c<centre interval, 6 digits>``; spike file and image share it (Spike-Zoo's
``reds_base`` pairs them by name, its ``base`` reader by sorted order: the same here).

Spikes
    ``intervals`` (default 301, Spike-Zoo's ``reds_base`` test length) intervals of the sample's spike
    stream, ``[c - intervals // 2, c - intervals // 2 + intervals)`` around the centre ``c``: the centre is
    file frame ``intervals // 2``, the middle frame Spike-Zoo's ``get_spike`` crops around, so any shorter
    crop it takes (41 for training) is centred on the ground truth's interval. Written by
    :func:`sensor.io.dat.write_dat` (SpikeCV / Spike-Zoo ``.dat``: no header, ``H * W / 8`` bytes a frame,
    LSB first, rows bottom-up); the frame size is the sample's sensor (``export.json`` ``height`` / ``width``:
    Spike-Zoo's ``height`` / ``width`` config).

Ground truth
    The sample's clean image at the centre (``truth.npz`` ``clean``: ideal spikes per interval,
    ``rate_e / threshold_e``) as an 8-bit grayscale PNG, LINEAR (no sRGB curve: Spike-Zoo reads
    ``value / 255`` as intensity): ``round(255 * clip(clean / white, 0, 1))`` with ``white`` the 99.5th
    percentile of the sample's clean images over all its centres (the white level of
    :mod:`recon.metrics`). So ``value / 255 * white`` is ideal spikes per interval: ``white`` is
    Spike-Zoo's ``rate`` of that pair (recorded per pair).

Split
    Pairs of one render (same scene and parameters, any lux / model / seed) go to the same split. Renders
    are ordered by the SHA-256 of their render key; the first ``round(test_fraction * n)`` of them (at
    least one and at most ``n - 1`` when there are two or more and ``0 < test_fraction < 1``) are ``test``,
    the rest ``train``. Both split folders always exist.

Each split folder is also a ``pairs:`` data spec of ``render2spike evaluate`` / ``train``: ``NAME.json``
gives ``height``, ``width``, ``transfer: linear``, ``spikes_per_ref_unit`` (= ``white``) and ``center``.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import uuid
from pathlib import Path

import numpy as np

from sensor.errors import InputError

EXPORT_FORMATS = ("spikezoo",)
EXPORT_FORMAT = "render2spike-spikezoo-export"
EXPORT_VERSION = 1
DEFAULT_INTERVALS = 301
DEFAULT_TEST_FRACTION = 0.2


def parse_export(text: str, dataset_out) -> tuple[str, Path]:
    """``spikezoo`` or ``spikezoo=FOLDER`` -> (format, folder); the folder defaults to ``DIR/spikezoo``."""
    kind, sep, folder = str(text).partition("=")
    if kind not in EXPORT_FORMATS:
        raise InputError(f"expected {' or '.join(EXPORT_FORMATS)}[=FOLDER], got '{text}'", field="--export")
    if sep and not folder.strip():
        raise InputError(f"expected a folder after '{kind}=', got ''", field="--export")
    return kind, (Path(folder) if sep else Path(dataset_out) / kind)


def check_export_target(folder, dataset_out, overwrite: bool = False, *, intervals: int = DEFAULT_INTERVALS,
                        test_fraction: float = DEFAULT_TEST_FRACTION) -> Path:
    """Refuse (one line, before anything is made) an export folder that would hold or hide the dataset, a file,
    a non-empty folder without ``overwrite``, and bad ``intervals`` / ``test_fraction``."""
    folder, out = Path(folder), Path(dataset_out)
    if isinstance(intervals, bool) or not isinstance(intervals, (int, np.integer)) or intervals < 1:
        raise InputError(f"expected a whole number of intervals >= 1, got {intervals!r}", field="--export-intervals")
    if not (isinstance(test_fraction, (int, float)) and 0.0 <= float(test_fraction) <= 1.0):
        raise InputError(f"expected a fraction from 0 to 1, got {test_fraction!r}", field="--export-test-fraction")
    f, o = folder.resolve(), out.resolve()
    if f == o or f in o.parents or any(f == p or p in f.parents for p in (o / "samples", o / "renders")):
        raise InputError("the export folder would hold, or sit inside the samples of, the dataset folder "
                         f"{out}; choose another folder (default: DIR/spikezoo)", path=folder, field="--export")
    if folder.exists() and not folder.is_dir():
        raise InputError("exists and is not a folder; give a folder for the export", path=folder, field="--export")
    if folder.is_dir() and any(folder.iterdir()) and not overwrite:
        raise InputError("the export folder exists and is not empty; choose another (--export spikezoo=FOLDER) or "
                         "pass --overwrite to replace it", path=folder, field="--export")
    return folder


def _test_renders(render_keys, test_fraction: float) -> set:
    keys = sorted(set(render_keys), key=lambda k: hashlib.sha256(str(k).encode()).hexdigest())
    n = len(keys)
    k = int(round(test_fraction * n))
    if n >= 2 and 0.0 < test_fraction < 1.0:
        k = min(max(k, 1), n - 1)
    return set(keys[:k])


def _done_samples(root: Path) -> list[tuple[str, dict]]:
    from render2spike.dataset import DATASET_FORMAT, MANIFEST
    man_path = root / MANIFEST
    try:
        man = json.loads(man_path.read_text())
    except FileNotFoundError:
        raise InputError("no dataset here (no manifest.json); make it with `render2spike dataset SPEC --out DIR`",
                         path=root) from None
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"not a readable dataset manifest ({exc})", path=man_path) from None
    if not (isinstance(man, dict) and man.get("format") == DATASET_FORMAT and isinstance(man.get("samples"), dict)):
        raise InputError(f"not a `render2spike dataset` manifest (format {DATASET_FORMAT})", path=man_path,
                         field="format")
    recs = sorted(man["samples"].items(), key=lambda kv: kv[1].get("index", 0))
    return [(sid, r) for sid, r in recs if r.get("status") == "done"]


def _load_truth(path: Path):
    try:
        with np.load(path) as z:
            return np.asarray(z["centers"]).astype(np.int64), np.asarray(z["clean"], np.float32)
    except FileNotFoundError:
        raise InputError("missing (the sample is incomplete)", path=path) from None
    except KeyError as exc:
        raise InputError(f"has no array {exc}", path=path, field=str(exc).strip("'")) from None
    except Exception as exc:  # zip / npy errors
        raise InputError(f"not a readable truth file ({type(exc).__name__}: {exc})", path=path) from None


def export_spikezoo(dataset_dir, folder=None, *, intervals: int = DEFAULT_INTERVALS,
                    test_fraction: float = DEFAULT_TEST_FRACTION, overwrite: bool = False, log=print) -> dict:
    """Write the finished samples of ``dataset_dir`` as Spike-Zoo pairs in ``folder`` (module docstring).

    ``folder`` defaults to ``dataset_dir/spikezoo``. Everything is checked (every sample's frame size and
    that the window of ``intervals`` fits its clip at every centre) before anything is written; the export
    is built in a temporary folder beside ``folder`` and renamed into place (an existing ``folder`` is
    replaced only with ``overwrite``). Returns the ``export.json`` contents.
    """
    from recon.imageio import white_level, write_png
    from recon.metrics import WHITE_PERCENTILE
    from sensor.io.dat import write_dat
    from sensor.io.fileio import package_version, write_json_atomic
    from sensor.io.lock import FolderLock
    from sensor.io.spikefile import read_spikes_with_meta

    root = Path(dataset_dir)
    folder = Path(folder) if folder is not None else root / "spikezoo"
    check_export_target(folder, root, overwrite, intervals=intervals, test_fraction=test_fraction)
    L = int(intervals)
    if not root.is_dir():
        raise InputError("dataset folder does not exist", path=root, field="--out")
    with FolderLock(root, "a dataset run or export"):
        done = _done_samples(root)
        if not done:
            raise InputError("the dataset has no finished sample to export", path=root)
        # check every sample before writing anything
        plans = []
        for sid, rec in done:
            sdir = root / "samples" / sid
            info_path = sdir / "sample.json"
            try:
                info = json.loads(info_path.read_text())
                H, W, T = int(info["height"]), int(info["width"]), int(info["n_intervals"])
            except (OSError, ValueError, KeyError, TypeError) as exc:
                raise InputError(f"not a readable sample description ({type(exc).__name__}: {exc})",
                                 path=info_path) from None
            if (H * W) % 8:
                raise InputError(f"frames of {H} x {W} pixels: a .dat frame needs H * W to be a multiple of 8",
                                 path=info_path, field="height/width")
            centers, clean = _load_truth(sdir / "truth.npz")
            if clean.shape != (len(centers), H, W):
                raise InputError(f"'clean' has shape {clean.shape}; expected ({len(centers)}, {H}, {W})",
                                 path=sdir / "truth.npz", field="clean")
            most = min(min(2 * int(c) + 1, 2 * (T - int(c))) for c in centers) if len(centers) else T
            for c in centers:
                a = int(c) - L // 2
                if a < 0 or a + L > T:
                    raise InputError(f"a window of {L} intervals around centre {int(c)} does not fit the clip of {T} "
                                     f"intervals; pass --export-intervals {most} or fewer", path=sdir,
                                     field="--export-intervals")
            plans.append((sid, rec, sdir, info, centers, clean))
        test = _test_renders([rec.get("render_key") for _, rec, *_ in plans], float(test_fraction))

        folder.parent.mkdir(parents=True, exist_ok=True)
        tmp = folder.parent / f".tmp-{folder.name}-{uuid.uuid4().hex[:8]}"
        pairs = []
        try:
            for split in ("train", "test"):
                for sub in ("spike", "gt"):
                    (tmp / split / sub).mkdir(parents=True)
            for sid, rec, sdir, info, centers, clean in plans:
                split = "test" if rec.get("render_key") in test else "train"
                spikes, _ = read_spikes_with_meta(sdir / "spikes.npz")
                if spikes.shape[1:] != clean.shape[1:]:
                    raise InputError(f"spikes are {spikes.shape[1]} x {spikes.shape[2]} but the truth is "
                                     f"{clean.shape[1]} x {clean.shape[2]}", path=sdir / "spikes.npz")
                white = float(white_level(clean, WHITE_PERCENTILE))
                for c, img in zip(centers, clean):
                    c = int(c)
                    name = f"{sid}_c{c:06d}"
                    a = c - L // 2
                    write_dat(tmp / split / "spike" / f"{name}.dat", spikes[a:a + L])
                    gt = np.round(np.clip(img / np.float32(white), 0.0, 1.0) * 255.0).astype(np.uint8)
                    write_png(tmp / split / "gt" / f"{name}.png", gt)
                    write_json_atomic(tmp / split / f"{name}.json", {
                        "height": info["height"], "width": info["width"], "transfer": "linear",
                        "spikes_per_ref_unit": white, "center": L // 2, "lux": info.get("illuminance_lux"),
                        "dataset_sample": sid, "dataset_center_interval": c})
                    pairs.append({"name": name, "split": split, "sample": sid, "index": rec.get("index"),
                                  "render_key": rec.get("render_key"), "center_interval": c,
                                  "first_interval": a, "white_spikes_per_interval": white,
                                  "illuminance_lux": info.get("illuminance_lux"), "model": info.get("model_spec"),
                                  "seed": info.get("seed"), "profile_id": info.get("profile_id"),
                                  "height": info["height"], "width": info["width"]})
            sizes = sorted({(p["height"], p["width"]) for p in pairs})
            meta = {
                "format": EXPORT_FORMAT, "version": EXPORT_VERSION, "layout": "spikezoo",
                "dataset": str(root), "intervals": L, "center_frame": L // 2,
                "height": sizes[0][0] if len(sizes) == 1 else None,
                "width": sizes[0][1] if len(sizes) == 1 else None,
                "spikes": "SpikeCV / Spike-Zoo .dat: no header, H*W/8 bytes a frame, pixel p = r*W + c of the "
                          "stored frame in bit p % 8 (LSB first) of byte p // 8, rows stored bottom-up; frame "
                          "center_frame is the ground truth's interval",
                "gt": "8-bit grayscale PNG, linear: value / 255 * white_spikes_per_interval = the clean image at "
                      "the centre in ideal spikes per interval (rate_e / threshold_e)",
                "scale": f"white_spikes_per_interval = the {WHITE_PERCENTILE}th percentile of the sample's clean "
                         "images over all its centres; values above it are clipped to 255",
                "split_rule": "pairs of one render share a split; renders ordered by sha256(render_key), the first "
                              f"round(test_fraction * n) are test (1 .. n-1 of them when n >= 2); "
                              f"test_fraction = {float(test_fraction)}",
                "test_fraction": float(test_fraction),
                "n_train": sum(p["split"] == "train" for p in pairs),
                "n_test": sum(p["split"] == "test" for p in pairs),
                "pairs": pairs,
                "provenance": {"tool": "render2spike dataset --export spikezoo", "version": package_version()}}
            write_json_atomic(tmp / "export.json", meta)
            old = None
            if folder.exists():
                old = folder.parent / f".old-{folder.name}-{uuid.uuid4().hex[:8]}"
                os.rename(folder, old)
            try:
                os.rename(tmp, folder)
            except BaseException:
                if old is not None:
                    os.rename(old, folder)
                raise
            if old is not None:
                shutil.rmtree(old, ignore_errors=True)
        except BaseException:
            with contextlib.suppress(OSError):
                shutil.rmtree(tmp, ignore_errors=True)
            raise
    log(f"Spike-Zoo export: {folder} ({meta['n_train']} train and {meta['n_test']} test pairs, {L} intervals of "
        + (f"{meta['height']} x {meta['width']}" if meta["height"] else "several frame sizes") + ")")
    return meta
