"""The GPU benchmarks' report logic on made-up rows and files: no rendering, no timing.

``benchmarks/render_gpu.py``: what the issue's goal line decides from (GPU samples/s over CPU samples/s at the
same scene, resolution and spp, per CPU measured against) must pair the right rows and say met / not met
correctly. ``benchmarks/repro_check.py``: its frame comparison must see a one-ulp difference and count it.
``benchmarks/render_launch.py``: its table must carry every row, freeze outcome and load.
"""

import importlib.util
import json
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


def _frames(folder, values):
    from sensor.frames import frame_filename, write_frame
    folder.mkdir()
    for i, v in enumerate(values):
        write_frame(folder / frame_filename(i), v, np.full_like(v, 3.0), time_s=i * 1e-3)


def test_repro_compare_counts_a_one_ulp_difference(tmp_path):
    import pytest
    mod = _module("repro_check")
    rng = np.random.default_rng(5)
    a = [rng.uniform(1.0, 2.0, (4, 6)).astype(np.float32) for _ in range(3)]
    b = [x.copy() for x in a]
    b[1][2, 3] = np.nextafter(b[1][2, 3], np.float32(3.0))  # one ulp up, in one value of one frame
    _frames(tmp_path / "x", a)
    _frames(tmp_path / "y", a)
    _frames(tmp_path / "z", b)
    same = mod.compare(tmp_path / "x", tmp_path / "y")
    assert same == {"frames": 3, "frames_bitwise_equal": 3, "pixel_values_compared": 3 * 2 * 24,
                    "pixel_values_differing": 0, "max_rel_diff": 0.0}
    diff = mod.compare(tmp_path / "x", tmp_path / "z")
    assert diff["frames_bitwise_equal"] == 2 and diff["pixel_values_differing"] == 1
    ulp = float(np.spacing(a[1][2, 3])) / float(a[1][2, 3])  # one float32 ulp relative to the value
    assert diff["max_rel_diff"] == pytest.approx(ulp, rel=1e-6)
    sorted((tmp_path / "z").glob("frame_*.exr"))[-1].unlink()
    with pytest.raises(RuntimeError, match="different frame files"):
        mod.compare(tmp_path / "x", tmp_path / "z")


def test_launch_table_has_every_row_and_freeze_outcome(tmp_path):
    mod = _module("render_launch")
    med = {k: 1.0 for k in ("wall_ms", "call_ms", "sync_ms", "trace_ms", "codegen_ms", "backend_ms", "exec_ms")}
    base = {"date": "2026-11-26 12:00:00", "machine": "M", "load_before": [1.0, 2.0, 3.0],
            "load_after": [1.5, 2.0, 3.0], "variant": "cuda_ad_spectral", "scene": "s", "resolution": "32x48",
            "spp": 16, "median": dict(med, kernels=2), "samples_per_s": 1e7}
    rows = [dict(base), dict(base, freeze={"works": False, "error": "RuntimeError: VarType mismatch"}),
            dict(base, spp=256, freeze={"works": True, "wall_ms_median": 0.5, "films_equal_unfrozen": 9,
                                        "frames": 10})]
    text = mod.write_md(tmp_path, rows).read_text()
    table = [ln for ln in text.splitlines() if ln.startswith("|")]
    assert len(table) == 2 + 3
    assert len({ln.count("|") for ln in table}) == 1  # header, separator and rows have the same columns
    assert "1.00, 2.00, 3.00 / 1.50, 2.00, 3.00" in table[2]
    assert table[2].endswith("| - |") and "fails: RuntimeError: VarType mismatch" in table[3]
    assert "works: 0.50 ms, 9/10 films equal" in table[4]
