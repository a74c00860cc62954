#!/usr/bin/env bash
# The test command (README, .ci/run): installs missing system packages, then runs the whole suite with the
# Khronos validation layer enabled (tests fail on any validation error).
set -euo pipefail
cd "$(dirname "$0")/.."
. tools/ensure-deps.sh
export B2DR_VALIDATION=1
# Mesa 22.3's lavapipe uses one worker thread per core by default; nothing to tune for correctness.
cargo test --all-targets --no-fail-fast "$@"
