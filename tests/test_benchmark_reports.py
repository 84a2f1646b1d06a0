"""The GPU render benchmark's report logic (benchmarks/render_gpu.py) on made-up rows: no rendering, no timing.

What the issue's goal line decides from (GPU samples/s over CPU samples/s at the same scene, resolution and
spp, per CPU measured against) must pair the right rows and say met / not met correctly.
"""

import importlib.util
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _module():
    spec = importlib.util.spec_from_file_location("render_gpu", ROOT / "benchmarks" / "render_gpu.py")
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
