"""The Python packages' modules form no import cycle, as ``server/tests/module_graph.rs`` checks
for the server: every ``import`` and ``from ... import`` in ``client-py/dinerdash``,
``agents/dinerdash_agents`` and ``bench/dinerdash_bench`` is read with :mod:`ast`, those inside
functions (and under ``TYPE_CHECKING``) included, since an import moved into a function hides a
cycle without removing it.

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
    "dinerdash_bench": REPO / "bench" / "dinerdash_bench",
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
    assert len(graph) > 3, f"found only {sorted(graph)} under {PACKAGES[package]}"
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


#: The client's layers, lowest first: a module may import the client's modules of its own layer
#: or a lower one, never a higher one. ``_batch`` (the reply's arrays) knows nothing of
#: connections or sessions; the transports know no environment.
LAYERS = [
    {"dinerdash._proto", "dinerdash.game", "dinerdash._grpc_settings"},
    {"dinerdash._batch", "dinerdash.errors", "dinerdash._version"},
    {"dinerdash.connection", "dinerdash.server", "dinerdash._arguments"},
    {"dinerdash._shm", "dinerdash._endpoint"},
    {"dinerdash._session"},
    {"dinerdash._fleet"},
    {"dinerdash.env", "dinerdash.vector"},
]


def test_the_client_layers_point_down() -> None:
    graph = graph_of("dinerdash", PACKAGES["dinerdash"])
    layer = {m: i for i, ms in enumerate(LAYERS) for m in ms}
    for m in layer:
        assert m in graph or m == "dinerdash._proto", f"{m} is no module of the client"
    upward = [
        f"{m} -> {t}"
        for m in sorted(layer)
        for t in sorted(graph.get(m, ()))
        if t in layer and layer[t] > layer[m]
    ]
    assert not upward, "imports up the layers: " + "; ".join(upward)


def _private_writes(path: Path) -> list[str]:
    """``x._attr = ...`` (and ``+=``, annotated) where ``x`` is not ``self`` or ``cls``, unless
    ``x`` is made in the same module by a class of that module or as a copy of ``self`` (the
    ``child`` of a fork)."""
    tree = ast.parse(path.read_text(), str(path))
    classes = {n.name for n in ast.walk(tree) if isinstance(n, ast.ClassDef)}
    made_here: set[str] = set()
    for node in ast.walk(tree):
        # ``child = Own(...)`` / ``child = copy.copy(self)``: an object of this module's class.
        if isinstance(node, ast.Assign) and isinstance(node.value, ast.Call):
            names = {n.id for n in ast.walk(node.value) if isinstance(n, ast.Name)}
            if names & (classes | {"self"}):
                made_here.update(t.id for t in node.targets if isinstance(t, ast.Name))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign):
            targets = node.targets
        elif isinstance(node, (ast.AugAssign, ast.AnnAssign)):
            targets = [node.target]
        else:
            continue
        for target in targets:
            for sub in ast.walk(target):
                if not (isinstance(sub, ast.Attribute) and sub.attr.startswith("_")):
                    continue
                if not sub.attr.startswith("__") and not (
                    isinstance(sub.value, ast.Name) and sub.value.id in {"self", "cls", *made_here}
                ):
                    out.append(f"{path.name}:{node.lineno}: {ast.unparse(sub)}")
    return out


@pytest.mark.parametrize("package", sorted(PACKAGES))
def test_no_module_writes_another_objects_private_state(package: str) -> None:
    """Read with :mod:`ast`: no assignment to a private attribute (``_name``) of an object other
    than ``self``/``cls`` or one the same module's class just made (a fork's ``child``)."""
    paths = [p for p in sorted(PACKAGES[package].rglob("*.py")) if "_proto" not in p.parts]
    found = [w for path in paths for w in _private_writes(path)]
    assert not found, "private state written from outside: " + "; ".join(found)


#: A session core's state (:class:`dinerdash._session.SessionCore`): its range of environments
#: and server (fixed: a move makes new cores) and what a step, a failover, a move or a
#: reconnect leaves in it. Only ``_session.py`` (the core's own methods: ``adopt``,
#: ``interrupt``, ``reset``...) changes them; every other module reads them.
SESSION_STATE = [
    "index",
    "start",
    "stop",
    "last",
    "pending",
    "reconnected",
    "session_id",
    "offer",
    "transport",
    "last_transport",
    "step_thread",
    "shm_sent",
    "drain_ms",
]
#: Methods that change a container in place (``core.entering.update(...)`` writes the state).
_MUTATORS = {"add", "update", "clear", "discard", "remove", "pop", "fill", "sort", "append"}


def _session_state_writes(path: Path) -> list[str]:
    """``x.<state> = ...`` (and ``+=``, annotated, ``x.<state>[i] = ...``, ``del``) and
    ``x.<state>.update(...)``-like calls, for a name of :data:`SESSION_STATE` and any ``x``
    but ``self``/``cls`` (a class's own attribute of that name is its own)."""

    def session_attr(node: ast.AST) -> bool:
        return (
            isinstance(node, ast.Attribute)
            and node.attr in SESSION_STATE
            and not (isinstance(node.value, ast.Name) and node.value.id in {"self", "cls"})
        )

    def written(target: ast.AST):
        """The attributes a write to ``target`` changes: ``a.b[i].c = ...`` changes ``a.b[i].c``
        and ``a.b`` (in place), not what the index ``i`` reads."""
        if isinstance(target, (ast.Tuple, ast.List)):
            for element in target.elts:
                yield from written(element)
        elif isinstance(target, ast.Starred):
            yield from written(target.value)
        elif isinstance(target, ast.Attribute):
            yield target
            yield from written(target.value)
        elif isinstance(target, ast.Subscript):
            yield from written(target.value)

    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Assign):
            targets = node.targets
        elif isinstance(node, (ast.AugAssign, ast.AnnAssign)):
            targets = [node.target]
        elif isinstance(node, ast.Delete):
            targets = node.targets
        elif (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr in _MUTATORS
            and session_attr(node.func.value)
        ):
            out.append(f"{path.name}:{node.lineno}: {ast.unparse(node.func)}()")
            continue
        else:
            continue
        for target in targets:
            for sub in written(target):
                if session_attr(sub):
                    out.append(f"{path.name}:{node.lineno}: {ast.unparse(sub)}")
    return out


