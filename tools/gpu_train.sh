#!/usr/bin/env bash
# Train b2dr-nano further on a CUDA machine in ONE call (docs/training.md "On a GPU in one device call").
#
#   bash tools/gpu_train.sh prepare   # here (network for pip download): .gpu/b2dr (stripped release binary),
#                                     # .gpu/*.whl (diffusers + importlib_metadata: the GPU image has torch, not them)
#   bash tools/gpu_train.sh run       # there, from the repository root, with .gpu carried: exports the training
#                                     # data, encodes it once, times real steps, sizes the schedule to TRAIN_S
#                                     # seconds, trains, exports; writes $OUT/gpu_run.tar and $OUT/gpu_train.log
#
# Settings (environment): TRAIN_S (300: seconds of training steps), BATCH (128), LR (2e-4), WARMUP (200), INIT
# (models/b2dr-nano: the package to continue from), CONFIG (nano; nano-z16-g4 for the 16-channel L2-VAE design of
# issue #32, whose VAE is frozen and taken from VAE), VAE (default: INIT/vae when CONFIG is not nano), DEVICE (cuda; cpu for a dry run), SCENARIOS (default: the 36
# training scenarios of the committed model), SAMPLES (12 per scenario), B2DR (.gpu/b2dr), PY (python3), THREADS
# (CPU threads; default all cores), WORK.
set -euo pipefail
cd "$(dirname "$0")/.."
root=$(pwd)

prepare() {
    cargo build --release --quiet
    mkdir -p .gpu
    strip -o .gpu/b2dr target/release/b2dr
    local py=${PY:-$HOME/.cache/b2dr-venv/bin/python}
    local v
    v=$("$py" -c "import diffusers; print(diffusers.__version__)")
    rm -f .gpu/*.whl
    "$py" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
        --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 -d .gpu \
        "diffusers==$v" importlib_metadata
    du -sh .gpu
    echo "carry .gpu (it is git-ignored): run(command=\"bash tools/gpu_train.sh run\", carry=[\".gpu\"])"
}

run() {
    : "${OUT:?OUT (the folder whose files come back) must be set}"
    local dev=${DEVICE:-cuda} train_s=${TRAIN_S:-300} batch=${BATCH:-128} lr=${LR:-2e-4} warmup=${WARMUP:-200}
    local init=${INIT:-models/b2dr-nano} samples=${SAMPLES:-12} b2dr=${B2DR:-.gpu/b2dr} py=${PY:-python3}
    local work=${WORK:-/tmp/b2dr-gpu} config=${CONFIG:-nano} vae=${VAE:-}
    init=$(cd "$init" && pwd)
    # a design other than nano trains its diffusion stage on a frozen VAE of its own latent width (the package's)
    if [ "$config" != nano ] && [ -z "$vae" ]; then vae=$init/vae; fi
    if [ -n "$vae" ]; then vae=$(cd "$vae" && pwd); fi
    b2dr=$(cd "$(dirname "$b2dr")" && pwd)/$(basename "$b2dr")
    rm -rf "$work" && mkdir -p "$work"
    exec > >(tee "$OUT/gpu_train.log") 2>&1
    local t0=$SECONDS
    if compgen -G ".gpu/*.whl" >/dev/null; then
        "$py" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$work/site" .gpu/*.whl
        export PYTHONPATH="$work/site${PYTHONPATH:+:$PYTHONPATH}"
    fi
    "$py" -c "import torch, diffusers; print('torch', torch.__version__, 'diffusers', diffusers.__version__, \
'cuda', torch.cuda.is_available(), torch.cuda.get_device_name(0) if torch.cuda.is_available() else '')"
    if [ "$dev" = cuda ]; then "$py" -c "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)" \
        || { echo "DEVICE=cuda but torch sees no GPU" >&2; exit 1; }; fi
    local s=${SCENARIOS:-}
    if [ -z "$s" ]; then
        for l in town cross tjunction straight curve multilane; do
            for k in 0 1 2 3; do s="$s builtin:$l:$k"; done
            for k in 0 1; do s="$s builtin:$l:$k:60"; done
        done
    fi
    # shellcheck disable=SC2086
    "$b2dr" export-training --scenario $s --out "$work/data" --size 112x200 --samples-per-scenario "$samples" \
        --offsets "0,0,0;0,1.5,0;0,-1.5,0;0,0,8" --seed 0 --quiet
    echo "data exported ($((SECONDS - t0)) s)"
    cd python
    local common=(--data "$work/data" --config "$config" ${vae:+--vae "$vae"} --init-from "$init" --batch "$batch" --device "$dev" --ema 0.999
        --warmup "$warmup" --lr "$lr" --prediction v_prediction --object-weight 4 --p-noprev 0.2 --log-every 100 ${THREADS:+--threads $THREADS})
    # encode the data once and time real steps (data, cache, optimizer included) in a throwaway run
    "$py" -m b2dr_ref.train "${common[@]}" --out "$work/timing" --steps 60 --precache
    local per_step steps
    per_step=$("$py" -c "import csv, statistics as st; r = list(csv.DictReader(open('$work/timing/log.csv'))); \
print(st.median(float(x['sec']) for x in r[20:]))")
    steps=$("$py" -c "print(max(100, int($train_s / $per_step)))")
    echo "timing: $per_step s per step at batch $batch -> $steps steps in $train_s s ($((SECONDS - t0)) s so far)"
    mkdir -p "$work/run"
    cp "$work/timing/latents.pt" "$work/run/"
    # --precache again: the latents come from the file, the position encodings are computed before the clock
    "$py" -m b2dr_ref.train "${common[@]}" --out "$work/run" --steps "$steps" --precache \
        --time-limit "$("$py" -c "print($train_s * 1.15)")"
    "$py" -m b2dr_ref.train export --run "$work/run" --out "$work/out/b2dr-$config-gpu" --dtype f16
    cp "$work/run/log.csv" "$work/run/run.json" "$work/out/"
    tar -C "$work/out" -cf "$OUT/gpu_run.tar" .
    echo "done in $((SECONDS - t0)) s: $OUT/gpu_run.tar ($(du -h "$OUT/gpu_run.tar" | cut -f1))"
    cd "$root"
}

case "${1:-}" in
    prepare) prepare ;;
    run) run ;;
    *) echo "usage: bash tools/gpu_train.sh prepare|run" >&2; exit 2 ;;
esac
