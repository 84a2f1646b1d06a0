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
