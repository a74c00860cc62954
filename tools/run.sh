#!/usr/bin/env bash
# The run command (README): installs missing system packages, builds b2dr in release mode and runs the main job
# on the built-in default: a closed-loop simulation of the built-in synthetic town (expert planner, reactive
# IDM traffic, nuPlan closed-loop score, per-step traces, bird's-eye views), then a guided sampling run of the
# built-in b2dr-tiny renderer model (PNG + EXR). Outputs go to out/ (or the folder given as $1).
set -euo pipefail
cd "$(dirname "$0")/.."
. tools/ensure-deps.sh
out="${1:-out}"
cargo build --release --quiet
b=target/release/b2dr
$b info
$b sim --scenario builtin:town --planner expert --agents idm --out "$out/sim"
$b sim --scenario builtin:town --planner cv --agents idm --out "$out/sim-cv"
$b sample --steps 20 --size 224x400 --out "$out/sample"
echo
echo "closed-loop score (expert planner, IDM agents): $out/sim/metrics.json"
echo "closed-loop score (constant-velocity planner):  $out/sim-cv/metrics.json"
echo "bird's-eye views and traces:                    $out/sim/"
echo "renderer sample (b2dr-tiny, random weights):    $out/sample/sample.png, sample.exr"
