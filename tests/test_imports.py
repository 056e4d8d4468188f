"""The import graph of the ``bimp`` package, read from the source with ``ast``: no cycles, and no import of a bimp
module inside a function unless its line says why it must wait (``# lazy: torch``, a heavy or optional dependency).

Every ``import`` and ``from ... import`` of a ``bimp.*`` module counts, at module level and inside functions alike, so
an import moved into a function cannot hide a cycle. ``from bimp.x import y`` is an edge to ``bimp.x.y`` when ``y``
is a module, else to ``bimp.x`` (its ``__init__``). The packages a module's import runs implicitly on the way to it
are left out: a package exposing its submodules (``bimp`` -> ``bimp.agents.registry``) would make every package one
cycle. Lazy ``"module:attr"`` strings (the policy and scenario tables, the commands) are not imports.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import bimp

ROOT = Path(__file__).resolve().parent.parent
# The packages of the one namespace and their folders (pyproject.toml's package-dir mapping).
PACKAGES = {"bimp": ROOT / "bimp", "bimp.envs": ROOT / "envs", "bimp.planners": ROOT / "planners",
            "bimp.agents": ROOT / "agents", "bimp.configs": ROOT / "configs"}
LAZY = "# lazy:"  # the comment that lets a function import a bimp module (a heavy or optional dependency behind it)


def modules() -> dict[str, Path]:
    """``{module name: file}`` of every module of the package."""
    found = {}
    for package, folder in PACKAGES.items():
        for path in sorted(folder.rglob("*.py")):  # subpackages too (bimp.envs.highway)
            parts = path.relative_to(folder).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            found[".".join((package, *parts))] = path
    return found


def _package(name: str, path: Path) -> str:
    return name if path.name == "__init__.py" else name.rpartition(".")[0]


def imports(name: str, path: Path, known: set[str]) -> list[tuple[str, int, bool, str]]:
    """``(imported module, line, inside a function, source line)`` for every import of a bimp module in ``path``."""
    source = path.read_text()
    lines = source.splitlines()
    tree = ast.parse(source, str(path))
    found = []

    def visit(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            local = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            targets: list[str] = []
            if isinstance(child, ast.Import):
                targets = [alias.name for alias in child.names]
            elif isinstance(child, ast.ImportFrom):
                base = child.module or ""
                if child.level:  # relative: from the module's own package up
                    parts = _package(name, path).split(".")
                    base = ".".join(parts[:len(parts) - child.level + 1] + ([base] if base else []))
                targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else base
                           for alias in child.names]
            for target in targets:
                while target and target not in known:  # `import bimp.agents.cli as c` names the module itself
                    target = target.rpartition(".")[0]
                if target and target != name:
                    text = "\n".join(lines[child.lineno - 1:child.end_lineno])
                    found.append((target, child.lineno, in_function, text))
            visit(child, local)

    visit(tree, False)
    return found


def graph() -> tuple[dict[str, set[str]], list[str]]:
    """The import graph ``{module: {modules it imports}}`` and the function-local imports without a reason."""
    files = modules()
    known = set(files)
    edges: dict[str, set[str]] = {name: set() for name in files}
    unexplained = []
    for name, path in files.items():
        for target, line, in_function, text in imports(name, path, known):
            edges[name].add(target)
            said = f"{name} (line {line}) imports {target} inside a function"
            if in_function and LAZY not in text and said not in unexplained:
                unexplained.append(said)
    return edges, unexplained


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The import cycles, one per strongly connected component of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def connect(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for nxt in sorted(edges.get(node, ())):
            if nxt not in index:
                connect(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(edges):
        if node not in index:
            connect(node)
    return found


def _path(edges: dict[str, set[str]], component: list[str]) -> str:
    """One cycle through the component, as ``a -> b -> a``, to name in the failure."""
    members, start = set(component), component[0]
    path, node, seen = [start], start, {start}
    while True:
        node = next(n for n in sorted(edges[node]) if n in members)
        path.append(node)
        if node in seen:
            return " -> ".join(path[path.index(node):])
        seen.add(node)


def test_the_package_is_read_whole():
    files = modules()
    assert Path(bimp.__file__).resolve() == files["bimp"]
    assert {"bimp.agents.evaluation.evaluate", "bimp.agents.registry", "bimp.envs.scenarios", "bimp.planners.core",
            "bimp.configs", "bimp.envs.highway.adapter"} <= set(files)


# The layers, bottom up: a module imports its own layer and those below, never one above (envs <- planners <- agents).
# agents/ itself is three: what acts (the policy table, baselines, IDM, RL, the rollout), what measures it
# (agents/evaluation/), and the CLI over both. A module's layer is that of its longest matching prefix.
LAYERS = (("bimp.configs",), ("bimp.envs",), ("bimp.planners",), ("bimp.agents",), ("bimp.agents.evaluation",),
          ("bimp.agents.cli", "bimp.agents.commands"))


def _layer(module: str) -> int | None:
    matches = [(len(p), i) for i, names in enumerate(LAYERS) for p in names
               if module == p or module.startswith(p + ".")]
    return max(matches)[1] if matches else None


def test_imports_point_down_the_layers():
    """Nothing in envs/ imports a planner or an agent, nothing in planners/ an agent (DESIGN section 8): a user of
    the envs alone never loads JAX or torch through them. Nothing that acts imports the evaluation tools, and no
    library module imports the CLI."""
    upward = [f"{m} imports {t}" for m, targets in graph()[0].items() for t in targets
              if _layer(m) is not None and _layer(t) is not None and _layer(t) > _layer(m)]
    assert not upward, upward


def test_the_layers_are_read_as_meant():
    assert [_layer(m) for m in ("bimp.agents.rollout", "bimp.agents.evaluation.records", "bimp.agents.commands.tune",
                                "bimp.agents.cli", "bimp.planners.core", "bimp")] == [3, 4, 5, 5, 2, None]


def test_the_package_has_no_import_cycle():
    edges = graph()[0]
    found = [_path(edges, component) for component in cycles(edges)]
    assert not found, "import cycles:\n  " + "\n  ".join(found)


def test_no_function_hides_an_import_of_a_bimp_module():
    unexplained = graph()[1]
    assert not unexplained, (f"import these at the top of the module, or say why they must wait with `{LAZY} REASON` "
                             "on the import's line (a heavy or optional dependency):\n  " + "\n  ".join(unexplained))


@pytest.mark.parametrize("source, cycle", [
    ({"bimp.a": "from bimp import b\n", "bimp.b": "def f():\n    import bimp.a\n"}, "bimp.a -> bimp.b -> bimp.a"),
    ({"bimp.a": "from bimp.b import thing\n", "bimp.b": "from bimp.c import x\n", "bimp.c": "import bimp.a\n"},
     "bimp.a -> bimp.b -> bimp.c -> bimp.a"),
])
def test_a_cycle_is_found_and_named_even_through_a_function(tmp_path, monkeypatch, source, cycle):
    folder = tmp_path / "bimp"
    folder.mkdir()
    (folder / "__init__.py").write_text("")
    for name, text in source.items():
        (folder / f"{name.split('.')[-1]}.py").write_text(text)
    monkeypatch.setitem(globals(), "PACKAGES", {"bimp": folder})
    edges, unexplained = graph()
    assert [_path(edges, c) for c in cycles(edges)] == [cycle]
    assert unexplained == (["bimp.b (line 2) imports bimp.a inside a function"] if "def f" in source["bimp.b"] else [])
