"""Import a script of ``scripts/`` as a module, so a test calls the code the script runs.

The scripts are not a package; pytest's ``pythonpath`` setting (pyproject.toml) puts this
directory on the path, so every test imports it as ``from script_loader import load_script``.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


def load_script(relative: str) -> ModuleType:
    """The script ``scripts/<relative>`` (e.g. ``"results/gap_closed.py"``), executed as a module
    named after its file and registered in ``sys.modules`` (a dataclass in it looks its module up
    there)."""
    path = SCRIPTS / relative
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[path.stem] = module
    spec.loader.exec_module(module)
    return module
