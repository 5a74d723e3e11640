#!/usr/bin/env bash
# Table IV pilot (docs/table4.md): a slim TRACKER (default p2b), -U against -W (and -S with
# ARMS), training seeds 0-2, on one synthetic WORLD (default the `small-km` KITTI-layout world),
# in one class-agnostic setting; PARALLEL runs at a time (default 2), one torch thread each. Run
# again after a kill: training resumes from OUT/last.pt and finished runs and evaluations are kept.
#   bash experiments/table4_pilot.sh [ROOT [SETTING]]   # defaults: runs/table4-pilot kitti-1
#   ARMS="none decorrelation sam" PARALLEL=3 bash experiments/table4_pilot.sh ROOT kitti-1
#   WORLD="--dataset nuscenes --preset default-km --sensor hdl32" \
#     bash experiments/table4_pilot.sh runs/table4-pilot-nus1 nuscenes-1
#   TRACKER=mbptrack ARMS=none SEEDS=0 TRAIN_EXTRA="--set adam_beta1=0.5 --set adam_eps=1e-6" \
#     bash experiments/table4_pilot.sh runs/mbptrack-pilot kitti-1
#   TEST=0 ...   # train only: no test reading (a lever's runs, ranked on never-trained worlds)
set -euo pipefail
root=${1:-runs/table4-pilot}
setting=${2:-kitti-1}
read -r -a arms <<< "${ARMS:-none decorrelation}"
parallel=${PARALLEL:-2}
tracker=${TRACKER:-p2b}
read -r -a world <<< "${WORLD:---dataset synthetic --preset small-km}"
read -r -a seeds <<< "${SEEDS:-0 1 2}"
read -r -a train_extra <<< "${TRAIN_EXTRA:-}"
export OMP_NUM_THREADS=1 PYTHONUNBUFFERED=1
budget=(--epochs 8 --iters-per-epoch 50 --batch-size 16 --val-max-tracklets 16 --val-max-frames 60)

train_one() {  # WEIGHTING SEED
  local out="$root/$tracker-$1-s$2" resume=()
  if [ -e "$out/done" ]; then return; fi
  if [ -e "$out/config.yaml" ]; then resume=(--resume); fi
  pointtrack train --tracker "$tracker" --model-size slim --setting "$setting" --weighting "$1" \
    "${world[@]}" --world-seed 0 --seed "$2" --threads 1 \
    "${budget[@]}" "${train_extra[@]}" --no-progress --out "$out" "${resume[@]}" > "$root/logs/train-$1-s$2.log" 2>&1
  touch "$out/done"
}

eval_one() {  # NAME TRACKER...
  local out="$root/test/$1"
  if [ -e "$out/done" ]; then return; fi
  shift
  pointtrack eval --tracker "$@" "${world[@]}" --seed 0 --split test \
    --setting "$setting" --eval-seeds 0 1 2 --workers 1 --no-progress --out "$out" \
    > "$root/logs/eval-$(basename "$out").log" 2>&1
  touch "$out/done"
}

limited() {  # run "$@" in the background once fewer than $parallel jobs run
  while [ "$(jobs -rp | wc -l)" -ge "$parallel" ]; do wait -n; done
  "$@" &
}

mkdir -p "$root/logs" "$root/test"
for seed in "${seeds[@]}"; do
  for arm in "${arms[@]}"; do limited train_one "$arm" "$seed"; done
done
wait
if [ "${TEST:-1}" = 0 ]; then exit 0; fi
eval_one baselines previous_box constant_velocity
for seed in "${seeds[@]}"; do
  for arm in "${arms[@]}"; do limited eval_one "$tracker-$arm-s$seed" "$root/$tracker-$arm-s$seed/best.pt"; done
done
wait
case $tracker in  # Table IV has rows for P2B and BAT only
  p2b | bat) python experiments/table4.py "$root" --tracker "$tracker" --setting "$setting" \
    --arms "${arms[@]}" --seeds "${seeds[@]}" ;;
esac
