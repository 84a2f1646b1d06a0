"""A moving mesh keeps the shading normals it was loaded with, in both launches.

The film launch moves a mesh by rewriting its vertices, and Mitsuba recomputes a rewritten mesh's vertex normals
from its triangles unless they are set too; the renderer sets them (``renderer.carried_normals``). Without that, a
mesh with a negative scale renders inside out (its faces keep their winding, which the reflection turns inwards) and
a mesh file loses its authored normals. Mitsuba's load, the frozen launch's instances and the film launch all carry
normals by the inverse transpose of the pose.
"""

import numpy as np
import pytest

from tests.render.conftest import assert_image_means_agree, film_and_frozen_frames, needs_mitsuba

pytestmark = [pytest.mark.render, needs_mitsuba]

BACK = {"name": "back", "shape": "rectangle", "size": [10, 10], "position": [0, 0, -0.5],
        "material": {"reflectance": 0.3}}
REF = {"point": [0, 0, 0.05], "normal": [0, 0, 1]}
#: one-sided, so that a normal turned inwards shows as a black face (two-sided materials hide it)
ONE_SIDED = {"reflectance": 0.8, "two_sided": False}
SLOW = {"parametric": [{"translate": {"velocity_m_s": [0.0001, 0.0, 0.0]}}]}
TURN = {"parametric": [{"translate": {"velocity_m_s": [0.3, 0.1, 0.0]}},
                       {"rotate": {"axis": [0, 1, 0], "omega_rad_s": 20.0}}]}


def write_ply_with_normals(path, normal=(0.0, 0.0, 1.0)):
    """A 3 cm box of 8 shared vertices whose vertex normals are all ``normal``: nothing a recomputation from its
    triangles would give."""
    import trimesh
    box = trimesh.creation.box(extents=[0.03, 0.03, 0.03])
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    lines = ["ply", "format ascii 1.0", f"element vertex {len(box.vertices)}", "property float x",
             "property float y", "property float z", "property float nx", "property float ny", "property float nz",
             f"element face {len(box.faces)}", "property list uchar int vertex_indices", "end_header"]
    lines += [" ".join(f"{x:.9g}" for x in (*v, *n)) for v in box.vertices]
    lines += ["3 " + " ".join(str(int(i)) for i in f) for f in box.faces]
    path.write_text("\n".join(lines) + "\n")
    return path


def _objects(tmp_path, case, motion):
    if case == "negative_scale_cube":
        obj = {"name": "thing", "shape": "cube", "size": [0.06, 0.06, 0.06], "scale": [-1.0, 1.0, 1.0],
               "rotation_deg": [20.0, 30.0, 0.0], "material": ONE_SIDED}
    else:
        obj = {"name": "thing", "shape": "mesh", "file": str(write_ply_with_normals(tmp_path / "box.ply")),
               "scale": [1.5, 0.8, 1.0], "rotation_deg": [25.0, 35.0, 0.0], "material": ONE_SIDED}
    if motion is not None:
        obj["motion"] = motion
    return [BACK, obj]


def _plain_ply(tmp_path):
    """A 3 cm icosphere PLY without normals: Mitsuba computes them from the triangles, at every pose."""
    import trimesh
    path = tmp_path / "plain.ply"
    trimesh.creation.icosphere(subdivisions=2, radius=0.015).export(path)
    assert b"nx" not in path.read_bytes().split(b"end_header")[0]
    return str(path)


V = [0.5, 0.2, 0.0]  # m/s: 2 px/ms right, 0.8 px/ms up at the scene's 2.5 mm per pixel
TIMES = (0.0, 0.004, 0.008, 0.01)


