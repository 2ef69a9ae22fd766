#!/usr/bin/env bash
# Create .venv (Python >= 3.11) and install slam-gym with its test extras, once per change of
# pyproject.toml / constraints.txt. Sourced by scripts/main.sh and scripts/test.sh.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
python_bin="${PYTHON:-}"
if [ -z "$python_bin" ]; then
  for candidate in python3.11 python3.12 python3.13 python3; do
    if command -v "$candidate" >/dev/null 2>&1; then python_bin="$candidate"; break; fi
  done
fi
if [ -z "$python_bin" ] || ! "$python_bin" -c 'import sys; sys.exit(sys.version_info < (3, 11))'; then
  echo "slam-gym needs Python >= 3.11 (set PYTHON=/path/to/python3.11)" >&2
  exit 1
fi
if [ ! -x .venv/bin/python ]; then
  "$python_bin" -m venv .venv
fi
stamp=".venv/.slam-gym-installed"
want="$(cat pyproject.toml constraints.txt | sha256sum | cut -d' ' -f1)"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  echo "installing slam-gym and its dependencies into .venv (first run only) ..." >&2
  .venv/bin/python -m pip install --quiet --upgrade pip
  # torch first, pinned to the CPU build, then everything else under the same constraint
  .venv/bin/python -m pip install --quiet -c constraints.txt "torch==2.13.0"
  # setuptools announces every editable install ("Editable installation. Please be careful
  # with folders in your working directory with the same name as your package ..."): a notice,
  # not a problem here (the packages are those folders), so it is filtered by its text alone
  PYTHONWARNINGS="ignore:Editable installation:UserWarning" \
    .venv/bin/python -m pip install --quiet -c constraints.txt -e ".[test,ray,contrib]"
  # compile the numba kernels now (numba caches them in __pycache__), not in the first env reset
  # of the first process (~8 s): a few decisions of each back-end, fusing and optimising
  .venv/bin/python -c 'import numpy as np; from slam_gym.envs.hybrid_slam import HybridSLAMEnv
for back_end in ("ekf", "relative"):
    env = HybridSLAMEnv(n_particles=10, n_steps=120, back_end=back_end)
    env.reset(seed=0)
    for _ in range(5):
        env.step(np.array([1, 1]))'
  echo "$want" > "$stamp"
fi
