"""Issue 27's structural targets, kept from regressing: thin stages (<= 300 lines each), no module over 800
lines, no import cycle among objcam's modules, and the synthetic-capture code in one package (``objcam/synth/``).

The import graph is read from the source with :mod:`ast` (nothing is imported): every ``import`` and
``from ... import``, at the top of a module or inside a function (a lazy import that dodges a cycle at import time
is still a cycle in the design), relative ones resolved. ``from objcam.pkg import name`` is an edge to the module
``objcam.pkg.name`` when that is a module, else to ``objcam.pkg`` itself; ``import objcam.pkg.sub`` is an edge to
``objcam.pkg.sub`` only (not to the package ``__init__`` Python runs first). So a package's ``__init__`` importing
its submodules is no cycle by itself; a submodule importing its own package's ``__init__`` (``from objcam import
pkg``, or a name ``pkg/__init__.py`` defines or re-exports) while that ``__init__`` imports it is one.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "objcam"
MAX_STAGE_LINES = 300
MAX_MODULE_LINES = 800
SYNTH_PACKAGE = "synth"  # objcam/synth/: the synthetic-capture code


def module_files(root: Path, package: str) -> dict[str, Path]:
    """{dotted module name: file} of every ``.py`` file under ``root / package`` (a package is its
    ``__init__``)."""
    out = {}
    for f in sorted((root / package).rglob("*.py")):
        parts = f.relative_to(root).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = f
    return out


def _statements(tree: ast.AST):
    """Every statement of ``tree``, nested ones (in functions, classes, if / try / with / loop bodies) included;
    expressions are not entered (an import is a statement; a tenth of the time of ast.walk)."""
    todo = [tree]
    while todo:
        node = todo.pop()
        for name in ("body", "orelse", "finalbody", "handlers", "cases"):
            children = getattr(node, name, None)
            if isinstance(children, list):
                todo += children
        if isinstance(node, ast.stmt):
            yield node


def _imported_names(tree: ast.Module, module: str, is_package: bool) -> list[tuple[str, int]]:
    """(dotted name, line) of everything a module imports, anywhere in its body: ``import a.b`` gives ``a.b``,
    ``from a import x`` gives ``a.x`` (``x`` may be a submodule or a name defined in ``a``), relative imports
    resolved against the module's package (its own name when it is a package's ``__init__``)."""
    names = []
    for node in _statements(tree):
        if isinstance(node, ast.Import):
            names += [(alias.name, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            prefix = node.module or ""
            if node.level:
                base = module.split(".")[:None if is_package else -1]
                base = base[:len(base) - (node.level - 1)]
                prefix = ".".join(base + ([node.module] if node.module else []))
            names += [(prefix if alias.name == "*" else f"{prefix}.{alias.name}", node.lineno)
                      for alias in node.names]
    return names


def import_graph(root: Path, package: str) -> dict[str, dict[str, int]]:
    """{module: {imported module: line of its first import}} among the modules of ``package`` under ``root``.

    An imported name maps to the longest of its prefixes that is a module: ``from a import x`` is ``a.x`` when
    that is a module, else ``a``; names outside the package map to nothing."""
    files = module_files(root, package)
    graph: dict[str, dict[str, int]] = {}
    for mod, path in files.items():
        edges: dict[str, int] = {}
        for name, line in _imported_names(ast.parse(path.read_text(), str(path)), mod, path.name == "__init__.py"):
            while name and name not in files:
                name = name.rpartition(".")[0]
            if name and name != mod:  # a package's __init__ importing its own names is no edge
                edges[name] = min(line, edges.get(name, line))
        graph[mod] = edges
    return graph


def strongly_connected(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """The strongly connected components of more than one module (each sorted), by Tarjan's algorithm,
    iterative (no recursion limit)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    out: list[list[str]] = []
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.get(child, {})))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                comp = []
                while True:
                    m = stack.pop()
                    on_stack.discard(m)
                    comp.append(m)
                    if m == node:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return sorted(out)


def describe_cycles(graph: dict[str, dict[str, int]], components: list[list[str]]) -> str:
    """One line per import inside each cycle (``a:12 -> b``), the cycles separated by blank lines."""
    blocks = []
    for comp in components:
        members = set(comp)
        blocks.append("\n".join(f"  {a}:{line} -> {b}" for a in comp for b, line in sorted(graph[a].items())
                                if b in members))
    return "\n\n".join(blocks)


def _lines(path: Path) -> int:
    return len(path.read_text().splitlines())


# ------------------------------------------------------------------------------------------------ targets


def test_stages_are_thin():
    stages = sorted(p for p in (ROOT / PACKAGE / "stages").glob("*.py") if p.name != "__init__.py")
    assert stages
    long = {p.name: _lines(p) for p in stages if _lines(p) > MAX_STAGE_LINES}
    assert not long, f"stage modules over {MAX_STAGE_LINES} lines: {long}"


