"""The docs describe the repository (issue 37 item 6): no reference to a design file outside it,
and no path to a file or folder of the repository that does not exist."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TOP = ("slam_gym", "filters", "policies", "scripts", "docs", "examples", "tests", "benchmarks",
       ".ci")
_TOPS = "|".join(re.escape(t) for t in TOP)
PATH = re.compile(r"(?<![\w./-])((?:" + _TOPS + r")/[\w./<>{},*-]*[\w*>}])")
"""A path from the repository's root, as docs and docstrings write it."""

OUTSIDE = re.compile(r"DESIGN\.md|DESIGN (?:section )?\d|DESIGN \"")


def tracked_text_files() -> list[Path]:
    names = subprocess.run(["git", "ls-files", "*.md", "*.py", "*.sh", ".ci/*"], cwd=ROOT,
                           capture_output=True, text=True, check=True).stdout.split()
    return [ROOT / n for n in names if n != "DEVELOPERS.md"]


def missing_paths(text: str) -> list[str]:
    """The repository paths ``text`` names that do not exist (patterns with ``<...>``, ``{...}``
    or ``*`` must match something)."""
    missing = []
    for match in PATH.finditer(text):
        path = match.group(1).rstrip(".")
        while path[-1] in ">}" and {">": "<", "}": "{"}[path[-1]] not in path:
            path = path[:-1]  # the end of a <...> or {...} around the path
        if re.search(r"[<{*]", path):
            pattern = re.sub(r"<[^>]*>|\{[^}]*\}", "*", path)
            if not list(ROOT.glob(pattern)):
                missing.append(path)
        elif not (ROOT / path).exists():
            missing.append(path)
    return missing


def test_no_file_cites_the_design_outside_the_repository():
    found = [f"{p.relative_to(ROOT)}:{i}" for p in tracked_text_files()
             for i, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1)
             if OUTSIDE.search(line) and p.name != "test_docs.py"]
    assert found == []


def test_docs_and_docstrings_name_only_files_that_exist():
    docs = [p for p in tracked_text_files() if p.name != "test_docs.py"]
    found = {str(p.relative_to(ROOT)): missing_paths(p.read_text(encoding="utf-8"))
             for p in docs}
    assert {k: v for k, v in found.items() if v} == {}


def test_the_path_check_finds_a_missing_module():
    assert missing_paths("`slam_gym/runner.py` plays a stream; see slam_gym/world.py.") == [
        "slam_gym/runner.py"]
    assert missing_paths("hyper-parameters in `slam_gym/training/hyperparams/<algo>.yml`") == []
