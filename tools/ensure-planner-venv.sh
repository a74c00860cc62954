#!/usr/bin/env bash
# The Python of the README run's planner (models/e2e-planner served by `python -m b2dr_ref.e2e_numpy serve`: the
# numpy forward, no torch). A fresh machine's python3 has no numpy, so a small virtualenv with numpy and
# safetensors only is created once, with pip, in ~/.cache/b2dr-planner-venv (B2DR_PLANNER_VENV overrides), and
# B2DR_PLANNER_PY names its python. Sourced by tools/run.sh; needs python3 with the venv module (Debian:
# python3-venv, installed by tools/ensure-deps.sh when root) and network on the first run.
set -euo pipefail
planner_venv="${B2DR_PLANNER_VENV:-$HOME/.cache/b2dr-planner-venv}"
if ! "$planner_venv/bin/python" -c "import numpy, safetensors" >/dev/null 2>&1; then
  echo "b2dr: setting up the planner's Python environment in $planner_venv (numpy, safetensors; once)" >&2
  mkdir -p "$(dirname "$planner_venv")"
  [ -x "$planner_venv/bin/python" ] || python3 -m venv "$planner_venv" || {
    echo "b2dr: python3 -m venv failed: install python3-venv (Debian) or set B2DR_PLANNER_VENV to a virtualenv with numpy and safetensors" >&2
    exit 1
  }
  "$planner_venv/bin/pip" install -q --no-cache-dir numpy safetensors
fi
B2DR_PLANNER_PY="$planner_venv/bin/python"
export B2DR_PLANNER_PY
