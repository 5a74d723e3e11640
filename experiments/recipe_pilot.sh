#!/usr/bin/env bash
# Recipe v1 vs v2 pilot (docs/notes/recipe-experiments.md, "Pilot"): P2B slim on the synthetic
# `small` world, kitti-1, seeds 0 and 1, equal samples (100 steps of 16), four runs at a time;
# then OPE of each run's last.pt on the small world's val split (eval seed 0), the template mode
# it was trained with. Usage: PYTHONPATH=$PWD nice -n 10 bash experiments/recipe_pilot.sh
# runs/recipe-pilot. A second argument "320" runs the amended pilot
# (docs/notes/recipe-experiments.md): 4 epochs x 10 steps x 8.
set -euo pipefail
OUT=${1:-runs/recipe-pilot}
if [ "${2:-1600}" = 320 ]; then
  BUDGET=(--epochs 4 --iters-per-epoch 10 --batch-size 8); MAX_TRACKLETS=(--max-tracklets 12)
else
  BUDGET=(--epochs 1 --iters-per-epoch 100 --batch-size 16); MAX_TRACKLETS=()
fi
mkdir -p "$OUT"
export OMP_NUM_THREADS=1
train() {  # recipe seed
  pointtrack train --tracker p2b --model-size slim --setting kitti-1 --preset small \
    "${BUDGET[@]}" --seed "$2" --threads 1 \
    --val-max-tracklets 4 --val-max-frames 10 --no-progress \
    --set recipe="$1" --out "$OUT/p2b-slim-$1-s$2" > "$OUT/train-$1-s$2.log" 2>&1
}
evaluate() {  # recipe seed template_mode
  pointtrack eval --tracker "$OUT/p2b-slim-$1-s$2/last.pt" --dataset synthetic --preset small \
    --split val --setting kitti-1 --template-mode "$3" --eval-seed 0 --num-envs 4 \
    "${MAX_TRACKLETS[@]}" \
    --no-progress --no-analysis --out "$OUT/eval-$1-s$2" > "$OUT/eval-$1-s$2.log" 2>&1
}
# all four at once: on a shared, loaded CPU each process gets its share of the cores
train v1 0 & train v2 0 & train v1 1 & train v2 1 & wait
evaluate v1 0 first_and_previous & evaluate v2 0 first_and_previous_merged &
evaluate v1 1 first_and_previous & evaluate v2 1 first_and_previous_merged & wait
echo done > "$OUT/DONE"