def _moving_and_still(tmp_path, case):
    """(moving object, still(t_s) -> the same object standing in its pose at t_s) for a film-launch case:
    translations of a mirrored cube and of a mesh with authored normals, and scales keyframed over time (a
    cube's through zero into a mirror image, a plain mesh's non-uniformly), linear between t = 0 and 0.01 s."""
    if case in ("negative_scale_cube", "authored_normals"):
        obj = _objects(tmp_path, case, None)[1]
        moving = {**obj, "motion": {"parametric": [{"translate": {"velocity_m_s": V}}]}}
        return moving, lambda t: {**obj, "position": [x * t for x in V]}
    if case == "cube_scaled_through_zero":
        obj = {"name": "thing", "shape": "cube", "size": [0.06, 0.06, 0.06], "rotation_deg": [20.0, 30.0, 0.0],
               "material": ONE_SIDED}
        s0, s1 = np.array([1.0, 1.0, 1.0]), np.array([-1.0, 1.0, 1.0])
    else:  # "plain_mesh_stretched"
        obj = {"name": "thing", "shape": "mesh", "file": _plain_ply(tmp_path), "rotation_deg": [25.0, 35.0, 0.0],
               "material": ONE_SIDED}
        s0, s1 = np.array([1.0, 1.0, 1.0]), np.array([2.0, 0.4, 1.0])
    moving = {**obj, "motion": {"keyframes": [{"time_s": 0.0, "scale": s0.tolist()},
                                              {"time_s": 0.01, "scale": s1.tolist()}]}}
    return moving, lambda t: {**obj, "scale": (s0 + (s1 - s0) * t / 0.01).tolist()}


@pytest.mark.parametrize("case", ["negative_scale_cube", pytest.param("authored_normals", marks=pytest.mark.slow),
                                  "cube_scaled_through_zero",
                                  pytest.param("plain_mesh_stretched", marks=pytest.mark.slow)])
def test_a_moving_mesh_renders_as_it_stands_in_the_film_launch(tmp_path, write_scene, case):
    # At each time a moving mesh renders as the same mesh standing still in its pose: with the same seeds the two
    # frames are the same estimate, up to the float32 round-off of the rewritten vertices (a sample's path
    # changes only where it passes within ~1e-7 m of an edge: 2.5e-7 of the largest pixel at most, seen). Before
    # the fix the translating negative-scale cube lost 72 % of the image mean at t = 0 (inside out) and the
    # authored normals were recomputed. The times after the first catch normals left to a recomputation when a
    # pose only translates (the scalar variants skip an update to equal values); the keyframed scales, a cube
    # mirrored part-way (its normals are carried though they equal a recomputation at t = 0) and a mesh without
    # normals (recomputed at every pose, as its load would: carrying them mismatched by up to 5 % of a pixel).
    from render2spike.render.renderer import SceneRenderer
    from render2spike.render.scene import load_scene
    moving, still = _moving_and_still(tmp_path, case)
    r = SceneRenderer(load_scene(write_scene({"objects": [BACK, moving], "reference": REF}, name="moving.yaml")),
                      launch="film")
    assert "thing" in r._moving
    for t in TIMES:
        b = r.render_frame(t, 1, 16)["phi"]
        sc = load_scene(write_scene({"objects": [BACK, still(t)], "reference": REF}, name="still.yaml"))
        ref = SceneRenderer(sc, launch="film", calibration=r.calibration)
        assert not ref._moving
        a = ref.render_frame(t, 1, 16)["phi"]  # (same time: same seeds)
        assert abs(b.mean() / a.mean() - 1.0) < 1e-5, (t, b.mean() / a.mean())
        assert np.abs(b - a).max() <= 1e-4 * a.max(), (t, np.abs(b - a).max() / a.max())


def test_the_film_launch_carries_authored_normals_by_the_inverse_transpose(tmp_path, write_scene):
    # After a rewrite at any time, the mesh's vertex normals are its loaded ones carried by the inverse transpose
    # of the pose change (as an instance's would be), not a recomputation from its triangles
    from render2spike.render.renderer import SceneRenderer
    from render2spike.render.scene import load_scene
    sc = load_scene(write_scene({"objects": _objects(tmp_path, "authored_normals", TURN), "reference": REF}))
    r = SceneRenderer(sc, launch="film")
    kind, _, motion, shape_m, _ = r._moving["thing"]
    assert kind == "vertices"
    for t in (0.0, 0.004, 0.009):
        r.set_time(t)
        n = np.array(r.params["thing.vertex_normals"]).reshape(-1, 3)
        a = (motion.matrix(t) @ shape_m)[:3, :3]  # the file's frame to the world at t
        want = np.array([0.0, 0.0, 1.0]) @ np.linalg.inv(a)  # the file's +z normal, by the inverse transpose
        want /= np.linalg.norm(want)
        np.testing.assert_allclose(n, np.broadcast_to(want, n.shape), atol=1e-5)  # float32 normals


