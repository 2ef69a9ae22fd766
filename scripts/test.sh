#!/usr/bin/env bash
# The test command: set up .venv if needed, lint, run the whole test suite.
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/setup.sh"
.venv/bin/ruff check .
.venv/bin/python -m pytest -q "$@"
