#!/usr/bin/env bash
# The main job: set up .venv if needed, then the quick benchmark on the default scenario
# (brooks-bailey, clutter levels 0-3; fixed-10s, esdf-innovation, fixed-10s-optimise and the
# shipped learned policy, with dead reckoning as a baseline; 3 seeds, 500 particles): prints the
# table, writes results, summary and plots into out/main.
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/setup.sh"
.venv/bin/slam-gym benchmark --quick --out out/main "$@"
