"""The static import graph of the packages (cilia_runtime, single_cilium, ciliary_carpet): no import
circle, layers that import only downwards (LAYERS), and no module reaching into another's private
parts.

Built from the source with ``ast`` (nothing is imported): every ``import`` and ``from ... import``
statement of every module, at the top or inside a function (a lazy import is still an edge), that
names a module of the two packages. ``from package import name`` is an edge to the submodule
``package.name`` when there is one, else to ``package`` (its ``__init__``). The implicit import of
a parent package by its submodules is not an edge (it is how Python packages work, and a package's
``__init__`` re-exporting its submodules is the layer's front door, not a circle).

Private means a name with a leading underscore (dunder names such as ``__version__`` are public).
A module may import a private module only from inside that module's own package, and no module
may import or read (``module._name``) another module's private names.
"""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("cilia_runtime", "single_cilium", "ciliary_carpet")

# The layers, bottom first: a module may import its own layer and the layers below it, never one
# above. The machinery at the ground floor; the filament; the flow sums; the carpet model; the flow
# through it (path lines, FTLE); designs (objects in, objects out); the writers of outputs; the
# scene file turned into objects; the render that runs a scene; the command line; the front door.
LAYERS = ("cilia_runtime", "single_cilium", "ciliary_carpet.stokes", "ciliary_carpet.carpet",
          "ciliary_carpet.transport", "ciliary_carpet.design", "ciliary_carpet.output",
          "ciliary_carpet.scenes", "ciliary_carpet.render", "ciliary_carpet.batch", "ciliary_carpet.cli",
          "ciliary_carpet")

# Known faults, each listed with why it is tolerated until it is fixed (none today: issue 25 fixed
# the last ones); test_known_faults_still_exist keeps the lists honest.
ALLOWED_CYCLES: set[frozenset[str]] = set()
ALLOWED_PRIVATE: set[str] = set()
# Imports that go up the layers, until they are turned round (issue 44).
ALLOWED_UPWARD: set[str] = set()


def _is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def _modules() -> dict[str, Path]:
    """Every module of the packages by dotted name (a package by its own name, for __init__.py)."""
    out = {}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = path
    return out


MODULES = _modules()


def _package_of(module: str) -> str:
    """The package a module lives in (a package's __init__ lives in the package itself)."""
    return module if (MODULES[module].name == "__init__.py") else module.rpartition(".")[0]


