#!/usr/bin/env bash
# The test command (README, .ci/run): installs missing system packages, then runs the whole suite with the
# Khronos validation layer enabled (tests fail on any validation error), then the python/ tests (pytest, in a
# cached virtualenv: tools/ensure-python.sh).
set -euo pipefail
cd "$(dirname "$0")/.."
. tools/ensure-deps.sh
export B2DR_VALIDATION=1
# Mesa 22.3's lavapipe uses one worker thread per core by default; nothing to tune for correctness.
# every test's scratch folders (std::env::temp_dir(), Python's tempfile) go to one folder removed at the end, so
# repeated runs do not fill /tmp (a failing run keeps it for inspection: its path is printed)
scratch=$(mktemp -d "${TMPDIR:-/tmp}/b2dr-test.XXXXXX")
export TMPDIR="$scratch"
# the build and the Python environment need disk: about 2.4 GB for target/debug (profile.dev keeps line tables only)
# and about 6 GB for the virtualenv (PyPI's torch carries its CUDA libraries) on the first run. Say what is free
# up front, so a full disk reads as such rather than as a compiler crash.
free_mb=$(df -Pm . | awk 'NR == 2 {print $4}')
echo "b2dr: ${free_mb} MB free on $(df -P . | awk 'NR == 2 {print $6}') for target/ (and the Python environment)" >&2
[ "${free_mb:-0}" -ge 4096 ] || echo "b2dr: warning: under 4 GB free; the build may run out of disk" >&2
# no incremental cache: a one-shot test build does not reuse it, and it adds ~1.4 GB (set CARGO_INCREMENTAL=1 to keep it)
export CARGO_INCREMENTAL="${CARGO_INCREMENTAL:-0}"
status=0
cargo test --all-targets --no-fail-fast "$@" || status=$?
# the Python side (reference modules, trainer, dataset reader): pytest in the cached environment
. tools/ensure-python.sh
(cd python && OMP_NUM_THREADS=1 "$B2DR_PY" -m pytest -q) || status=$?
if [ "$status" -eq 0 ]; then rm -rf "$scratch"; else echo "test scratch files kept in $scratch" >&2; fi
exit $status