@pytest.mark.parametrize("case", ["negative_scale_cube", pytest.param("authored_normals", marks=pytest.mark.slow)])
def test_film_and_frozen_launches_shade_a_moving_mesh_alike(tmp_path, write_scene, case):
    # The frozen launch moves the mesh as an instance of its t = 0 pose; the film launch rewrites it. Same time,
    # independent seeds: the image means must agree within what each frame's own variance estimate allows
    # (|z| > 4.5: probability 7e-6 if they agree). Before the fix: z = -8102 and -1197 at t = 0 (measured).
    from render2spike.render.scene import load_scene
    sc = load_scene(write_scene({"objects": _objects(tmp_path, case, TURN), "reference": REF}))
    assert_image_means_agree(*film_and_frozen_frames(sc, "thing"))


def test_the_film_launch_records_how_it_moves_mesh_normals(tmp_path, write_scene):
    # The film launch's frames of a scene with a moving mesh that carries its normals depend on how they are
    # moved, so their hash carries it ("mesh_normals"); the hashes of scenes without such a mesh do not, and
    # every film-launch folder records it
    import json

    from render2spike.render.backend import mitsuba
    from render2spike.render.job import render_scene
    from render2spike.render.launch import settings_of
    from render2spike.render.scene import load_scene
    from sensor.io.frames import MANIFEST_NAME
    v = mitsuba().variant()
    sc = load_scene(write_scene({"objects": _objects(tmp_path, "negative_scale_cube", SLOW), "reference": REF}),
                    ["render.spp=4"])
    new = settings_of(sc, v, "film")
    assert new["mesh_normals"] == "carried"
    assert "mesh_normals" not in settings_of(sc, v, "frozen")  # the frozen launch moves meshes as instances
    still = load_scene(write_scene({"objects": _objects(tmp_path, "negative_scale_cube", None), "reference": REF},
                                   name="still.yaml"))
    assert "mesh_normals" not in settings_of(still, v, "film")
    plain, _ = _moving_and_still(tmp_path, "plain_mesh_stretched")  # a moving mesh without normals
    plain = load_scene(write_scene({"objects": [BACK, plain], "reference": REF}, name="plain.yaml"))
    assert "mesh_normals" not in settings_of(plain, v, "film")
    quiet = {"progress": False, "log": lambda *a: None}
    render_scene(sc, tmp_path / "f", launch="film", **quiet)
    manifest = json.loads((tmp_path / "f" / MANIFEST_NAME).read_text())
    assert manifest["mesh_normals"] == "carried" and manifest["scene_hash"] == sc.content_hash(new)
    render_scene(still, tmp_path / "s", launch="film", **quiet)  # a static scene's folder too
    m = json.loads((tmp_path / "s" / MANIFEST_NAME).read_text())
    assert m["mesh_normals"] == "carried" and m["launch"] == "film"


