"""The package's module-level imports form no cycle (a layered house: each module imports only
from below), and its packages import only the layers above them in docs/ARCHITECTURE.md's
table, lazy imports included (annotation-only imports under ``if TYPE_CHECKING:`` do not run).

The scanner reads the source (no import is run), resolves relative imports, and finds the
strongly connected components of the module graph; the second test shows it finds a cycle, the
fourth that the layer check finds an import from below.
"""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1] / "prognos_torch"


def _modules(root: Path) -> dict[str, Path]:
    out = {}
    for p in root.rglob("*.py"):
        parts = list(p.relative_to(root.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


def _type_checking(node) -> bool:
    return isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)


def _nodes(tree: ast.Module, lazy: bool):
    """The module's top-level statements, or with ``lazy`` every node outside ``if
    TYPE_CHECKING:`` blocks (imports inside functions included)."""
    if not lazy:
        yield from tree.body
        return
    todo = list(tree.body)
    while todo:
        node = todo.pop()
        if _type_checking(node):
            todo.extend(node.orelse)
            continue
        yield node
        todo.extend(ast.iter_child_nodes(node))


def import_graph(root: Path, lazy: bool = False) -> dict[str, set[str]]:
    """``{module: modules it imports at module level}`` within the package at ``root`` (with
    ``lazy``: anywhere in the module but under ``if TYPE_CHECKING:``)."""
    mods = _modules(root)
    pkg = root.name
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for m, p in mods.items():
        is_pkg = p.name == "__init__.py"
        for node in _nodes(ast.parse(p.read_text(encoding="utf-8")), lazy):
            if isinstance(node, ast.ImportFrom):
                if node.level:
                    base = m.split(".") if is_pkg else m.split(".")[:-1]
                    base = base[: len(base) - (node.level - 1)]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                names = [f"{target}.{a.name}" for a in node.names]
                targets = [n if n in mods else target for n in names]
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                continue
            for t in targets:
                if not (t == pkg or t.startswith(pkg + ".")):
                    continue
                while t not in mods and "." in t:
                    t = t.rsplit(".", 1)[0]
                if t in mods and t != m:
                    graph[m].add(t)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = 0
    for start in graph:
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on.add(start)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
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
    return out


def test_the_package_has_no_import_cycle():
    graph = import_graph(ROOT)
    assert len(graph) > 100 and sum(map(len, graph.values())) > 100  # the scan saw the package
    assert cycles(graph) == []


def test_the_scanner_finds_a_cycle(tmp_path):
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from .sub.b import f\n")
    (pkg / "sub" / "__init__.py").write_text("from .b import f\n")
    (pkg / "sub" / "b.py").write_text("from ..a import g\n\ndef f():\n    from .. import c\n")
    (pkg / "c.py").write_text("import pkg.a\n")
    graph = import_graph(pkg)
    assert graph["pkg.sub.b"] == {"pkg.a"}  # the import inside f does not count
    assert cycles(graph) == [["pkg.a", "pkg.sub.b"]]


#: top-level helper modules and the layer of the table they belong to
HELPERS = {"_text": "workflow", "_command": "workflow", "_workers": "workflow", "cli_parser": "cli",
           "cli_prognose": "cli", "__main__": "cli"}  # fmt: skip


def layers(doc: Path) -> dict[str, int]:
    """``{package: row}`` of the "## Layers" table of ``doc`` (first column, backticked)."""
    text = doc.read_text(encoding="utf-8").split("## Layers", 1)[1]
    rows = [line for line in text.splitlines() if line.startswith("| `")]
    out = {}
    for i, line in enumerate(rows):
        first = line.split("|")[1]
        for name in first.split("`")[1::2]:
            out[name] = i
    return out


def layer_violations(root: Path, rows: dict[str, int]) -> list[str]:
    """Imports (lazy ones included) of a package from a row below its own."""
    pkg = root.name
    graph = import_graph(root, lazy=True)

    def row(module: str) -> int | None:
        parts = module.split(".")
        if len(parts) == 1:  # the package's __init__ (the version): every layer may read it
            return None
        name = HELPERS.get(parts[1], parts[1])
        assert name in rows, f"{module}: its package {name!r} is not in the layer table"
        return rows[name]

    bad = []
    for m, targets in graph.items():
        mine = row(m)
        for t in targets:
            theirs = row(t)
            if mine is not None and theirs is not None and theirs > mine:
                bad.append(f"{m} imports {t}")
    assert pkg
    return sorted(bad)


def test_packages_import_only_the_layers_above_them():
    rows = layers(ROOT.parent / "docs" / "ARCHITECTURE.md")
    assert {"core", "filters", "optim", "prognosis", "workflow", "cli"} <= set(rows)
    assert layer_violations(ROOT, rows) == []


def test_the_layer_check_finds_an_import_from_below(tmp_path):
    pkg = tmp_path / "pkg"
    for sub in ("core", "filters"):
        (pkg / sub).mkdir(parents=True)
        (pkg / sub / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("")
    (pkg / "core" / "a.py").write_text("def f():\n    from ..filters import b\n")
    (pkg / "filters" / "b.py").write_text(
        "from typing import TYPE_CHECKING\nfrom ..core import a\nif TYPE_CHECKING:\n    from ..core import a\n"
    )
    assert layer_violations(pkg, {"core": 0, "filters": 1}) == ["pkg.core.a imports pkg.filters.b"]