def test_no_module_is_huge():
    long = {str(p.relative_to(ROOT)): _lines(p) for p in module_files(ROOT, PACKAGE).values()
            if _lines(p) > MAX_MODULE_LINES}
    assert not long, f"modules over {MAX_MODULE_LINES} lines: {long}"


def test_no_import_cycles():
    graph = import_graph(ROOT, PACKAGE)
    assert len(graph) > 50 and sum(map(len, graph.values())) > 100  # the whole package was read
    cycles = strongly_connected(graph)
    assert not cycles, f"{len(cycles)} import cycle(s) among objcam's modules:\n" + describe_cycles(graph, cycles)


def test_synthetic_capture_code_lives_in_objcam_synth():
    synth = ROOT / PACKAGE / SYNTH_PACKAGE
    cli = ROOT / PACKAGE / "pipeline" / "synth_cli.py"  # the `objcam synth` subcommand: CLI, calls objcam.synth
    stray = sorted(str(p.relative_to(ROOT)) for p in (ROOT / PACKAGE).rglob("*.py")
                   if (p.name.startswith("synth") or p.name == "synthetic.py") and synth not in p.parents
                   and p != cli)
    assert not stray, f"synthetic-capture modules outside objcam/{SYNTH_PACKAGE}/: {stray}"


# ------------------------------------------------------------------------------------- the cycle finder


def _write_package(root: Path, files: dict[str, str]) -> None:
    for name, text in files.items():
        path = root / "fake" / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


def test_cycle_finder_sees_lazy_imports(tmp_path):
    # a imports b absolutely and b imports a relatively, both inside functions
    _write_package(tmp_path, {
        "__init__.py": "",
        "a.py": "def f():\n    from fake.b import g\n    return g\n",
        "b.py": "import os\n\n\ndef g():\n    from .a import f\n    return f\n",
        "c.py": "from fake import a\n",
    })
    graph = import_graph(tmp_path, "fake")
    assert graph["fake.a"] == {"fake.b": 2} and graph["fake.b"] == {"fake.a": 5} and graph["fake.c"] == {"fake.a": 1}
    assert strongly_connected(graph) == [["fake.a", "fake.b"]]
    assert describe_cycles(graph, strongly_connected(graph)) == "  fake.a:2 -> fake.b\n  fake.b:5 -> fake.a"


def test_cycle_finder_sees_a_submodule_importing_its_package(tmp_path):
    # edges imports the package itself, other a name the package re-exports: both are cycles with its __init__
    _write_package(tmp_path, {
        "__init__.py": "",
        "pkg/__init__.py": "from fake.pkg.edges import edge\nfrom .edges import other\nfrom .other import third\n",
        "pkg/edges.py": "def edge():\n    from fake import pkg\n    return pkg\n\n\nother = 1\n",
        "pkg/other.py": "def third():\n    from fake.pkg import edge\n    return edge\n",
    })
    graph = import_graph(tmp_path, "fake")
    assert graph["fake.pkg"] == {"fake.pkg.edges": 1, "fake.pkg.other": 3}
    assert graph["fake.pkg.edges"] == {"fake.pkg": 2} and graph["fake.pkg.other"] == {"fake.pkg": 2}
    assert strongly_connected(graph) == [["fake.pkg", "fake.pkg.edges", "fake.pkg.other"]]


def test_cycle_finder_passes_an_acyclic_package(tmp_path):
    _write_package(tmp_path, {
        "__init__.py": "from fake.a import f\n",
        "a.py": "from fake.b import g\n\n\ndef f():\n    from . import c\n    return g, c\n",
        "b.py": "def g():\n    import fake.c\n    return fake.c\n",
        "c.py": "import numpy\n",
        "sub/__init__.py": "from . import d\nfrom .d import name\n",
        "sub/d.py": "from ..c import numpy as name\n",
    })
    graph = import_graph(tmp_path, "fake")
    assert graph["fake.a"] == {"fake.b": 1, "fake.c": 5} and graph["fake.sub"] == {"fake.sub.d": 1}
    assert graph["fake.sub.d"] == {"fake.c": 1}
    assert strongly_connected(graph) == []


def test_cycle_finder_separates_cycles():
    """Two cycles joined one way, a self-contained chain: two components, the chain in none."""
    graph = {"a": {"b": 1}, "b": {"a": 1, "c": 2}, "c": {"d": 1}, "d": {"c": 1, "e": 1}, "e": {}, "f": {"a": 1}}
    assert strongly_connected(graph) == [["a", "b"], ["c", "d"]]


@pytest.mark.parametrize("n", [3, 2000])
def test_cycle_finder_on_a_ring(n):
    """A ring of n modules is one cycle, found without recursion."""
    graph = {f"m{i}": {f"m{(i + 1) % n}": 1} for i in range(n)}
    graph["tail"] = {"m0": 1}
    assert strongly_connected(graph) == [sorted(f"m{i}" for i in range(n))]
