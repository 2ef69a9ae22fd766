"""README and the examples use only public names (issue 37 item 5).

A name is public when it is in the ``__all__`` of a public module: ``slam_gym``,
``slam_gym.evaluation``, ``policies`` or ``filters``; every other module path of the project is
internal. The examples are parsed with ``ast`` (their imports, and every ``module.name`` they
read), README's Python blocks likewise, and every dotted project name in README's text and the
examples' docstrings is checked too.
"""

from __future__ import annotations

import ast
import importlib
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PUBLIC_MODULES = ("slam_gym", "slam_gym.evaluation", "policies", "filters")
PROJECT = ("slam_gym", "policies", "filters")
NOT_PYTHON = {"slam_gym.policies": "the entry-point group of policy plug-ins"}
"""Dotted names in the text that are not Python names."""

DOTTED = re.compile(r"\b(?:slam_gym|policies|filters)(?:\.[A-Za-z_][A-Za-z0-9_]*)+")
EXAMPLES = sorted((ROOT / "examples").glob("*.py"))


def public_names(module: str) -> set[str]:
    return set(importlib.import_module(module).__all__)


def _is_project(module: str) -> bool:
    return module.split(".")[0] in PROJECT


def problems_in_code(source: str, where: str) -> list[str]:
    """Every non-public project name ``source`` imports or reads off a project module."""
    found = []
    tree = ast.parse(source)
    aliases: dict[str, str] = {}  # local name -> project module imported whole
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and _is_project(node.module):
            if node.module not in PUBLIC_MODULES:
                found.append(f"{where}:{node.lineno}: from {node.module} (an internal module)")
                continue
            for alias in node.names:
                if alias.name not in public_names(node.module):
                    found.append(f"{where}:{node.lineno}: {node.module}.{alias.name}")
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if not _is_project(alias.name):
                    continue
                if alias.name not in PUBLIC_MODULES:
                    found.append(f"{where}:{node.lineno}: import {alias.name} (internal)")
                aliases[alias.asname or alias.name] = alias.name
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                and node.value.id in aliases):
            module = aliases[node.value.id]
            if module in PUBLIC_MODULES and node.attr not in public_names(module):
                found.append(f"{where}:{node.lineno}: {module}.{node.attr}")
    return found


def problems_in_text(text: str, where: str) -> list[str]:
    """Every dotted project name in ``text`` that is neither a public module nor a public
    module's public name."""
    found = []
    for match in DOTTED.finditer(text):
        dotted = match.group(0)
        if dotted in NOT_PYTHON or dotted in PUBLIC_MODULES:
            continue
        module, _, name = dotted.rpartition(".")
        if module not in PUBLIC_MODULES or name not in public_names(module):
            line = text.count("\n", 0, match.start()) + 1
            found.append(f"{where}:{line}: {dotted}")
    return found


def readme_python_blocks() -> list[str]:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    return re.findall(r"```python\n(.*?)```", text, flags=re.S)


def test_the_public_modules_list_what_they_export():
    for module in PUBLIC_MODULES:
        names = public_names(module)
        assert names, module
        mod = importlib.import_module(module)
        missing = [n for n in names if not hasattr(mod, n)]
        assert missing == [], (module, missing)


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda p: p.name)
def test_the_examples_use_only_public_names(path):
    source = path.read_text(encoding="utf-8")
    docstring = ast.get_docstring(ast.parse(source)) or ""
    assert problems_in_code(source, path.name) == []
    assert problems_in_text(docstring, path.name) == []


def test_the_readme_uses_only_public_names():
    blocks = readme_python_blocks()
    assert blocks  # the usage example is there to check
    for i, block in enumerate(blocks):
        assert problems_in_code(block, f"README block {i}") == []
    assert problems_in_text((ROOT / "README.md").read_text(encoding="utf-8"), "README") == []


def test_the_checks_catch_internal_names():
    code = ("import policies\nfrom slam_gym.envs.wrappers import DiscreteActions\n"
            "from slam_gym import HybridSLAMEnv, Episode\npolicies.base\n")
    assert problems_in_code(code, "x") == [
        "x:2: from slam_gym.envs.wrappers (an internal module)",
        "x:3: slam_gym.Episode",
        "x:4: policies.base",
    ]
    assert problems_in_text("see `slam_gym.training.run.train_run` and slam_gym.benchmark",
                            "t") == ["t:1: slam_gym.training.run.train_run"]
