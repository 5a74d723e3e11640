#!/usr/bin/env bash
# Table IV pilot (docs/table4.md): P2B slim kitti-1, -U against -W, training seeds 0-2, on the
# `small-km` world; two runs at a time, one torch thread each. Run again after a kill: training
# resumes from OUT/last.pt and finished evaluations are kept.
#   bash experiments/table4_pilot.sh [ROOT]      # ROOT defaults to runs/table4-pilot
set -euo pipefail
root=${1:-runs/table4-pilot}
export OMP_NUM_THREADS=1 PYTHONUNBUFFERED=1
budget=(--epochs 8 --iters-per-epoch 50 --batch-size 16 --val-max-tracklets 16 --val-max-frames 60)

train_one() {  # WEIGHTING SEED
  local out="$root/p2b-$1-s$2" resume=()
  if [ -e "$out/done" ]; then return; fi
  if [ -e "$out/config.yaml" ]; then resume=(--resume); fi
  pointtrack train --tracker p2b --model-size slim --setting kitti-1 --weighting "$1" \
    --dataset synthetic --preset small-km --world-seed 0 --seed "$2" --threads 1 \
    "${budget[@]}" --no-progress --out "$out" "${resume[@]}" > "$root/logs/train-$1-s$2.log" 2>&1
  touch "$out/done"
}

eval_one() {  # NAME TRACKER...
  local out="$root/test/$1"
  if [ -e "$out/done" ]; then return; fi
  shift
  pointtrack eval --tracker "$@" --dataset synthetic --preset small-km --seed 0 --split test \
    --setting kitti-1 --eval-seeds 0 1 2 --workers 1 --no-progress --out "$out" \
    > "$root/logs/eval-$(basename "$out").log" 2>&1
  touch "$out/done"
}

mkdir -p "$root/logs" "$root/test"
for seed in 0 1 2; do
  train_one none "$seed" &
  train_one decorrelation "$seed" &
  wait
done
eval_one baselines previous_box constant_velocity
for seed in 0 1 2; do
  for w in none decorrelation; do
    eval_one "p2b-$w-s$seed" "$root/p2b-$w-s$seed/best.pt" &
    if [ "$w" = decorrelation ]; then wait; fi
  done
done
wait
python experiments/table4.py "$root"
