"""The GPU benchmarks' report logic on made-up rows and files: no rendering, no timing.

``benchmarks/render_gpu.py``: what the issue's goal line decides from (GPU samples/s over CPU samples/s at the
same scene, resolution and spp, per CPU measured against) must pair the right rows and say met / not met
correctly. ``benchmarks/repro_check.py``: its frame comparison must see a one-ulp difference in either
channel and a different reference light level. ``benchmarks/render_launch.py``: a frame's split from its
clock readings and kernel history, medians without the warm-up frames, and a table with each value under its
own column, every freeze outcome and the load. And every benchmark script or result file the docs name, and the
CPU reference the GPU check reads, exists.
"""

import importlib.util
import json
import re
import sys

import numpy as np
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _module(name="render_gpu"):
    spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    saved, had = list(sys.path), sys.modules.get("tables")
    try:
        spec.loader.exec_module(mod)  # it puts benchmarks/ first on sys.path for its `tables`
    finally:
        sys.path[:] = saved  # neither the path nor the benchmark's `tables` module is left to shadow
        if had is None:      # anything in later tests (`tables` is also PyTables' name)
            sys.modules.pop("tables", None)
        else:
            sys.modules["tables"] = had
    return mod


def _row(variant, scene, res, spp, sps):
    return {"ok": True, "variant": variant, "scene": scene, "resolution": res, "spp": spp, "samples_per_s": sps,
            "frames": 16, "bare_s_per_frame": 0.01, "pipeline_s_per_frame": 0.011, "overhead_ratio": 1.1,
            "compile_s_per_block": [0.5, 0.6], "load_before": [1.0], "load_after": [1.2]}


def _meta(cpu, cores):
    return {"command": "x", "date": "2026-11-26 12:00:00", "machine": {"cpu": cpu, "cores": cores, "gpu": "G"},
            "load_before": [1.0, 1.0, 1.0], "load_after": [1.1, 1.0, 1.0], "working": ["cuda_ad_spectral"],
            "not_working": {}, "auto_variant": "cuda_ad_spectral"}


def test_ratios_pair_same_point_and_prefer_llvm_over_scalar():
    m = _module()
    rows = [_row("cuda_ad_spectral", "disk", "250x400", 256, 1e9),
            _row("scalar_spectral", "disk", "250x400", 256, 1e6),  # listed first: LLVM must still be chosen
            _row("llvm_ad_spectral", "disk", "250x400", 256, 4e7),
            _row("llvm_ad_spectral", "disk", "250x400", 16, 3e7),  # no GPU row at 16 spp: not paired
            _row("cuda_ad_spectral", "plane", "32x48", 256, 1e8)]  # no CPU row: not paired
    out = m.ratio_rows(rows, rows, "here")
    assert len(out) == 1
    q = out[0]
    assert (q["scene"], q["resolution"], q["spp"], q["cpu_variant"]) == ("disk", "250x400", 256, "llvm_ad_spectral")
    assert q["ratio"] == 1e9 / 4e7


def test_goal_lines_per_reference(tmp_path):
    m = _module()
    rows = [_row("cuda_ad_spectral", "disk", "250x400", 256, 1e9),
            _row("llvm_ad_spectral", "disk", "250x400", 256, 1e8),    # 10x on the same machine: not met
            _row("cuda_ad_spectral", "disk", "64x96", 16, 2e7),
            _row("llvm_ad_spectral", "disk", "64x96", 16, 1e7)]       # 2x
    ref = {"meta": _meta("EPYC", 2), "rows": [_row("llvm_ad_spectral", "disk", "250x400", 256, 1e7),    # 100x
                                              _row("llvm_ad_spectral", "disk", "64x96", 16, 5e5)]}      # 40x
    path = m.write_report(tmp_path, _meta("Xeon", 16), rows, ref)
    text = path.read_text()
    lines = [ln for ln in text.splitlines() if ln.startswith("- ")]
    assert len(lines) == 2
    same, other = lines
    assert "Xeon, 16 cores" in same and "**not met**" in same and "at 0 of 2 points" in same
    assert "EPYC, 2 cores" in other and "**met**" in other and "not met" not in other
    assert "100.0-100.0x" in other and "40.0-40.0x" in other
    saved = json.loads((tmp_path / "render_gpu.json").read_text())
    assert saved["rows"] == rows


def _frames(folder, values, E=None, reference=None):
    from sensor.io.frames import frame_filename, write_frame, write_manifest
    folder.mkdir()
    entries = []
    for i, v in enumerate(values):
        e = np.full_like(v, 3.0) if E is None else E[i]
        write_frame(folder / frame_filename(i), v, e, time_s=i * 1e-3)
        entries.append({"file": frame_filename(i), "time_s": i * 1e-3})
    write_manifest(folder, *values[0].shape, entries, reference=reference)