def test_a_refusal_names_every_cause_that_explains_it_in_one_command(tmp_path, write_scene):
    # _refusal_hint: a folder of the film launch on a GPU variant, refused on the CPU with --launch frozen, needs
    # both switches: one sentence names both; each alone is named when it alone explains the folder's hash
    from render2spike.render.launch import refusal_hint, settings_of
    from render2spike.render.scene import load_scene
    sc = load_scene(write_scene({"objects": _objects(tmp_path, "negative_scale_cube", SLOW), "reference": REF}))
    gpu, cpu = "cuda_ad_spectral", "llvm_ad_spectral"
    both = sc.content_hash(settings_of(sc, gpu, "film"))
    h = refusal_hint(sc, cpu, "frozen", "frozen", both, gpu, "film", {}, {})
    assert f"pass --variant {gpu} --launch film to resume it" in h and h.count("resume it") == 1
    h = refusal_hint(sc, cpu, "film", "film", both, gpu, "film", {"mesh_normals": "carried"}, {})
    assert f"pass --variant {gpu} to resume it" in h and "--launch" not in h
    launch_only = sc.content_hash(settings_of(sc, cpu, "film"))
    h = refusal_hint(sc, cpu, "frozen", "frozen", launch_only, cpu, "film", {"mesh_normals": "carried"}, {})
    assert "pass --launch film to resume it" in h and "--variant" not in h
    # a hash that neither explains (another scene): no advice to switch
    assert "pass" not in refusal_hint(sc, cpu, "frozen", "frozen", "0" * 16, cpu, "film", {}, {})
    assert "pass" not in refusal_hint(sc, cpu, "frozen", "frozen", "0" * 16, gpu, "film", {}, {})
    # a run's summary without a hash (render2spike run): no hash to match, so no advice
    for missing in (None, ""):
        assert refusal_hint(sc, cpu, "film", "film", missing, 42, "film", {}, {}) == ""
    # a manifest's variant that is no variant name (a damaged file): no exception, no advice to pass it
    for bad in (42, ["x"], "foo", None):
        assert "--variant" not in refusal_hint(sc, cpu, "film", "film", both, bad, "film", {}, {})
    # a CUDA variant is advised for a machine with a GPU; one the CLI does not offer through the environment
    assert "on a machine with a CUDA GPU" in refusal_hint(sc, cpu, "film", "film", both, gpu, "film", {}, {})
    pol = "llvm_ad_spectral_polarized"
    h = refusal_hint(sc, cpu, "film", "film", sc.content_hash(settings_of(sc, pol, "film")), pol, "film", {}, {})
    assert f"RENDER2SPIKE_VARIANT={pol}" in h


@pytest.mark.slow
def test_the_scalar_variant_moves_meshes_and_their_normals(tmp_path):
    # The scalar variants (the fallback without a working libLLVM) hold vertex buffers as drjit.scalar.ArrayXf,
    # where mi.Float is a Python float: the film launch could not move a mesh there at all before (a TypeError),
    # and they skip the update of a parameter set to equal values. The film-launch tests above, in a child
    # process on scalar_spectral (the variant is set for the whole process).
    import os
    import subprocess
    import sys
    from pathlib import Path
    root = Path(__file__).resolve().parents[2]
    env = dict(os.environ, PYTHONPATH=str(root), RENDER2SPIKE_VARIANT="scalar_spectral")
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--runslow", "--basetemp",
                        str(tmp_path / "t"), f"{__file__}::test_a_moving_mesh_renders_as_it_stands_in_the_film_launch",
                        f"{__file__}::test_the_film_launch_carries_authored_normals_by_the_inverse_transpose",
                        f"{__file__}::test_the_scalar_variant_reports_its_variant"],
                       cwd=root, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0 and "6 passed" in r.stdout, r.stdout[-3000:] + r.stderr[-2000:]


def test_the_scalar_variant_reports_its_variant():
    # (run by the test above in its child process: that the child really is on the variant it was given)
    import os

    from render2spike.render.backend import mitsuba
    assert mitsuba().variant() == os.environ.get("RENDER2SPIKE_VARIANT", mitsuba().variant())


