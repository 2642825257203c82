"""The layers of the code base, as import-linter contracts (``[tool.importlinter]`` in
pyproject.toml), run by the tests so that a change that breaks one fails here.

``lint-imports`` checks the layers (core < methods < bench < apps) and cycles between the
children of each package (``acyclic_siblings``). Two checks it does not make are here, on the
same import graph (grimp, import-linter's own): no module-to-module cycle at all (a package's
``__init__`` and its children included), and every module of sysid_bench placed in a layer.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import grimp
import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("sysid_bench", "methods")


def _config() -> dict:
    with open(ROOT / "pyproject.toml", "rb") as f:
        return tomllib.load(f)["tool"]["importlinter"]


def _contract(cid: str) -> dict:
    return next(c for c in _config()["contracts"] if c["id"] == cid)


@pytest.fixture(scope="module")
def graph():
    return grimp.build_graph(*PACKAGES, cache_dir=None)


def test_lint_imports_keeps_every_contract():
    exe = shutil.which("lint-imports", path=str(Path(sys.executable).parent)) or "lint-imports"
    r = subprocess.run([exe, "--no-cache"], cwd=ROOT, capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, "lint-imports found broken contracts:\n" + r.stdout + r.stderr


def _cycles(graph) -> list[list[str]]:
    """The strongly connected components of more than one module (each holds a cycle)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    counter = 0
    for root in sorted(graph.modules):
        if root in index:
            continue
        # iterative Tarjan: (node, iterator over its successors)
        work = [(root, iter(sorted(graph.find_modules_directly_imported_by(root))))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            v, succ = work[-1]
            for w in succ:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph.find_modules_directly_imported_by(w)))))
                    break
                if w in on_stack:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        found.append(sorted(comp))
    return found


def _describe(graph, comp: list[str]) -> str:
    """One cycle through ``comp``, each import with its line."""
    members = set(comp)
    start = comp[0]
    # breadth-first from start back to start, inside the component
    prev: dict[str, str] = {}
    frontier = [start]
    seen = {start}
    end = None
    while frontier and end is None:
        nxt = []
        for v in frontier:
            for w in sorted(graph.find_modules_directly_imported_by(v) & members):
                if w == start:
                    end = v
                    break
                if w not in seen:
                    seen.add(w)
                    prev[w] = v
                    nxt.append(w)
            if end is not None:
                break
        frontier = nxt
    path = [end]
    while path[-1] != start:
        path.append(prev[path[-1]])
    path = path[::-1] + [start]
    lines = []
    for a, b in zip(path, path[1:]):
        det = graph.get_import_details(importer=a, imported=b)
        where = f" (line {det[0]['line_number']}: {det[0]['line_contents']})" if det else ""
        lines.append(f"  {a} -> {b}{where}")
    return "\n".join(lines)


def test_no_import_cycles(graph):
    cycles = _cycles(graph)
    assert not cycles, "import cycles:\n" + "\n\n".join(_describe(graph, c) for c in cycles)


def test_cycle_finder_finds_a_cycle():
    g = grimp.ImportGraph()
    for m in ("p", "p.a", "p.b", "p.c", "p.d"):
        g.add_module(m)
    g.add_import(importer="p.a", imported="p.b")
    g.add_import(importer="p.b", imported="p.c")
    g.add_import(importer="p.c", imported="p.a")
    g.add_import(importer="p.d", imported="p.a")
    assert _cycles(g) == [["p.a", "p.b", "p.c"]]
    text = _describe(g, ["p.a", "p.b", "p.c"])
    assert text.splitlines() == ["  p.a -> p.b", "  p.b -> p.c", "  p.c -> p.a"]


def test_every_module_of_sysid_bench_is_in_a_layer(graph):
    # the folder tree is the layer map: every module of sysid_bench is in core/, bench/ or
    # apps/, or is one of the public aliases at the top (which the layers never import)
    folders = {"sysid_bench.core", "sysid_bench.bench", "sysid_bench.apps"}
    aliases = set(_contract("apps")["forbidden_modules"])
    top = {".".join(m.split(".")[:2]) for m in graph.modules if m.startswith("sysid_bench.")}
    missing = sorted(top - folders - aliases)
    assert not missing, (f"modules in no layer: {missing}; move each into sysid_bench/core/, "
                         "bench/ or apps/ (or list a public alias in pyproject.toml's contracts)")
    assert set(_contract("bench")["forbidden_modules"]) == aliases | {"sysid_bench.apps"}
    assert set(_contract("methods")["forbidden_modules"]) == (
        aliases | {"sysid_bench.apps", "sysid_bench.bench"})
    assert set(_contract("core")["forbidden_modules"]) == (
        aliases | {"sysid_bench.apps", "sysid_bench.bench", "methods"})