def test_only_the_session_core_changes_its_state() -> None:
    """Read with :mod:`ast`: no module of the client but ``_session.py`` assigns (or changes in
    place) a session core's state attributes (:data:`SESSION_STATE`); the fleet, the failover
    and the envs change them through the core's methods (:mod:`dinerdash._session`)."""
    root = PACKAGES["dinerdash"]
    paths = [p for p in sorted(root.rglob("*.py")) if "_proto" not in p.parts]
    assert root / "_fleet.py" in paths and root / "_session.py" in paths
    found = [w for p in paths if p.name != "_session.py" for w in _session_state_writes(p)]
    assert not found, "a session core's state written from outside _session.py: " + "; ".join(found)


def test_the_session_state_check_sees_every_kind_of_write(tmp_path: Path) -> None:
    """The check finds a plain, a tuple, an augmented, an indexed and an in-place write, and
    leaves a class's own attribute of the same name and a read alone."""
    path = tmp_path / "m.py"
    path.write_text(
        "def f(core, new, env):\n"
        "    core.last = None\n"
        "    new.pending, new.offer = None, None\n"
        "    env._core.reconnected = False\n"
        "    core.stop[0] = True\n"
        "    new.start |= 1\n"
        "    new.transport.update([2])\n"
        "    x = core.last\n"
        "    loads[core.index] += core.stop\n"
        "    mask[[i - core.start for i in core.session_id]] = True\n"
        "    core.pending.copy()\n"
        "class C:\n"
        "    def g(self):\n"
        "        self.last = 1\n"
    )
    found = _session_state_writes(path)
    assert [w.split(": ", 1)[1] for w in found] == [
        "core.last",
        "new.pending",
        "new.offer",
        "env._core.reconnected",
        "core.stop",
        "new.start",
        "new.transport.update()",
    ], found


def _unread_internal_names(root: Path) -> list[str]:
    """The package-internal module-level names (a function, class or assignment named ``_x``,
    or any in a private module ``_x.py``/package ``_x/``) that no code of the package reads:
    by name, anywhere in the package (a use under another object of the same name hides one;
    the check errs towards silence, never towards a false alarm)."""
    paths = [p for p in sorted(root.rglob("*.py")) if "_proto" not in p.parts]
    read: set[str] = set()
    defined: list[tuple[str, str]] = []
    for path in paths:
        tree = ast.parse(path.read_text(), str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Name) and isinstance(node.ctx, ast.Load):
                read.add(node.id)
            elif isinstance(node, ast.Attribute):
                read.add(node.attr)
            elif isinstance(node, ast.alias):
                read.add(node.name.rpartition(".")[2])
        parts = path.relative_to(root).parts
        internal = any(p.startswith("_") and not p.startswith("__") for p in parts)
        for node in tree.body:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                names = [node.name]
            elif isinstance(node, ast.Assign):
                names = [t.id for t in node.targets if isinstance(t, ast.Name)]
            elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
                names = [node.target.id]
            else:
                names = []
            defined += [
                (f"{path.relative_to(root)}:{node.lineno}", name)
                for name in names
                if not name.startswith("__") and (internal or name.startswith("_"))
            ]
    return [f"{where}: {name}" for where, name in defined if name not in read]


def test_the_package_holds_no_test_only_code() -> None:
    """Read with :mod:`ast`: every package-internal module-level name of the client is read by
    the client itself. One only tests read (as ``_shm._CHANNELS`` was) belongs in ``tests/``
    (or in :mod:`dinerdash.testing`, public, when it helps users test), one nobody reads goes."""
    found = _unread_internal_names(PACKAGES["dinerdash"])
    assert not found, "internal names the package never reads: " + "; ".join(found)


def test_the_test_only_check_finds_an_unread_internal_name(tmp_path: Path) -> None:
    (tmp_path / "_inner.py").write_text("def used():\n    pass\nTESTS_ONLY = 1\n")
    (tmp_path / "outer.py").write_text(
        "from ._inner import used\n_unread = 2\nPUBLIC = 3\n\ndef f():\n    used()\n"
    )
    assert [w.split(": ", 1)[1] for w in _unread_internal_names(tmp_path)] == [
        "TESTS_ONLY",
        "_unread",
    ]
