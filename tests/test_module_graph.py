"""The Python packages' modules form no import cycle, as ``server/tests/module_graph.rs`` checks
for the server: every ``import`` and ``from ... import`` in ``client-py/dinerdash`` and
``agents/dinerdash_agents`` is read with :mod:`ast`, those inside functions (and under
``TYPE_CHECKING``) included, since an import moved into a function hides a cycle without
removing it.

An edge goes to the module an import names: ``from . import checkpoint`` to ``pkg.checkpoint``,
``from . import __version__`` to the package's ``__init__``, ``from .x import y`` to ``pkg.x.y``
when that is a module, else to ``pkg.x``. The parent packages Python initialises on the way are
not edges (every module would otherwise depend on ``__init__``, which imports them back)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
PACKAGES = {
    "dinerdash": REPO / "client-py" / "dinerdash",
    "dinerdash_agents": REPO / "agents" / "dinerdash_agents",
}

Graph = dict[str, set[str]]


def modules(package: str, root: Path) -> dict[str, tuple[Path, bool]]:
    """Dotted module name -> (file, whether it is a package's ``__init__``)."""
    found = {}
    for path in sorted(root.rglob("*.py")):
        parts = list(path.relative_to(root).with_suffix("").parts)
        is_package = parts[-1] == "__init__"
        if is_package:
            parts = parts[:-1]
        found[".".join([package, *parts])] = (path, is_package)
    return found


def _known(name: str, known: dict) -> str | None:
    """``name`` or its longest prefix that is a module of ``known``."""
    parts = name.split(".")
    while parts:
        if ".".join(parts) in known:
            return ".".join(parts)
        parts.pop()
    return None


def imports_of(module: str, path: Path, is_package: bool, package: str, known: dict) -> set[str]:
    """The modules of ``package`` that ``module``'s code imports, anywhere in the file."""
    out: set[str] = set()
    here = module if is_package else module.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = here.split(".")
                base = base[: len(base) - (node.level - 1)]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            names = []
            for alias in node.names:
                child = f"{source}.{alias.name}"
                names.append(child if child in known else source)
        else:
            continue
        for name in names:
            if name == package or name.startswith(package + "."):
                target = _known(name, known)
                if target is not None and target != module:
                    out.add(target)
    return out


def graph_of(package: str, root: Path) -> Graph:
    known = modules(package, root)
    return {
        name: imports_of(name, path, is_package, package, known)
        for name, (path, is_package) in known.items()
    }


def cycles(graph: Graph) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def _explain(graph: Graph, component: list[str]) -> str:
    inside = set(component)
    return "; ".join(
        f"{m} -> {', '.join(sorted(graph[m] & inside))}" for m in component if graph[m] & inside
    )


@pytest.mark.parametrize("package", sorted(PACKAGES))
def test_no_import_cycle(package: str) -> None:
    graph = graph_of(package, PACKAGES[package])
    assert len(graph) > 5, f"found only {sorted(graph)} under {PACKAGES[package]}"
    found = cycles(graph)
    assert not found, "import cycles: " + " | ".join(_explain(graph, c) for c in found)


def test_the_reader_sees_every_kind_of_import(tmp_path: Path) -> None:
    """A cycle hidden in a function, one through ``from . import``, one through the package's
    ``__init__`` (``from . import __version__``) and an absolute one are all found; a package's
    own parents are not edges."""
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    files = {
        "__init__.py": "from .a import f\n__version__ = '1'\n",
        "a.py": "def f():\n    from . import b\n",
        "b.py": "from .a import f\n",
        "c.py": "from . import __version__\n",
        "sub/__init__.py": "",
        "sub/d.py": "import pkg.sub.e\n",
        "sub/e.py": "from ..sub import d\nfrom .. import c\n",
    }
    for name, text in files.items():
        (pkg / name).write_text(text)
    graph = graph_of("pkg", pkg)
    assert graph["pkg.a"] == {"pkg.b"} and graph["pkg.b"] == {"pkg.a"}
    assert graph["pkg.c"] == {"pkg"} and graph["pkg.sub.e"] == {"pkg.sub.d", "pkg.c"}
    assert graph["pkg.sub.d"] == {"pkg.sub.e"}
    assert cycles(graph) == [["pkg.a", "pkg.b"], ["pkg.sub.d", "pkg.sub.e"]]
    # The package's __init__ imports a, which does not import it: no cycle through pkg.
    assert "pkg" not in graph["pkg.a"]
