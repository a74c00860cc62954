#!/usr/bin/env bash
# The run command (README): installs missing system packages, builds b2dr in release mode and runs the main job
# on the built-in default: the closed loop WITH RENDERED CAMERAS on the built-in synthetic town. The trained image
# planner models/e2e-planner (docs/e2e_planner.md) reads the front camera, served by its numpy forward
# (`python -m b2dr_ref.e2e_numpy serve`: no torch; numpy and safetensors in a small cached virtualenv,
# tools/ensure-planner-venv.sh); other traffic reacts (IDM); the nuPlan closed-loop score grades the drive. The
# same run under each renderer (the generative renderer b2dr with the built-in model, its masks-only baseline,
# log replay, the world's exact ground truth) gives the paper's comparison table. Outputs go to out/ (or the
# folder given as $1).
set -euo pipefail
cd "$(dirname "$0")/.."
. tools/ensure-deps.sh
. tools/ensure-planner-venv.sh
out="${1:-out}"
cargo build --release --quiet
b="${CARGO_TARGET_DIR:-target}/release/b2dr"
$b info
# 15 s of driving (30 planner steps at 2 Hz) with the three front cameras: long enough for the renderers to change
# the trained planner's drive (6 s was not: b2dr and masks-only tied), short enough for ~10 minutes on 2 cores
# (lavapipe); drop --cameras for the full 6-camera run.
# the planner command (run from python/, where b2dr_ref and b2dr_planner live); the pixel-rule planner
# examples/image_planner.py stays as an example (`cmd:python3 examples/image_planner.py`)
planner="cmd:cd $(printf %q "$PWD/python") && exec $(printf %q "$B2DR_PLANNER_PY") -m b2dr_ref.e2e_numpy serve --weights $(printf %q "$PWD/models/e2e-planner")"
$b run --scenario builtin:town --planner "$planner" --agents idm \
  --renderer b2dr,b2dr-noref-noprev,log-replay,groundtruth \
  --cameras CAM_FRONT_LEFT,CAM_FRONT,CAM_FRONT_RIGHT --steps 150 --out "$out/run"
echo
echo "comparison table (score per metric, per renderer): $out/run/comparison.md"
echo "the generative renderer's run (frames, mosaics, GIF, trace, metrics with per-stage timing): $out/run/b2dr/town-0/"
echo "side-by-side front camera per renderer: $out/run/side_by_side_town-0_*.png"