def test_which_mesh_files_bring_their_own_normals(tmp_path):
    # builder.mesh_file_has_normals: what Mitsuba's loaders take from a file (PLY: an nx property of the vertex
    # element, ASCII or binary; OBJ: vn lines that faces use); builder.carries_normals: a cube always
    import trimesh

    from render2spike.render.builder import carries_normals, mesh_file_has_normals
    from sensor.errors import InputError
    box = trimesh.creation.box(extents=[1, 1, 1])
    assert mesh_file_has_normals(write_ply_with_normals(tmp_path / "a.ply"))
    (tmp_path / "b.ply").write_bytes(trimesh.exchange.ply.export_ply(box, encoding="binary", vertex_normal=True))
    (tmp_path / "c.ply").write_bytes(trimesh.exchange.ply.export_ply(box, encoding="binary", vertex_normal=False))
    assert mesh_file_has_normals(tmp_path / "b.ply") and not mesh_file_has_normals(tmp_path / "c.ply")
    # a normal-like property of another element is not a vertex normal
    (tmp_path / "d.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                                    "property float z\nelement face 1\nproperty float nx\n"
                                    "property list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n"
                                    "0.5 3 0 1 2\n")
    assert not mesh_file_has_normals(tmp_path / "d.ply")
    # all three of nx, ny, nz, or Mitsuba computes them
    (tmp_path / "i.ply").write_text((tmp_path / "d.ply").read_text().replace(
        "property float z\nelement face 1\nproperty float nx\n", "property float z\nproperty float nx\n"
        "element face 1\n").replace("0 0 0\n1 0 0\n0 1 0\n", "0 0 0 1\n1 0 0 1\n0 1 0 1\n"))
    assert not mesh_file_has_normals(tmp_path / "i.ply")
    # OBJ lines are tokenised as Mitsuba's loader does: leading blanks, tabs, CRLF
    tri = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\n"
    for name, lines, want in (("e.obj", "vn 0 0 1\nf 1//1 2//1 3//1\n", True),
                              ("f.obj", "vn 0 0 1\nf 1/1/1 2/1/1 3/1/1\n", True),
                              ("g.obj", "vn\t0 0 1\r\n  f\t1//1 2//1 3//1\r\n", True),
                              ("h.obj", "   vn 0 0 1\nf 1//1 2//1 3//1\n", True),
                              ("k.obj", "f 1 2 3\n", False), ("l.obj", "f 1/1 2/1 3/1\n", False)):
        (tmp_path / name).write_text(tri + lines)
        assert mesh_file_has_normals(tmp_path / name) == want, name
    # vn lines with faces that give no normal index: Mitsuba 3.9 leaves those normals undefined (garbage that
    # changes from load to load): refused, naming the file
    for name, faces in (("m.obj", "f 1 2 3\n"), ("n.obj", "f 1/1 2/1 3/1\n"), ("o.obj", "f 1/1/ 2/1/ 3/1/\n"),
                        ("p.obj", "f 1//1 2//1 3//1\nf 1 2 3\n"), ("q.obj", "f 1//0 2//0 3//0\n"),
                        ("r.obj", "f 1 2//1 3//1\n"),
                        # an explicit 0 (in any spelling) overwrites the normal carried along the line
                        ("s.obj", "f 1//1 2//0 3\n"), ("t.obj", "f 1//1 2//1 3//0\n"),
                        ("u.obj", "f 1//00 2//00 3//00\n"),
                        # a carriage return ends a corner, as a blank does
                        ("w.obj", "f 1\r2//1 3//1\n")):
        (tmp_path / name).write_bytes((tri + "vn 0 0 1\n" + faces).encode())
        with pytest.raises(InputError, match="without a normal index") as err:
            mesh_file_has_normals(tmp_path / name)
        assert name in str(err.value)
    # a line of two corners makes no triangle: its missing normal is never used (Mitsuba builds nothing of it)
    (tmp_path / "x.obj").write_text(tri + "vn 0 0 1\nf 1//1 2//1 3//1\nf 2 3\n")
    assert mesh_file_has_normals(tmp_path / "x.obj")
    with pytest.raises(InputError, match="cannot read the mesh file"):
        mesh_file_has_normals(tmp_path / "missing.ply")

    class _Scene:  # (carries_normals needs only Scene.file and the objects, for the field a refusal names)
        data = {"objects": []}

        def file(self, name, field):
            return tmp_path / name
    assert carries_normals(_Scene(), {"shape": "cube"}) and not carries_normals(_Scene(), {"shape": "sphere"})
    assert carries_normals(_Scene(), {"shape": "mesh", "file": "a.ply"})
    assert not carries_normals(_Scene(), {"shape": "mesh", "file": "c.ply"})


def test_a_moving_mesh_flat_at_t0_is_refused(tmp_path, write_scene):
    # Both launches place a moving mesh in its t = 0 pose and move it from there: a scale keyframed through zero
    # exactly at t = 0 is refused with the field to change (it raised numpy's LinAlgError before)
    from render2spike.render.launch import resolve_launch
    from render2spike.render.renderer import SceneRenderer
    from render2spike.render.scene import load_scene
    from sensor.errors import InputError
    obj = {"name": "thing", "shape": "cube", "size": [0.06, 0.06, 0.06], "material": ONE_SIDED,
           "motion": {"keyframes": [{"time_s": -0.005, "scale": [1.0, 1.0, 1.0]},
                                    {"time_s": 0.005, "scale": [-1.0, 1.0, 1.0]}]}}
    sc = load_scene(write_scene({"objects": [BACK, obj], "reference": REF}))
    for call in (lambda: resolve_launch("auto", "llvm_ad_spectral", sc), lambda: SceneRenderer(sc, launch="film")):
        with pytest.raises(InputError, match="flat at t = 0") as err:
            call()
        assert "objects.1.motion" in str(err.value)


