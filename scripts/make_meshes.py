"""Write the bundled meshes the procedural scene generator places: ``python scripts/make_meshes.py``.

Each is a closed triangle mesh about 1 m across (radius 0.5, centred on the origin; the generator scales it),
with vertex normals and spherical (u, v) texture coordinates, as binary little-endian PLY in ``scenes/``:

* ``mesh_torus.ply``: a torus, major radius 0.35, minor 0.15;
* ``mesh_blob.ply``: an icosphere of radius 0.5 whose radius is modulated by smooth noise (seed 7), +-20 %;
* ``mesh_cone.ply``: a cone, radius 0.5, height 1;
* ``mesh_capsule.ply``: a capsule, radius 0.25, length 1.

Made with trimesh from fixed parameters and a fixed seed, so a rerun writes the same files.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

OUT = Path(__file__).resolve().parents[1] / "scenes"


def write_ply(path: Path, vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray, uv: np.ndarray) -> None:
    """Binary little-endian PLY with x, y, z, nx, ny, nz, u, v (float32) and triangles (uint8 count, int32)."""
    head = ("ply\nformat binary_little_endian 1.0\n"
            f"element vertex {len(vertices)}\n"
            "property float x\nproperty float y\nproperty float z\n"
            "property float nx\nproperty float ny\nproperty float nz\n"
            "property float u\nproperty float v\n"
            f"element face {len(faces)}\n"
            "property list uchar int vertex_indices\nend_header\n").encode()
    vert = np.c_[vertices, normals, uv].astype("<f4")
    body = vert.tobytes() + b"".join(struct.pack("<B3i", 3, *map(int, f)) for f in faces)
    path.write_bytes(head + body)


def spherical_uv(v: np.ndarray) -> np.ndarray:
    c = v - v.mean(axis=0)
    r = np.linalg.norm(c, axis=1) + 1e-12
    u = 0.5 + np.arctan2(c[:, 1], c[:, 0]) / (2 * np.pi)
    w = 0.5 + np.arcsin(np.clip(c[:, 2] / r, -1, 1)) / np.pi
    return np.c_[u, w]


def main() -> None:
    import trimesh
    meshes = {
        "torus": trimesh.creation.torus(major_radius=0.35, minor_radius=0.15, major_sections=48, minor_sections=24),
        "cone": trimesh.creation.cone(radius=0.5, height=1.0, sections=48),
        "capsule": trimesh.creation.capsule(height=0.5, radius=0.25, count=[24, 24]),
    }
    blob = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    rng = np.random.default_rng(7)
    k = rng.normal(size=(6, 3))
    ph = rng.uniform(0, 2 * np.pi, 6)
    d = blob.vertices / np.linalg.norm(blob.vertices, axis=1, keepdims=True)
    mod = 1.0 + 0.2 * np.tanh(np.sum(np.sin(d @ k.T * 2.0 + ph), axis=1) / 2.0)
    meshes["blob"] = trimesh.Trimesh(d * 0.5 * mod[:, None], blob.faces, process=True)
    for name, m in meshes.items():
        m.vertices -= m.bounds.mean(axis=0)  # centred on the origin
        write_ply(OUT / f"mesh_{name}.ply", np.asarray(m.vertices), np.asarray(m.faces),
                  np.asarray(m.vertex_normals), spherical_uv(np.asarray(m.vertices)))
        print(f"{name}: {len(m.vertices)} vertices, {len(m.faces)} faces")


if __name__ == "__main__":
    main()
