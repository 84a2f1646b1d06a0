"""Procedurally generated DAVIS-layout data, for tests and for the documented CPU training run.

``python -m recon.synth OUT [--sequences N] [--frames F] [--size HxW] [--seed S]`` writes
``OUT/JPEGImages/480p/<name>/00000.jpg ...`` where the names are those of the
shipped DAVIS-2017 split (so ``split=train`` / ``split=test`` work unchanged):
the first ``N - 5`` training names and the 5 test names. Each sequence is a
smooth textured background with 3-7 textured shapes (ellipses, rectangles,
triangles) moving linearly, drawn from one seeded ``numpy.random.Generator``
per sequence. No images are downloaded.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from sensor.io.fileio import atomic_path


def _texture(rng, H, W):
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    kind = rng.integers(0, 4)
    if kind == 0:  # stripes
        f, a = rng.uniform(0.05, 0.35), rng.uniform(0, np.pi)
        t = 0.5 + 0.5 * np.sin(f * (xx * np.cos(a) + yy * np.sin(a)))
    elif kind == 1:  # checker
        s = int(rng.integers(3, 12))
        t = (((yy // s) + (xx // s)) % 2).astype(np.float32)
    elif kind == 2:  # smooth blobs
        t = np.zeros((H, W), np.float32)
        hi = max(H, W) / 3
        lo = 3.0 if hi > 3.0 else 1.0
        for _ in range(4):
            cy, cx, r = rng.uniform(0, H), rng.uniform(0, W), rng.uniform(lo, max(hi, lo + 1.0))
            t += np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * r * r)).astype(np.float32)
        t /= max(t.max(), 1e-6)
    else:  # flat
        t = np.ones((H, W), np.float32)
    return t


def make_sequence(rng: np.random.Generator, n_frames: int, size: tuple[int, int]) -> np.ndarray:
    """One sequence: uint8 sRGB frames (F, H, W, 3)."""
    H, W = size
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    g = rng.uniform(0.1, 0.9, 3)
    ang = rng.uniform(0, 2 * np.pi)
    bg = (0.4 + 0.4 * ((xx * np.cos(ang) + yy * np.sin(ang)) / max(H, W)))[..., None] * g
    bg = bg * (0.7 + 0.3 * _texture(rng, H, W))[..., None]
    shapes = []
    for _ in range(int(rng.integers(3, 8))):
        shapes.append(dict(kind=int(rng.integers(0, 3)), cy=rng.uniform(0, H), cx=rng.uniform(0, W),
                           ry=rng.uniform(H / 12, H / 4), rx=rng.uniform(W / 12, W / 4), vy=rng.uniform(-2, 2),
                           vx=rng.uniform(-3, 3), col=rng.uniform(0.0, 1.0, 3), tex=_texture(rng, H, W),
                           contrast=rng.uniform(0.2, 0.8)))
    frames = np.empty((n_frames, H, W, 3), np.uint8)
    for f in range(n_frames):
        img = bg.copy()
        for s in shapes:
            cy, cx = s["cy"] + s["vy"] * f, s["cx"] + s["vx"] * f
            dy, dx = (yy - cy) / s["ry"], (xx - cx) / s["rx"]
            if s["kind"] == 0:
                m = dy * dy + dx * dx <= 1
            elif s["kind"] == 1:
                m = (np.abs(dy) <= 1) & (np.abs(dx) <= 1)
            else:
                m = (dy <= 1) & (dy >= -1) & (np.abs(dx) <= (dy + 1) / 2)
            shade = (1 - s["contrast"]) + s["contrast"] * s["tex"]
            img[m] = (s["col"][None, :] * shade[m][:, None])
        frames[f] = np.clip(np.round(np.clip(img, 0, 1) ** (1 / 2.2) * 255), 0, 255).astype(np.uint8)
    return frames


def make_davis_like(root, names, n_frames: int = 12, size=(96, 128), seed: int = 0, quality: int = 92) -> Path:
    """Write sequences ``names`` as ``root/JPEGImages/480p/<name>/%05d.jpg``; returns ``root``."""
    from PIL import Image
    root = Path(root)
    ss = np.random.SeedSequence(int(seed))
    for name, child in zip(names, ss.spawn(len(names))):
        rng = np.random.Generator(np.random.PCG64(child))
        d = root / "JPEGImages" / "480p" / name
        d.mkdir(parents=True, exist_ok=True)
        for f, img in enumerate(make_sequence(rng, n_frames, tuple(size))):
            with atomic_path(d / f"{f:05d}.jpg") as tmp:
                Image.fromarray(img).save(tmp, format="JPEG", quality=quality)
    return root


def main(argv=None) -> int:
    from .datasets import DAVIS_SPLIT_FILE, load_split, parse_hw
    ap = argparse.ArgumentParser(prog="python -m recon.synth", description=__doc__.split("\n\n")[0])
    ap.add_argument("out")
    ap.add_argument("--sequences", type=int, default=90, help="how many sequences (the last 5 are the test ones)")
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--size", default="96x128", help="HxW of the generated frames")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    split = load_split(DAVIS_SPLIT_FILE)
    n_test = len(split["test"])
    if a.sequences < n_test:
        ap.error(f"argument --sequences: expected at least {n_test} (the test sequences are always written), "
                 f"got {a.sequences}")
    if a.frames < 1:
        ap.error(f"argument --frames: expected a whole number >= 1, got {a.frames}")
    if a.seed < 0:
        ap.error(f"argument --seed: expected a seed (a whole number >= 0), got {a.seed}")
    n_train = a.sequences - n_test
    names = split["train"][:n_train] + split["test"]
    make_davis_like(a.out, names, a.frames, parse_hw(a.size, "--size"), a.seed)
    print(f"wrote {len(names)} sequences x {a.frames} frames to {a.out}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
