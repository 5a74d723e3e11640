#!/usr/bin/env bash
# The papers'-width kitti-1 -U run of docs/checkpoints.md ("kitti-1 at the papers' widths on the
# CPU, across sessions"), one model on one core; run again, it resumes from OUT/last.pt.
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
export OMP_NUM_THREADS=1 PYTHONUNBUFFERED=1
exec python3 -m training.cli train --tracker "$model" --setting kitti-1 --weighting none \
  --dataset synthetic --preset default --model-size default --batch-size 16 \
  --iters-per-epoch 50 --lr 1e-3 --size-jitter 0.3 --ema-decay 0.995 --threads 1 \
  --val-max-tracklets 16 --val-max-frames 40 --seed 0 --device cpu --num-workers 0 \
  --no-progress --epochs 48 --set lr_step_epochs=32 --set val_every=10 --out "$out" "${resume[@]}"
