#!/bin/bash
# One benchmark run as a SLURM array: each task runs one shard; the last to finish merges.
#   sbatch scripts/slurm/array.sh     watch: squeue --me     merge by hand: e3cm-bench merge <OUT>
# Edit two places, then submit from the repository (with e3cm-bench installed):
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
ROOT=/data/megadepth_test_1500
OUT=runs/megadepth_e3cm
COMMAND=(megadepth --root "$ROOT" --out "$OUT" --matcher e3cm --backbone vgg19 --device cuda)

# A shard that dies is rerun alone (sbatch --array=K scripts/slurm/array.sh) and resumes.
e3cm-bench "${COMMAND[@]}" --shard "${SLURM_ARRAY_TASK_ID}/${SLURM_ARRAY_TASK_COUNT}"
