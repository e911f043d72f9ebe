"""The import rule of docs/ARCHITECTURE.md: cli -> flows -> tasks -> core, storage beside tasks, and no cycles.

Every import is read from the source (module level and inside functions alike), so a lazy import
cannot hide an edge that breaks the rule or closes a cycle.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
#: the repository's top-level folders, installed as subpackages of neuralslicer (pyproject.toml)
OUTER = ("storage", "tasks", "flows", "deployments", "cli")
LAYERS = ("neuralslicer", *OUTER)
# what each first-party layer may import (besides the standard library and third-party packages)
ALLOWED = {
    "neuralslicer": {"neuralslicer"},
    "storage": {"storage", "neuralslicer"},
    "tasks": {"tasks", "storage", "neuralslicer"},
    "flows": {"flows", "tasks", "storage", "neuralslicer"},
    "deployments": {"deployments", "flows", "storage", "neuralslicer"},
    "cli": {"cli", "flows", "storage", "neuralslicer"},
}
# third-party packages of the workflow engine: only outside the core and the store
ENGINE = ("prefect", "prefect_dask", "distributed", "dask")


def layer_of(module: str) -> str:
    """The layer of a dotted module name: ``neuralslicer.flows.slice`` is in flows, ``neuralslicer.cage`` in the core,
    anything else its top-level name."""
    parts = module.split(".")
    if parts[0] == "neuralslicer" and len(parts) > 1 and parts[1] in OUTER:
        return parts[1]
    return parts[0]


def module_name(path: Path) -> str:
    """Dotted module name of a source file, as installed (``cli/main.py`` is ``neuralslicer.cli.main``)."""
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    if parts[0] in OUTER:
        parts.insert(0, "neuralslicer")
    return ".".join(parts)


def imports_of(path: Path, package: list[str]) -> list[tuple[str, int]]:
    """Every module a file imports (absolute dotted names) with its line, relative imports resolved
    against ``package``; ``from pkg import name`` gives ``pkg.name`` (a submodule, if it is one)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    out: list[tuple[str, int]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package[:len(package) - node.level + 1] + ([base] if base else []))
            out += [(f"{base}.{a.name}", node.lineno) for a in node.names]
    return out


def package_of(path: Path) -> list[str]:
    """The package a first-party file's relative imports start from."""
    name = module_name(path).split(".")
    return name if path.name == "__init__.py" else name[:-1]


def sources() -> dict[str, Path]:
    """First-party modules by name."""
    files = [p for layer in LAYERS for p in (REPO / layer).rglob("*.py")]
    return {module_name(p): p for p in files if "examples" not in p.parts}


def test_layers_import_one_way() -> None:
    """No layer imports one above it; the core and the store never import the workflow engine."""
    bad = []
    for name, path in sources().items():
        layer = layer_of(name)
        for target, line in imports_of(path, package_of(path)):
            top = layer_of(target)
            if top in LAYERS and top not in ALLOWED[layer]:
                bad.append(f"{path.relative_to(REPO)}:{line} imports {target}")
            if layer in ("neuralslicer", "storage") and top in ENGINE:
                bad.append(f"{path.relative_to(REPO)}:{line} imports {target} (the workflow engine)")
    assert not bad, "imports against the rule:\n" + "\n".join(bad)


def import_graph() -> dict[str, set[str]]:
    """Edges between first-party modules (a package's __init__ counts as the package)."""
    mods = sources()
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for name, path in mods.items():
        for target, _ in imports_of(path, package_of(path)):
            if target not in mods:  # `from pkg import name`: an edge to the package
                target = target.rsplit(".", 1)[0]
            if target in mods and target != name:
                graph[name].add(target)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
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

    for v in graph:
        if v not in index:
            visit(v)
    return out


def test_no_import_cycles() -> None:
    """No two first-party modules import each other, directly or around a loop (lazy imports included)."""
    found = cycles(import_graph())
    assert not found, "import cycles: " + "; ".join(" <-> ".join(c) for c in found)


def test_rule_check_catches_a_violation(tmp_path: Path) -> None:
    """The scan sees an import inside a function body, resolves a relative one, and finds a cycle."""
    f = tmp_path / "m.py"
    f.write_text("import os\n\ndef f():\n    from neuralslicer.storage import ArtifactStore\n    from ..flows import slice\n")
    assert imports_of(f, ["neuralslicer", "motion"]) == [
        ("os", 1), ("neuralslicer.storage.ArtifactStore", 4), ("neuralslicer.flows.slice", 5)]
    assert layer_of("neuralslicer.storage.ArtifactStore") == "storage" and layer_of("neuralslicer.cage") == "neuralslicer"
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


@pytest.mark.parametrize("layer", ["neuralslicer", "neuralslicer.storage"])
def test_core_runs_without_prefect(layer: str) -> None:
    """Importing the core (or the store) with Prefect made unimportable still works (the core: its own folder, not
    the outer layers installed beside it)."""
    import subprocess
    import sys

    skip = [f"neuralslicer.{o}" for o in OUTER] if layer == "neuralslicer" else []
    code = ("import sys; sys.modules['prefect'] = None\n"
            f"import importlib, pkgutil, {layer}\n"
            f"for m in pkgutil.walk_packages({layer}.__path__[:1], '{layer}.'):\n"
            f"    if '.examples' not in m.name and not m.name.startswith(tuple({skip!r})):\n"
            "        importlib.import_module(m.name)\n"
            "        print(m.name)\n")
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    imported = done.stdout.split()
    assert len(imported) > (40 if layer == "neuralslicer" else 2) and not any(m.startswith(tuple(skip)) for m in imported)


def test_prefect_is_used_through_its_public_settings() -> None:
    """No source file sets Prefect's private ``PREFECT__...`` settings (they change without notice between releases;
    the local server gets its ephemeral mode from ``create_app``'s documented arguments)."""
    private = [f"{path.relative_to(REPO)}:{i}" for path in sources().values()
               for i, line in enumerate(path.read_text().splitlines(), 1) if "PREFECT__" in line]
    assert private == []