def test_the_normals_rule_agrees_with_mitsubas_loaders(tmp_path):
    # The oracle: Mitsuba itself. A file whose normals it keeps has, after loading, normals that are not its own
    # recomputation from the triangles (every normal here is +z, which no tetrahedron's faces give); a file it
    # computes them for has its recomputation. mesh_file_has_normals must say which, file by file.
    from render2spike.render.backend import mitsuba
    from render2spike.render.builder import mesh_file_has_normals
    mi = mitsuba()
    tet_v = ["0 0 0", "1 0 0", "0 1 0", "0 0 1"]
    tet_f = [(1, 3, 2), (1, 2, 4), (1, 4, 3), (2, 3, 4)]
    objs = {
        "vv_n.obj": "\n".join(f"v {v}" for v in tet_v) + "\nvn 0 0 1\n"
                    + "".join(f"f {a}//1 {b}//1 {c}//1\n" for a, b, c in tet_f),
        "tabs.obj": "\n".join(f"v {v}" for v in tet_v) + "\r\nvt 0 0\r\n  vn\t0 0 1\r\n"
                    + "".join(f"\tf\t{a}/1/1 {b}/1/1 {c}/1/1\r\n" for a, b, c in tet_f),
        "plain.obj": "\n".join(f"v {v}" for v in tet_v) + "\n" + "".join(f"f {a} {b} {c}\n" for a, b, c in tet_f),
        # a corner without a normal index takes the one before it on its face line (Mitsuba 3.9 keeps it)
        "carried.obj": "\n".join(f"v {v}" for v in tet_v) + "\nvn 0 0 1\n"
                       + "".join(f"f {a}//1 {b} {c}\n" for a, b, c in tet_f),
        # "vn" with no blank after it is no normal line to Mitsuba
        "bare_vn.obj": "\n".join(f"v {v}" for v in tet_v) + "\nvn\n" + "".join(f"f {a} {b} {c}\n" for a, b, c in tet_f),
    }
    for name, text in objs.items():
        (tmp_path / name).write_text(text)

    def ply(name, props, rows):
        head = ["ply", "format ascii 1.0", "element vertex 4", "property float x", "property float y",
                "property float z", *[f"property float {p}" for p in props], "element face 4",
                "property list uchar int vertex_indices", "end_header"]
        body = [f"{v} {rows}".strip() for v in tet_v] + [f"3 {a - 1} {b - 1} {c - 1}" for a, b, c in tet_f]
        (tmp_path / name).write_text("\n".join(head + body) + "\n")
    ply("n.ply", ["nx", "ny", "nz"], "0 0 1")
    text = (tmp_path / "n.ply").read_text().replace("format ascii 1.0\n", "format ascii 1.0\ncomment no end_header here\n")
    (tmp_path / "comment.ply").write_text(text)
    ply("nx_only.ply", ["nx"], "1")
    ply("plain.ply", [], "")
    for name in (*objs, "n.ply", "comment.ply", "nx_only.ply", "plain.ply"):
        s = mi.load_dict({"type": "scene", "m": {"type": name.split(".")[1], "filename": str(tmp_path / name)}})
        p = mi.traverse(s)
        loaded = np.array(p["m.vertex_normals"])
        p["m.vertex_positions"] = type(p["m.vertex_positions"])(np.array(p["m.vertex_positions"]))
        p.set_dirty("m.vertex_positions")
        p.update()
        kept = not np.allclose(loaded, np.array(p["m.vertex_normals"]), atol=1e-4)
        assert mesh_file_has_normals(tmp_path / name) == kept, name


