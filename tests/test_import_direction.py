"""Imports run one way: filters <- policies <- slam_gym <- scripts and examples, never in a
circle.

Every module of the repository is parsed with :mod:`ast`; every ``import`` counts, including
those inside functions (a lazy import is still a dependency). docs/ARCHITECTURE.md, "Layers",
states the rule this test enforces.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

# its module-scoped fixtures are built once: every test of this file on one worker (pytest -n)
pytestmark = pytest.mark.xdist_group("test_import_direction")

ROOT = Path(__file__).resolve().parents[1]

LAYERS = {"filters": 0, "policies": 1, "slam_gym": 2, "scripts": 3, "examples": 3}
"""Package (or folder) -> floor; a module may import only from its own floor or below."""

PACKAGES = ("filters", "policies", "slam_gym")
"""The importable packages; ``scripts`` and ``examples`` hold files, not packages."""


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def project_modules() -> dict[str, Path]:
    """Module name -> file of every Python file under the layered folders."""
    modules: dict[str, Path] = {}
    for top in LAYERS:
        for path in sorted((ROOT / top).rglob("*.py")):
            modules[_module_name(path)] = path
    return modules


def _resolve(target: str, modules: dict[str, Path]) -> str | None:
    """The project module ``target`` names (itself, or the module holding the name), or None."""
    while target:
        if target in modules:
            return target
        target = target.rpartition(".")[0]
    return None


def imports_of(name: str, path: Path, modules: dict[str, Path]) -> list[tuple[str, int]]:
    """The project modules ``name`` imports, with the line of each import (all of them, at any
    depth: module level, inside functions, inside ``if TYPE_CHECKING``)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    is_package = path.name == "__init__.py"
    found: list[tuple[str, int]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".")
                base = base if is_package else base[:-1]
                base = base[: len(base) - (node.level - 1)]
                stem = ".".join(base + ([node.module] if node.module else []))
            else:
                stem = node.module or ""
            # ``from pkg import sub`` imports the module pkg.sub when there is one
            targets = [
                f"{stem}.{alias.name}" if f"{stem}.{alias.name}" in modules else stem
                for alias in node.names
            ]
        else:
            continue
        for target in targets:
            resolved = _resolve(target, modules)
            if resolved is not None and resolved != name:
                found.append((resolved, node.lineno))
    return found


def import_graph() -> dict[str, list[tuple[str, int]]]:
    modules = project_modules()
    return {name: imports_of(name, path, modules) for name, path in modules.items()}


def _floor(module: str) -> int:
    return LAYERS[module.split(".")[0]]


def upward_imports(graph: dict[str, list[tuple[str, int]]]) -> list[str]:
    return sorted(
        f"{source}:{line} imports {target}"
        for source, targets in graph.items()
        for target, line in targets
        if _floor(target) > _floor(source)
    )


def circles(graph: dict[str, list[tuple[str, int]]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    edges = {source: sorted({t for t, _ in targets}) for source, targets in graph.items()}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []
    counter = 0

    def visit(root: str) -> None:
        nonlocal counter
        work = [(root, iter(edges[root]))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            advanced = False
            for child in children:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(edges[child])))
                    advanced = True
                    break
                if child in on_stack:
                    low[node] = min(low[node], index[child])
            if advanced:
                continue
            work.pop()
            if work:
                parent = work[-1][0]
                low[parent] = min(low[parent], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    components.append(sorted(component))

    for module in sorted(edges):
        if module not in index:
            visit(module)
    return sorted(components)


def private_imports(modules: dict[str, Path] | None = None) -> list[str]:
    """Every ``from <project module> import _name`` of another module (a private name reached
    across modules: it should be made public instead)."""
    modules = project_modules() if modules is None else modules
    found = []
    for name, path in modules.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in ast.walk(tree):
            if (isinstance(node, ast.ImportFrom) and node.module
                    and _resolve(node.module, modules) not in (None, name)):
                found += [f"{name}:{node.lineno} imports {node.module}.{alias.name}"
                          for alias in node.names
                          if alias.name.startswith("_") and not alias.name.startswith("__")]
    return sorted(found)


@pytest.fixture(scope="module")
def graph() -> dict[str, list[tuple[str, int]]]:
    return import_graph()


def test_the_graph_sees_the_project(graph):
    # the parser must find the imports it is meant to judge, lazy ones among them
    assert len(graph) > 100
    n_imports = sum(len(targets) for targets in graph.values())
    assert n_imports > 300
    assert any(t.startswith("filters.") for t, _ in graph["slam_gym.world"])
    # an import inside a function (make_job_stream's) is seen
    assert "slam_gym.world" in {t for t, _ in graph["slam_gym.evaluation.core"]}


def test_no_upward_import(graph):
    assert upward_imports(graph) == []


def test_no_circle_between_modules(graph):
    assert circles(graph) == []


def test_no_private_name_is_imported_across_modules():
    assert private_imports() == []


def test_the_checks_catch_what_they_are_meant_to():
    fake = {
        "filters.a": [("policies.b", 3)],
        "policies.b": [("slam_gym.c", 4)],
        "slam_gym.c": [("filters.a", 5), ("slam_gym.d", 6)],
        "slam_gym.d": [("slam_gym.c", 7)],
    }
    assert upward_imports(fake) == [
        "filters.a:3 imports policies.b",
        "policies.b:4 imports slam_gym.c",
    ]
    assert circles(fake) == [["filters.a", "policies.b", "slam_gym.c", "slam_gym.d"]]


def test_the_env_runs_without_importing_scipy_stats_or_optimize():
    """A plain ``gym.make`` episode imports neither scipy.stats nor scipy.optimize: the two cost a
    process 0.5-1 s of CPU at import (docs/PERFORMANCE.md), and the env needs neither (its
    chi-square quantiles come from ``filters.association.chi_square_quantile``; the optimisers
    that use scipy.optimize import it when they run)."""
    import os
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent("""
        import sys
        import gymnasium as gym
        import slam_gym
        env = gym.make("slam_gym:SlamGym/HybridSLAM-Light-v1")
        env.reset(seed=0)
        for _ in range(12):
            env.step([1, 1])
        print(sorted(m for m in ("scipy.stats", "scipy.optimize") if m in sys.modules))
    """)
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                          timeout=600, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip().splitlines()[-1] == "[]"
