#!/usr/bin/env bash
# The test command (README, .ci/run): installs missing system packages, then runs the whole suite with the
# Khronos validation layer enabled (tests fail on any validation error) on the system's Vulkan driver, then the
# op, model-golden and render tests again on a second driver, Mesa 25 lavapipe (tools/ensure-mesa25.sh: unpacked
# from bookworm-backports into ~/.cache/b2dr-mesa25, selected per run with VK_ICD_FILENAMES), then the python/
# tests (pytest, in a cached virtualenv: tools/ensure-python.sh). B2DR_MESA25=0 skips the second driver's pass
# (the log says so); without it, a failed download of the driver fails the run.
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
# the second driver, fetched (once; cached) before the long build so a download failure shows up first
. tools/ensure-mesa25.sh
mesa25=ok
if [ "${B2DR_MESA25:-1}" = 0 ]; then
  mesa25=skip
  echo "b2dr: B2DR_MESA25=0: the Mesa 25 pass is skipped" >&2
elif ! b2dr_mesa25; then
  mesa25=failed
  status=1
  echo "b2dr: FAILED: the Mesa 25 driver could not be set up; its pass is skipped and the run fails (B2DR_MESA25=0 skips it on purpose)" >&2
fi
# which driver a pass ran on: `b2dr info`'s device and driver lines (driverName: driverInfo, and whether f16
# operations round to f16)
bin="${CARGO_TARGET_DIR:-target}/debug/b2dr"
driver_line() {
  if [ -x "$bin" ]; then
    "$bin" info 2>&1 | grep -E '^chosen:|^  driver:|^  f16 arithmetic:|^  f32\(f16' | sed "s/^ */b2dr: [$1] /" >&2 || true
  fi
}
cargo test --all-targets --no-fail-fast "$@" || status=$?
driver_line "system driver"
# the op, model-golden and render tests (and the f16 rows and rollouts of `bench trade`, the engine's own tests)
# on Mesa 25, same build, same validation layer: VK_ICD_FILENAMES (VK_DRIVER_FILES, its newer name) makes the
# loader see that driver only; LD_LIBRARY_PATH finds the newer libdrm it was built against
if [ "$mesa25" = ok ]; then
  mesa25_tests=(ops_attention ops_attention_naive ops_conv2d ops_elementwise ops_image ops_matmul ops_norm
    ops_softmax nn_golden nn_b2dr_golden nn_pipeline sampling_loop_golden render_job eval_render world_render
    bench_trade vk_engine)
  start=$(date +%s)
  (
    export VK_ICD_FILENAMES="$B2DR_MESA25_ICD" VK_DRIVER_FILES="$B2DR_MESA25_ICD"
    export LD_LIBRARY_PATH="$B2DR_MESA25_LIBS${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
    echo "b2dr: second pass on Mesa $B2DR_MESA25_VERSION lavapipe ($B2DR_MESA25_ICD): ${mesa25_tests[*]}" >&2
    driver_line "Mesa 25"
    cargo test --no-fail-fast $(printf -- '--test %s ' "${mesa25_tests[@]}") "$@"
  ) || status=$?
  echo "b2dr: the Mesa 25 pass took $(($(date +%s) - start)) s" >&2
fi
# the Python side (reference modules, trainer, dataset reader): pytest in the cached environment
. tools/ensure-python.sh
(cd python && OMP_NUM_THREADS=1 "$B2DR_PY" -m pytest -q) || status=$?
if [ "$status" -eq 0 ]; then rm -rf "$scratch"; else echo "test scratch files kept in $scratch" >&2; fi
exit $status
