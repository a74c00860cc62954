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
# and, on the first run only, about 6 GB for the virtualenv (PyPI's torch carries its CUDA libraries). Say what is
# free up front, so a full disk reads as such rather than as a compiler crash.
free_mb=$(df -Pm . | awk 'NR == 2 {print $4}')
need_mb=3000
[ -x "${B2DR_VENV:-$HOME/.cache/b2dr-venv}/bin/python" ] || need_mb=$((need_mb + 6500))
echo "b2dr: ${free_mb} MB free on $(df -P . | awk 'NR == 2 {print $6}'); this run needs about ${need_mb} MB" >&2
[ "${free_mb:-0}" -ge "$need_mb" ] || echo "b2dr: warning: less free disk than that; the run may fail with 'No space left on device'" >&2
# no incremental cache (it was 1.4 GB of the old 12 GB build, and CI builds once); developers who rerun after small
# edits can keep it with CARGO_INCREMENTAL=1
export CARGO_INCREMENTAL="${CARGO_INCREMENTAL:-0}"
status=0
cargo test --all-targets --no-fail-fast "$@" || status=$?
# the Python side (reference modules, trainer, dataset reader): pytest in the cached environment
. tools/ensure-python.sh
(cd python && OMP_NUM_THREADS=1 "$B2DR_PY" -m pytest -q) || status=$?
if [ "$status" -eq 0 ]; then rm -rf "$scratch"; else echo "test scratch files kept in $scratch" >&2; fi
exit $status
