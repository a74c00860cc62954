#!/usr/bin/env bash
# b2dr on a Slurm job array: one array task per shard (SLURM_ARRAY_TASK_ID -> --shard K/N), requeue-safe:
# every shard runs with --resume into its own folder, so a requeued (or resubmitted) task skips the scenarios it
# finished and refuses a folder of other flags. docs/scale_out.md.
#
#   mkdir -p logs
#   jid=$(sbatch --parsable --array=0-2 examples/slurm_array.sh run --scenario DIR_OR_LIST --renderer b2dr)
#   sbatch --dependency=afterok:$jid --wrap "b2dr merge out/scale/shard-{0,1,2} --out out/scale/merged"
#
# Arguments: the b2dr command line without --shard, --resume and --out (added here).
# Environment: B2DR_BIN (default: b2dr on PATH), B2DR_OUT (default out/scale; on a filesystem every node sees),
# B2DR_SHARDS (default: SLURM_ARRAY_TASK_COUNT, i.e. the array's size; the array must be contiguous),
# B2DR_DRY_RUN=1 prints the command instead of running it (no Slurm needed:
#   SLURM_ARRAY_TASK_ID=1 SLURM_ARRAY_TASK_COUNT=3 B2DR_DRY_RUN=1 bash examples/slurm_array.sh sim ...).
# The GPU: --gres=gpu:1 makes Slurm set CUDA_VISIBLE_DEVICES, and b2dr picks that GPU's Vulkan device.
#SBATCH --job-name=b2dr
#SBATCH --array=0-2
#SBATCH --gres=gpu:1
#SBATCH --cpus-per-task=4
#SBATCH --mem=16G
#SBATCH --time=04:00:00
#SBATCH --requeue
#SBATCH --open-mode=append
#SBATCH --output=logs/b2dr-%A_%a.log
set -euo pipefail

die() { echo "slurm_array.sh: $*" >&2; exit 2; }
[ "${SLURM_ARRAY_TASK_ID:-}" != "" ] || die "SLURM_ARRAY_TASK_ID is not set: submit with sbatch --array=0-(N-1)"
[ $# -ge 1 ] || die "give the b2dr command, e.g.: sbatch --array=0-2 $0 run --scenario builtin:town:0,builtin:cross:0"
for a in "$@"; do
  case "$a" in
    --shard|--shard=*|--resume|--out|--out=*) die "$a is set by this script (B2DR_OUT sets the folder)" ;;
  esac
done
n="${B2DR_SHARDS:-${SLURM_ARRAY_TASK_COUNT:-}}"
[ -n "$n" ] || die "neither B2DR_SHARDS nor SLURM_ARRAY_TASK_COUNT is set"
k=$(( SLURM_ARRAY_TASK_ID - ${SLURM_ARRAY_TASK_MIN:-0} ))
[ "$k" -ge 0 ] && [ "$k" -lt "$n" ] || die "shard $k is outside 0..$((n - 1)) (SLURM_ARRAY_TASK_ID=$SLURM_ARRAY_TASK_ID, N=$n)"
out="${B2DR_OUT:-out/scale}/shard-$k"
cmd=("${B2DR_BIN:-b2dr}" "$@" --shard "$k/$n" --resume --out "$out")
if [ "${B2DR_DRY_RUN:-0}" = 1 ]; then
  printf '%q ' "${cmd[@]}"
  echo
  exit 0
fi
echo "slurm_array.sh: shard $k/$n on $(hostname), CUDA_VISIBLE_DEVICES=${CUDA_VISIBLE_DEVICES:-unset}, restart ${SLURM_RESTART_COUNT:-0}" >&2
exec "${cmd[@]}"
