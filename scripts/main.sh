#!/usr/bin/env bash
# The main job: set up .venv if needed, then run the project's headline command.
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/setup.sh"
.venv/bin/slam-gym simulate --scenario brooks-bailey --clutter-level 2 --seed 0 --out out/main "$@"
