"""Number formatting shared by the benchmark tables (benchmarks/run.py, benchmarks/render.py)."""

from __future__ import annotations


def fmt(x, nd: int = 2) -> str:
    """A table cell: '' for None/'', strings as they are, scientific for very large or small numbers."""
    if x is None or (isinstance(x, str) and x == ""):
        return ""
    if isinstance(x, str):
        return x
    if abs(x) >= 1e5 or (0 < abs(x) < 1e-2):
        return f"{x:.2e}"
    return f"{x:.{nd}f}"


def machine() -> dict:
    """CPU model, cores and (where ``nvidia-smi`` answers) the GPU and driver of this machine."""
    import os
    import subprocess
    cpu = ""
    try:
        cpu = next(ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name"))
    except (OSError, StopIteration):
        pass
    gpu = None
    try:
        out = subprocess.run(["nvidia-smi", "--query-gpu=name,driver_version,memory.total", "--format=csv,noheader"],
                             capture_output=True, text=True, timeout=30)
        gpu = out.stdout.strip() or None
    except (OSError, subprocess.TimeoutExpired):
        pass
    return {"cpu": cpu, "cores": len(os.sched_getaffinity(0)), "gpu": gpu}


def write_report(out_dir, stem: str, lines: list[str], record: dict | None = None) -> None:
    """Write ``OUT/STEM.md`` (the lines) and, with ``record``, ``OUT/STEM.json``; print the table."""
    import json
    from pathlib import Path
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if record is not None:
        (out_dir / f"{stem}.json").write_text(json.dumps(record, indent=1, default=str))
    (out_dir / f"{stem}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
