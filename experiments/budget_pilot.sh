#!/usr/bin/env bash
# Table IV, is the budget the lever in the nuScenes scene-frame cells? (docs/table4.md, "Budget
# pilot"): one P2B-U slim run of nuscenes-1 at the shipped budget (25,600 samples, 4x the
# pilot's) in SETTING, everything else as the pilot cell; then `pointtrack select` ranks it as trained and
# with the pilot's selected still-target test (hold 2.5 m) beside the baselines on the
# never-trained worlds (no test reading: one seed is a diagnostic, not a cell). Resumable.
#   bash experiments/budget_pilot.sh [ROOT [SETTING]]   # defaults runs/table4-budget-nus1-scene
#                                                     # nuscenes-1
set -euo pipefail
root=${1:-runs/table4-budget-nus1-scene}
setting=${2:-nuscenes-1}
export OMP_NUM_THREADS=1 PYTHONUNBUFFERED=1
world=(--dataset nuscenes --preset default-km --sensor hdl32 --nuscenes-frame scene)
run="$root/p2b-none-s0"
mkdir -p "$root/logs" "$root/hold"
if [ ! -e "$run/done" ]; then
  resume=()
  if [ -e "$run/config.yaml" ]; then resume=(--resume); fi
  pointtrack train --tracker p2b --model-size slim --setting "$setting" --weighting none \
    "${world[@]}" --world-seed 0 --seed 0 --threads 1 --epochs 32 --iters-per-epoch 50 \
    --batch-size 16 --val-max-tracklets 16 --val-max-frames 60 --no-progress --out "$run" \
    "${resume[@]}" > "$root/logs/train-none-s0.log" 2>&1
  touch "$run/done"
fi
python experiments/hold_variants.py "$run" --holds 2.5 --out "$root/hold" > "$root/hold/none.txt"
out="$root/select"
if [ ! -e "$out/selection.json" ]; then
  pointtrack select "$run/best.pt" "$(cat "$root/hold/none.txt")" previous_box constant_velocity \
    --setting "$setting" "${world[@]}" --train-world 0 --no-progress --out "$out" \
    > "$root/logs/select.log" 2>&1
fi
python - "$out/selection.json" <<'PY'
import json, sys
for row in json.load(open(sys.argv[1]))["ranking"]:
    print(f"{row['success']:5.1f}  {row['candidate']}")
PY