def _resolve(importer: str, node: ast.ImportFrom) -> str:
    """The absolute module name of ``from <node.module> import ...`` (relative ones resolved)."""
    if not node.level:
        return node.module or ""
    base = _package_of(importer).split(".")
    base = base[:len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _ours(name: str) -> bool:
    return name.split(".")[0] in PACKAGES


def _scan(module: str) -> tuple[set[str], list[str]]:
    """(the modules of the packages that ``module`` imports, its private-access violations)."""
    tree = ast.parse(MODULES[module].read_text(), filename=str(MODULES[module]))
    edges: set[str] = set()
    bad: list[str] = []
    aliases: dict[str, str] = {}  # local name -> module of ours it is bound to

    def target(name: str) -> None:
        if name == module or name not in MODULES:
            return
        edges.add(name)
        private = [p for p in name.split(".") if _is_private(p)]
        if private and not (module + ".").startswith(name.rpartition(".")[0] + "."):
            bad.append(f"{module} imports the private module {name}")

    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if _ours(a.name):
                    target(a.name)
                    aliases[a.asname or a.name.split(".")[0]] = a.name if a.asname else a.name.split(".")[0]
        elif isinstance(node, ast.ImportFrom):
            src = _resolve(module, node)
            if not _ours(src):
                continue
            for a in node.names:
                sub = f"{src}.{a.name}"
                if sub in MODULES:
                    target(sub)
                    aliases[a.asname or a.name] = sub
                else:
                    target(src)
                    if _is_private(a.name) and src != module:
                        bad.append(f"{module} imports the private name {a.name} of {src}")
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in aliases:
            if _is_private(node.attr) and f"{aliases[node.value.id]}.{node.attr}" not in MODULES:
                bad.append(f"{module} reads the private name {node.attr} of {aliases[node.value.id]}")
    return edges, bad


GRAPH: dict[str, set[str]] = {}
PRIVATE: list[str] = []
for _m in MODULES:
    GRAPH[_m], _b = _scan(_m)
    PRIVATE += _b


def _cycles(graph: dict[str, set[str]]) -> list[frozenset[str]]:
    """The strongly connected components with more than one module (Tarjan), or with a self-loop."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[frozenset[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = set()
            while True:
                w = stack.pop()
                on.discard(w)
                comp.add(w)
                if w == v:
                    break
            if len(comp) > 1 or v in graph[v]:
                out.append(frozenset(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_scan_sees_the_packages():
    assert len(MODULES) > 40
    assert "ciliary_carpet.stokes.direct" in GRAPH["ciliary_carpet.stokes.dispatch"]
    assert "ciliary_carpet.stokes.kernel" in GRAPH["ciliary_carpet.stokes.direct"]
    assert "ciliary_carpet.stokes" in GRAPH["ciliary_carpet.carpet.carpet"]


def test_no_import_circle():
    """Every strongly connected component of the import graph is a single module, but for the
    known circles (ALLOWED_CYCLES): a component must be exactly a union of them."""
    bad = []
    for comp in _cycles(GRAPH):
        known = [a for a in ALLOWED_CYCLES if a <= comp]
        if not known or frozenset().union(*known) != comp:
            bad.append(sorted(comp))
    assert not bad, "import circles:\n" + "\n".join(" <-> ".join(c) for c in bad)


def test_no_private_imports_across_modules():
    bad = sorted(set(PRIVATE) - ALLOWED_PRIVATE)
    assert not bad, "\n".join(bad)


def _layer(module: str) -> int:
    """The index in LAYERS of the innermost layer that holds ``module``."""
    held = [i for i, name in enumerate(LAYERS) if module == name or module.startswith(name + ".")]
    assert held, f"{module} is in no layer: add its package to LAYERS"
    return max(held, key=lambda i: len(LAYERS[i]))


def _upward() -> set[str]:
    return {f"{m} -> {d}" for m, deps in GRAPH.items() for d in deps if _layer(d) > _layer(m)}


def test_layers_import_only_downwards():
    """No module imports one of a layer above its own (LAYERS), but for the known faults."""
    bad = sorted(_upward() - ALLOWED_UPWARD)
    assert not bad, "imports up the layers:\n" + "\n".join(bad)


def test_the_layer_check_can_fail():
    assert _layer("cilia_runtime.threads") < _layer("single_cilium.cycle") < _layer("ciliary_carpet.stokes.kernel")
    assert _layer("ciliary_carpet.scenes.scene") > _layer("ciliary_carpet.output.plan")
    assert not any(d.split(".")[0] != "cilia_runtime" for d in
                   set().union(*(GRAPH[m] for m in MODULES if m.startswith("cilia_runtime"))))


def test_known_faults_still_exist():
    """A known fault that is gone must leave its allow-list (so that the lists empty)."""
    comps = _cycles(GRAPH)
    gone = [sorted(a) for a in ALLOWED_CYCLES if not any(a <= c for c in comps)]
    gone += sorted(ALLOWED_PRIVATE - set(PRIVATE))
    gone += sorted(ALLOWED_UPWARD - _upward())
    assert not gone, f"these are fixed: remove them from ALLOWED_CYCLES / ALLOWED_PRIVATE: {gone}"


def test_the_flow_sums_layer():
    """ciliary_carpet.stokes: kernel at the bottom (it imports nothing of the package), the CUDA
    backend below the registry, and the rest of the package importing the layer through its
    front door (ciliary_carpet.stokes) only."""
    stokes = {m for m in MODULES if m.startswith("ciliary_carpet.stokes.")}
    assert not GRAPH["ciliary_carpet.stokes.kernel"]
    assert "ciliary_carpet.stokes.cuda" not in {m for s in ("kernel", "backend", "direct", "fmm")
                                                for m in GRAPH[f"ciliary_carpet.stokes.{s}"]}
    for m, deps in GRAPH.items():
        if m.startswith("ciliary_carpet.") and not m.startswith("ciliary_carpet.stokes"):
            assert not deps & stokes, f"{m} imports {sorted(deps & stokes)}: use ciliary_carpet.stokes"
