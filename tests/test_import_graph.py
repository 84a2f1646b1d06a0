"""The import graph of the three packages has no circles, function-level imports included.

Every ``import`` and ``from ... import`` anywhere in a module (top level, functions, classes) is an edge
from that module to the module it names: ``from a.b import c`` goes to ``a.b.c`` when that is a module,
else to ``a.b``. The implicit import of parent packages is not an edge. A cycle means two modules need each
other, which the function-level imports that hide it do not fix. The same walk checks the one-way flow:
``sensor`` and ``recon`` import neither Mitsuba nor ``render2spike``, and ``sensor`` does not import ``recon``.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("render2spike", "sensor", "recon")


def _modules() -> dict[str, Path]:
    mods = {}
    for pkg in PACKAGES:
        base = ROOT / pkg
        for p in base.rglob("*.py"):
            rel = p.relative_to(ROOT).with_suffix("")
            parts = list(rel.parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            mods[".".join(parts)] = p
    return mods


def _resolve(name: str, mods) -> str | None:
    """The longest prefix of dotted ``name`` that is one of our modules (None for third-party names)."""
    parts = name.split(".")
    while parts:
        cand = ".".join(parts)
        if cand in mods:
            return cand
        parts.pop()
    return None


def import_graph() -> tuple[dict[str, set[str]], dict[str, set[str]]]:
    """(edges between our modules, every top-level name each module imports)."""
    mods = _modules()
    edges: dict[str, set[str]] = {m: set() for m in mods}
    external: dict[str, set[str]] = {m: set() for m in mods}
    for mod, path in mods.items():
        is_pkg = path.name == "__init__.py"
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = mod.split(".") if is_pkg else mod.split(".")[:-1]
                    base = base[:len(base) - (node.level - 1)]
                    src = ".".join(base + ([node.module] if node.module else []))
                else:
                    src = node.module
                targets = [f"{src}.{a.name}" for a in node.names]
            for t in targets:
                external[mod].add(t.split(".")[0])
                r = _resolve(t, mods)
                if r is not None and r != mod:
                    edges[mod].add(r)
    return edges, external


def find_cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan), each sorted."""
    index, low, on, stack, out, counter = {}, {}, set(), [], [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    import sys
    old = sys.getrecursionlimit()
    sys.setrecursionlimit(max(old, 10000))
    try:
        for v in sorted(edges):
            if v not in index:
                visit(v)
    finally:
        sys.setrecursionlimit(old)
    return out


def test_find_cycles_finds_a_planted_cycle():
    assert find_cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert find_cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycles():
    edges, _ = import_graph()
    assert len(edges) > 50, "the walk found too few modules"
    cycles = find_cycles(edges)
    assert not cycles, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_data_flows_one_way():
    edges, external = import_graph()
    bad = []
    for mod, names in external.items():
        top = mod.split(".")[0]
        if top in ("sensor", "recon"):
            bad += [f"{mod} imports {n}" for n in sorted(names & {"mitsuba", "drjit", "render2spike"})]
        if top == "sensor":
            bad += [f"{mod} imports recon" for n in names if n == "recon"]
    assert not bad, "\n".join(bad)
