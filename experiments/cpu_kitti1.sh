#!/usr/bin/env bash
# The papers'-width kitti-1 -U run of docs/notes/checkpoints-history.md ("kitti-1 at the papers'
# widths on the CPU, across sessions"): the registered -U command (experiments/train_commands.sh)
# on one core, no deadline; run again, it resumes from OUT/last.pt.
#   bash experiments/cpu_kitti1.sh MODEL OUT      # MODEL: p2b | bat | gpt
set -euo pipefail
if [ $# -ne 2 ]; then
  echo "usage: bash experiments/cpu_kitti1.sh MODEL OUT" >&2
  exit 2
fi
model=$1 out=$2
resume=()
if [ -e "$out/config.yaml" ]; then
  resume=(--resume)
fi
export OMP_NUM_THREADS=1 PYTHONUNBUFFERED=1 DEVICE=cpu SMOKE=0
source experiments/train_commands.sh
train_u "$model" kitti-1 default 0 0 --epochs 48 --set lr_step_epochs=32 --set val_every=10 \
  --out "$out" "${resume[@]}"