def test_repro_compare_counts_one_ulp_differences_in_each_channel(tmp_path):
    import pytest
    mod = _module("repro_check")
    rng = np.random.default_rng(5)
    a = [rng.uniform(1.0, 2.0, (4, 6)).astype(np.float32) for _ in range(3)]
    E = [rng.uniform(10.0, 20.0, (4, 6)).astype(np.float32) for _ in range(3)]
    b = [x.copy() for x in a]
    b[1][2, 3] = np.nextafter(b[1][2, 3], np.float32(3.0))  # one ulp up, in one Phi value of frame 1
    E2 = [x.copy() for x in E]
    E2[2][0, 0] = np.nextafter(E2[2][0, 0], np.float32(0.0))  # one ulp down, in one E value of frame 2
    ref = {"raw_e_meter": 5.9}
    _frames(tmp_path / "x", a, E, ref)
    _frames(tmp_path / "y", a, E, ref)
    _frames(tmp_path / "z", b, E2, {"raw_e_meter": 6.0})
    same = mod.compare(tmp_path / "x", tmp_path / "y")
    assert same == {"frames": 3, "frames_bitwise_equal": 3, "pixel_values_compared": 3 * 2 * 24,
                    "pixel_values_differing": 0, "max_rel_diff": 0.0, "manifest_frames_equal": True,
                    "reference_equal": True}
    diff = mod.compare(tmp_path / "x", tmp_path / "z")
    assert diff["frames_bitwise_equal"] == 1 and diff["pixel_values_differing"] == 2
    ulps = [float(np.spacing(a[1][2, 3])) / float(a[1][2, 3]),  # one float32 ulp relative to each value
            float(np.spacing(np.nextafter(E[2][0, 0], np.float32(0.0)))) / float(E[2][0, 0])]
    assert diff["max_rel_diff"] == pytest.approx(max(ulps), rel=1e-6)
    assert diff["manifest_frames_equal"] and not diff["reference_equal"]
    sorted((tmp_path / "z").glob("frame_*.exr"))[-1].unlink()
    with pytest.raises(RuntimeError, match="different frame files"):
        mod.compare(tmp_path / "x", tmp_path / "z")


def test_launch_frame_row_and_medians():
    import pytest
    mod = _module("render_launch")
    JIT, MEMSET = "jit", "memset"  # stand-ins for Dr.Jit's KernelType values
    hist = [{"type": JIT, "codegen_time": 0.3, "backend_time": 0.0, "execution_time": 0.2, "cache_hit": True},
            {"type": JIT, "codegen_time": 0.1, "backend_time": 5.0, "execution_time": 0.4, "cache_hit": False},
            {"type": MEMSET, "execution_time": 0.05}]
    r = mod.frame_row(10.0, 10.001, 10.009, 10.012, hist, JIT)  # clock readings [s]
    assert r["update_ms"] == pytest.approx(1.0) and r["call_ms"] == pytest.approx(8.0)
    assert r["sync_ms"] == pytest.approx(3.0) and r["wall_ms"] == pytest.approx(12.0)
    assert r["codegen_ms"] == pytest.approx(0.4) and r["backend_ms"] == pytest.approx(5.0)
    assert r["exec_ms"] == pytest.approx(0.6) and r["other_kernels_ms"] == pytest.approx(0.05)
    assert r["trace_ms"] == pytest.approx(8.0 - 0.4 - 5.0)  # the render call less kernel assembly and compile
    assert r["kernels"] == 2 and r["cache_misses"] == 1
    assert r["params_update_ms"] == 0.0 and r["pose_ms"] == pytest.approx(1.0)  # a static scene: no update
    r = mod.frame_row(10.0, 10.001, 10.009, 10.012, hist, JIT, params_update_s=0.0007)  # set_time: 0.3 + 0.7 ms
    assert r["params_update_ms"] == pytest.approx(0.7) and r["pose_ms"] == pytest.approx(0.3)
    assert r["update_ms"] == pytest.approx(1.0)
    rows = [{"wall_ms": 100.0}, {"wall_ms": 90.0}, {"wall_ms": 3.0}, {"wall_ms": 5.0}, {"wall_ms": 4.0}]
    assert mod.summarize(rows, 2) == {"wall_ms": 4.0}  # the two warm-up frames are not in the median
    with pytest.raises(ValueError, match="no timed frames"):
        mod.summarize(rows, 5)


