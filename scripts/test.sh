#!/usr/bin/env bash
# The test command: set up .venv if needed, lint, run the whole test suite.
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/setup.sh"
.venv/bin/ruff check .
# across the cores (pytest-xdist; tests that start a local Ray instance share one worker)
.venv/bin/python -m pytest -q -n auto --dist loadgroup "$@"
