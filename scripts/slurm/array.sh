#!/bin/bash
# One benchmark run as a SLURM array: each task runs one shard; the last to finish merges.
#   sbatch scripts/slurm/array.sh     watch: squeue --me     merge by hand: e3cm-bench merge <OUT>
# Edit two places, then submit from the repository (with e3cm-bench installed and its
# environment active: sbatch passes the environment on to the tasks).
# Without editing: sbatch's own options override the #SBATCH lines (sbatch --partition=cpu
# --gres=none ...; or SBATCH_PARTITION=..., SBATCH_GRES=none in the environment), and the
# paths come from E3CM_ROOT, E3CM_OUT and E3CM_SHARDS; any arguments after the script are the
# command instead of COMMAND below:
#   E3CM_SHARDS=2 sbatch --array=1-2 scripts/slurm/array.sh hpatches --root R --out O --matcher sift
#
# 1. the partition and one task's resources (one GPU each); --array=1-N runs N shards
#    (sbatch reads #SBATCH lines only before the first command, so they stay up here)
#SBATCH --partition=gpu
#SBATCH --array=1-8
#SBATCH --gres=gpu:1
#SBATCH --cpus-per-task=8
#SBATCH --mem=32G
#SBATCH --time=04:00:00
#SBATCH --job-name=e3cm-bench
#SBATCH --output=slurm-%A_%a.out
set -euo pipefail

# 2. the paths and the command (any benchmark command; reproduce CONFIG ... works too)
ROOT="${E3CM_ROOT:-/data/megadepth_test_1500}"
OUT="${E3CM_OUT:-runs/megadepth_e3cm}"
COMMAND=(megadepth --root "$ROOT" --out "$OUT" --matcher e3cm --backbone vgg19 --device cuda)
# N, the number of shards: the size of --array above. Not SLURM_ARRAY_TASK_COUNT: a rerun of
# one shard (sbatch --array=3 scripts/slurm/array.sh) is an array of one task, and shard 3
# must still be the 3rd of N.
SHARDS="${E3CM_SHARDS:-8}"
case "$SHARDS" in
  ''|*[!0-9]*) echo "array.sh: E3CM_SHARDS=$SHARDS is not a whole number of shards" >&2; exit 2 ;;
esac
if [ "$#" -gt 0 ]; then
  COMMAND=("$@")
fi

# A shard that dies (time limit, scancel, a lost node) is rerun alone and resumes:
#   sbatch --array=K scripts/slurm/array.sh     (e3cm-bench merge <OUT> names the shards to rerun)
task="${SLURM_ARRAY_TASK_ID:?not a SLURM array task (submit with sbatch --array=1-N)}"
if [ "$task" -lt 1 ] || [ "$task" -gt "$SHARDS" ]; then
  echo "array.sh: array task $task is not a shard of 1..$SHARDS (--array=1-N with N = E3CM_SHARDS, $SHARDS)" >&2
  exit 2
fi
# exec: the scheduler's signals (scancel, the time limit) reach e3cm-bench itself
exec e3cm-bench "${COMMAND[@]}" --shard "$task/$SHARDS"
