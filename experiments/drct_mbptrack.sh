#!/usr/bin/env bash
# DRCT on MBPTrack (docs/mbptrack.md, "DRCT from the shipped file"): plain, -RD and DRCT
# fine-tunes of one MBPTrack start (default: the shipped mbptrack-kitti1-u) on WORLD (default:
# `default`), fine-tune seeds 21-23, each export (and the start) on the weather grid of
# EVAL_WORLD's test split (default: `small`); PARALLEL jobs at a time (default 2), one torch
# thread each. Run again after a kill: training resumes from OUT/last.pt, finished runs and
# evaluations are kept.
#   bash experiments/drct_mbptrack.sh [ROOT]            # default runs/mbptrack-drct-shipped
#   START=path/best.pt ARMS="plain drct" SEEDS=21 bash experiments/drct_mbptrack.sh ROOT
#   WORLD="--dataset synthetic --preset tiny" EVAL_WORLD="--dataset synthetic --preset tiny" \
#     BUDGET="--epochs 1 --iters-per-epoch 1 --batch-size 2" \
#     WEATHER="--weather fog --weather-levels 1" bash ... /tmp/smoke  # smoke test
set -euo pipefail
root=${1:-runs/mbptrack-drct-shipped}
start=${START:-mbptrack-kitti1-u}  # a shipped name or a checkpoint path
read -r -a arms <<< "${ARMS:-plain rd drct}"
read -r -a seeds <<< "${SEEDS:-21 22 23}"
parallel=${PARALLEL:-2}
read -r -a world <<< "${WORLD:---dataset synthetic --preset default}"
read -r -a eval_world <<< "${EVAL_WORLD:---dataset synthetic --preset small}"
read -r -a budget <<< "${BUDGET:---epochs 3 --iters-per-epoch 20 --batch-size 16}"
read -r -a weather <<< "${WEATHER:---weather all}"
export OMP_NUM_THREADS=1 PYTHONUNBUFFERED=1

arm_flags() {  # ARM -> the flags that make it
  case $1 in
    plain) ;;
    rd) echo --domain-randomize ;;
    drct) echo --drct ;;
    *) echo "unknown arm '$1' (plain, rd, drct)" >&2; return 2 ;;
  esac
}

train_one() {  # ARM SEED
  local out="$root/$1-s$2" resume=() flags
  if [ -e "$out/done" ]; then return; fi
  if [ -e "$out/config.yaml" ]; then resume=(--resume); fi
  read -r -a flags <<< "$(arm_flags "$1")"
  pointtrack train --tracker mbptrack --model-size slim --setting kitti-1 --weighting none \
    "${flags[@]}" "${world[@]}" --world-seed 0 --seed "$2" --threads 1 "${budget[@]}" \
    --lr 1e-4 --set lr_step_epochs=6 --set val_every=3 \
    --set adam_beta1=0.5 --set adam_eps=1e-6 --val-max-tracklets 16 --val-max-frames 40 \
    --init-weights "$start" --no-progress --out "$out" --export "$out.safetensors" \
    "${resume[@]}" > "$root/logs/train-$1-s$2.log" 2>&1
  touch "$out/done"
}

weather_one() {  # NAME TRACKER
  local out="$root/weather/$1"
  if [ -e "$out/done" ]; then return; fi
  pointtrack eval --tracker "$2" "${eval_world[@]}" --seed 0 --split test --setting kitti-1 \
    "${weather[@]}" --weather-seed 0 --fog-mode reference --no-analysis --workers 1 \
    --no-progress --out "$out" > "$root/logs/weather-$1.log" 2>&1
  touch "$out/done"
}

limited() {  # run "$@" in the background once fewer than $parallel jobs run
  while [ "$(jobs -rp | wc -l)" -ge "$parallel" ]; do wait -n; done
  "$@" &
}

mkdir -p "$root/logs" "$root/weather"
for arm in "${arms[@]}"; do arm_flags "$arm" > /dev/null; done
if [[ $start == */* && ! -e $start ]]; then echo "no start checkpoint at $start (set START)" >&2; exit 2; fi
limited weather_one start "$start"
for seed in "${seeds[@]}"; do
  for arm in "${arms[@]}"; do limited train_one "$arm" "$seed"; done
done
wait
for seed in "${seeds[@]}"; do
  for arm in "${arms[@]}"; do limited weather_one "$arm-s$seed" "$root/$arm-s$seed.safetensors"; done
done
wait
python experiments/drct_seeds.py "$root" --arms "${arms[@]}" --seeds "${seeds[@]}"
