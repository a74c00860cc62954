#!/usr/bin/env bash
# The Python environment of python/ (PyTorch reference modules, trainer, their pytest suite): a virtualenv at
# ~/.cache/b2dr-venv (override with B2DR_VENV), created and filled from PyPI on first use, reused afterwards.
# Sourced by tools/test.sh; sets B2DR_PY to its interpreter. ray (the scale-out driver, python/b2dr_ref/ray_driver.py),
# pyyaml and kubernetes (the manifest check of examples/k8s_indexed_job.yaml) serve the scale-out tests; accelerate,
# transformers (CLIP) and tensorboard (~20 MB with grpcio) the sd15 training recipe (python/b2dr_ref/training).
set -euo pipefail
venv="${B2DR_VENV:-$HOME/.cache/b2dr-venv}"
if ! "$venv/bin/python" -c "import torch, diffusers, safetensors, numpy, pytest, PIL, ray, yaml, kubernetes, accelerate, transformers, tensorboard" >/dev/null 2>&1; then
  echo "b2dr: setting up the Python environment in $venv (torch, diffusers, ray; once)" >&2
  mkdir -p "$(dirname "$venv")"
  [ -x "$venv/bin/python" ] || python3 -m venv "$venv"
  "$venv/bin/pip" install -q --no-cache-dir --upgrade pip >/dev/null
  # --no-cache-dir: the wheels (torch with its CUDA libraries is several GB) would otherwise be kept twice
  "$venv/bin/pip" install -q --no-cache-dir torch diffusers safetensors numpy pytest pillow ray pyyaml kubernetes \
    accelerate transformers tensorboard
fi
B2DR_PY="$venv/bin/python"
export B2DR_PY