def test_the_normals_rule_sees_a_mesh_file_changed_in_place(tmp_path):
    # the answer is cached per file, keyed by its inode, size and times: a rewrite of the same size whose
    # modification time is put back (as cp -p, rsync or tar do) still changes its status time
    import os
    import time

    from render2spike.render.builder import mesh_file_has_normals
    from sensor.errors import InputError
    f = tmp_path / "m.obj"
    good = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nf 1//1 2//1 3//1\n"
    bad = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nf 1 2//1 3//1\n"
    bad += " " * (len(good) - len(bad))
    f.write_text(good)
    st = f.stat()
    assert mesh_file_has_normals(f)
    time.sleep(0.05)
    f.write_text(bad)
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert f.stat().st_size == st.st_size and f.stat().st_mtime_ns == st.st_mtime_ns
    with pytest.raises(InputError, match="without a normal index"):
        mesh_file_has_normals(f)


def test_a_refused_obj_names_the_scene_field_still_or_moving(tmp_path, write_scene):
    from render2spike.render.renderer import SceneRenderer
    from render2spike.render.scene import load_scene
    from sensor.errors import InputError
    (tmp_path / "bad.obj").write_text("v 0 0 0\nv 0.01 0 0\nv 0 0.01 0\nvn 0 0 1\nf 1 2 3\n")
    obj = {"name": "thing", "shape": "mesh", "file": "bad.obj", "material": ONE_SIDED}
    for o in (obj, {**obj, "motion": SLOW}):
        with pytest.raises(InputError, match="without a normal index") as err:
            SceneRenderer(load_scene(write_scene({"objects": [BACK, o], "reference": REF})), launch="film")
        assert err.value.field == "objects.1.file"


def test_a_moving_mesh_flat_only_by_its_size_or_scale_is_refused_naming_it(write_scene):
    # the threshold: a thickness of 1e-13 of the rest is flat (refused, naming the scale); 1e-6 is a thin plate
    from render2spike.render.renderer import SceneRenderer
    from render2spike.render.scene import load_scene
    from sensor.errors import InputError
    base = {"name": "thing", "shape": "cube", "size": [0.06, 0.06, 0.06], "material": ONE_SIDED, "motion": SLOW}
    with pytest.raises(InputError, match="flat at t = 0") as err:
        SceneRenderer(load_scene(write_scene({"objects": [BACK, {**base, "scale": [1.0, 1.0, 1e-13]}],
                                              "reference": REF})), launch="film")
    assert err.value.field == "objects.1.scale"
    r = SceneRenderer(load_scene(write_scene({"objects": [BACK, {**base, "scale": [1.0, 1.0, 1e-6]}],
                                              "reference": REF}, name="thin.yaml")), launch="film")
    assert "thing" in r._moving
    # flat by its size, though its keyframes scale it: the size is named
    keyed = {**base, "size": [0.06, 0.06, 1e-15], "motion": {"keyframes": [
        {"time_s": 0.0, "scale": [1.0, 1.0, 1.0]}, {"time_s": 0.01, "scale": [1.0, 1.0, 2.0]}]}}
    with pytest.raises(InputError, match="flat at t = 0") as err:
        SceneRenderer(load_scene(write_scene({"objects": [BACK, keyed], "reference": REF}, name="size.yaml")),
                      launch="film")
    assert err.value.field == "objects.1.size"


def test_the_hash_of_a_scene_with_a_refused_obj_names_its_field(tmp_path, write_scene):
    # (settings_of reads the mesh file through builder.carries_normals: its refusal names the object's field too)
    from render2spike.render.launch import settings_of
    from render2spike.render.scene import load_scene
    from sensor.errors import InputError
    (tmp_path / "bad.obj").write_text("v 0 0 0\nv 0.01 0 0\nv 0 0.01 0\nvn 0 0 1\nf 1 2 3\n")
    sc = load_scene(write_scene({"objects": [BACK, {"name": "thing", "shape": "mesh", "file": "bad.obj",
                                                    "material": ONE_SIDED, "motion": SLOW}], "reference": REF}))
    with pytest.raises(InputError, match="without a normal index") as err:
        settings_of(sc, "llvm_ad_spectral", "film")
    assert err.value.field == "objects.1.file"
