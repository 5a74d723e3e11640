#!/usr/bin/env bash
# Table IV, the dead zone in the nuScenes scene-frame cells (docs/table4.md, "The dead zone"):
# per cell and arm, each pilot run's best.pt (and, for -U, the budget pilot's) with hold 0 or
# 2.5 m and dead zone 0.5 / 1 / 2 m (experiments/hold_variants.py), ranked by `pointtrack
# select` on never-trained worlds; the first-ranked gets one test reading and
# experiments/table4_ship.py ships it if it beats both baselines. Resumable.
#   bash experiments/table4_deadzone.sh [RUNS [ARMS]]   # RUNS holds table4-pilot-nus{1,2}-scene
#                                                       # and table4-budget-nus{1,2}-scene
set -euo pipefail
runs=${1:-runs}
read -r -a arms <<< "${2:-none decorrelation}"
export OMP_NUM_THREADS=1 PYTHONUNBUFFERED=1
world=(--dataset nuscenes --preset default-km --sensor hdl32 --nuscenes-frame scene)
source "$(dirname "$0")/table4_common.sh"

cell() {  # N ARM NAME
  local root="$runs/table4-pilot-nus$1-scene" arm=$2 name=$3 out
  out="$root/select-deadzone-$arm"
  local sources=("$root/p2b-$arm-s0" "$root/p2b-$arm-s1" "$root/p2b-$arm-s2")
  if [ "$arm" = none ]; then sources+=("$runs/table4-budget-nus$1-scene/p2b-none-s0"); fi
  local candidates=()
  mkdir -p "$root/logs"
  for source in "${sources[@]}"; do  # the budget run has a pilot run's name: prefixed, since
    # the test reading is filed under the selected file's name (experiments/table4_ship.py)
    local prefix=""
    case $source in */table4-budget-*) prefix=budget- ;; esac
    mapfile -t -O ${#candidates[@]} candidates < <(python experiments/hold_variants.py \
      "$source" --holds 0 2.5 --min-motions 0.5 1 2 --out "$(dirname "$source")/deadzone" \
      --prefix "$prefix")
  done
  select_once "$out" "$name" "nuscenes-$1" "$root/logs/select-deadzone-$arm.log" "${candidates[@]}"
  read_test_once "$root" "$(first_ranked "$out/selection.json")" "nuscenes-$1"
  python experiments/table4_ship.py "$root" "$arm" "$name" --select "select-deadzone-$arm" \
    --command "WORLD=\"${world[*]}\" bash experiments/table4_pilot.sh runs/$(basename "$root") nuscenes-$1" \
    --command "bash experiments/budget_pilot.sh runs/table4-budget-nus$1-scene nuscenes-$1" \
    --command "bash experiments/table4_deadzone.sh runs   # dead-zone variants, select, gate"
}

for arm in "${arms[@]}"; do
  suffix=$([ "$arm" = none ] && echo u || echo w)
  for n in 1 2; do cell "$n" "$arm" "p2b-nuscenes$n-$suffix"; done
done
python scripts/backfill_provenance.py