def test_launch_table_has_every_row_column_and_freeze_outcome(tmp_path):
    mod = _module("render_launch")
    med = {k: 1.0 + i for i, k in enumerate(mod.KEYS)}  # a distinct value per column
    base = {"date": "2026-11-26 12:00:00", "machine": "M", "load_before": [1.0, 2.0, 3.0],
            "load_after": [1.5, 2.0, 3.0], "variant": "cuda_ad_spectral", "scene": "s", "resolution": "32x48",
            "spp": 16, "median": dict(med, kernels=2), "samples_per_s": 1e7}
    old = dict(base, median={k: v for k, v in base["median"].items() if k not in ("update_ms", "other_kernels_ms")})
    rows = [dict(base), dict(base, launch="frozen", freeze={"works": False, "error": "RuntimeError: VarType mismatch"}),
            dict(base, spp=256, freeze={"works": True, "wall_ms_median": 0.5, "films_equal_unfrozen": 9,
                                        "frames": 10, "max_rel_diff_vs_unfrozen": 3e-7}), old]
    text = mod.write_md(tmp_path, rows).read_text()
    table = [ln for ln in text.splitlines() if ln.startswith("|")]
    assert len(table) == 2 + 4
    assert len({ln.count("|") for ln in table}) == 1  # header, separator and rows have the same columns
    head = [c.strip() for c in table[0].strip("|").split("|")]
    cells = [c.strip() for c in table[2].strip("|").split("|")]
    for i, k in enumerate(mod.KEYS):  # each value under its own column
        assert cells[head.index(k)] == f"{1.0 + i:.3f}"
    assert cells[head.index("load before/after")] == "1.00, 2.00, 3.00 / 1.50, 2.00, 3.00"
    assert cells[head.index("freeze")] == "-"
    assert cells[head.index("launch")] == "film"  # rows without a launch were the film launch's
    assert "fails: RuntimeError: VarType mismatch" in table[3]
    assert [c.strip() for c in table[3].strip("|").split("|")][head.index("launch")] == "frozen"
    assert "works: 0.50 ms, 9/10 films equal, max rel. diff. 3e-07" in table[4]
    old_cells = [c.strip() for c in table[5].strip("|").split("|")]
    assert old_cells[head.index("update_ms")] == "-" and old_cells[head.index("wall_ms")] == "1.000"


def test_frozen_launch_report_pairs_rounds_and_columns():
    # benchmarks/render_frozen.py: per round film / frozen, the job against the film's bare launch and against each
    # launch's own, every value under its own column, the load range over every child
    mod = _module("render_frozen")

    def row(ms, lb=1.0, la=1.5, rec=None):
        return {"median_ms": ms, "height": 32, "width": 48, "recordings": rec, "load_before": [lb], "load_after": [la]}
    p = {"scene": "plane", "size": "window", "spp": 16,
         "film": [row(4.0), row(6.0)], "frozen": [row(2.0, rec=3), row(1.5, lb=0.5, la=2.5, rec=2)],
         "pipeline_film": [row(5.0), row(6.6)], "pipeline_frozen": [row(3.0), row(3.0)]}
    p["pipeline_frozen"][0]["file_create"] = {"wall_ms": 0.61, "sys_ms": 0.55}  # (the second: a run before the probe)
    p["pipeline_nowrite_frozen"] = [row(2.2), row(1.8)]
    res = {"when": "now", "machine": "m", "rounds": 2, "frames": 8, "warm": 1, "points": [p],
           "jobs": [{"scene": "plane", "launch": "frozen", "wall_s": 1.5, "frames": 3, "spp": 35,
                     "render_noise_ratio": 0.197, "load_before": [0.7], "load_after": [0.9]}]}
    text = mod.report(res)
    launch_row = [ln for ln in text.splitlines() if ln.startswith("| plane | 32 x 48 | 16 | 4.00")][0]
    cells = [c.strip() for c in launch_row.strip("|").split("|")]
    assert cells[3:8] == ["4.00, 6.00", "2.00, 1.50", "2.00, 4.00", "3, 2", "0.50-2.50"]
    job_row = [ln for ln in text.splitlines() if ln.startswith("| plane | 32 x 48 | 16 | 5.00")][0]
    cells = [c.strip() for c in job_row.strip("|").split("|")]
    # frozen job / bare film launch, film job / film launch, frozen job / frozen launch
    assert cells[3:8] == ["5.00, 6.60", "3.00, 3.00", "0.75, 0.50", "1.25, 1.10", "1.50, 2.00"]
    # frozen job - its launch (ms); the file-creation probe; the job without frame files / its launch
    assert cells[8:11] == ["1.00, 1.50", "0.61 (0.55), -", "1.10, 1.20"]
    assert "| plane | frozen | 1.50 | 3 | 35 | 0.197 | 0.70-0.90 |" in text


def test_the_file_creation_probe_leaves_its_folder_as_it_found_it(tmp_path):
    mod = _module("render_frozen")
    (tmp_path / "frame.exr").write_bytes(b"x")
    got = mod.file_create_probe(tmp_path, n=5)
    assert got["wall_ms"] > 0 and got["sys_ms"] >= 0
    assert [p.name for p in tmp_path.iterdir()] == ["frame.exr"]


def test_files_the_docs_and_the_gpu_check_name_exist():
    docs = [ROOT / "README.md", ROOT / "benchmarks" / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    named = set()
    for doc in docs:
        named |= {(doc.name, m) for m in re.findall(r"\b((?:benchmarks|docs)/[\w/.\-]*\w)", doc.read_text())}
    gpu_check = (ROOT / "benchmarks" / "gpu_check.sh").read_text()
    named |= {("gpu_check.sh", m) for m in re.findall(r"--cpu-ref (\S+)", gpu_check)}
    assert any(path.startswith("benchmarks/results/") for _, path in named)
    missing = sorted((doc, path) for doc, path in named if not (ROOT / path).exists())
    assert not missing, f"named but not in the repository: {missing}"
