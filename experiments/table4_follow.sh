#!/usr/bin/env bash
# Table IV follow-up in the nuScenes scene-frame cells (docs/table4.md, "Follow-up: region and
# budget together"): P2B slim -U and -W, training seeds 0-2, the search region cut around the
# previous box (+4 m) at the shipped budget (25,600 samples), nuscenes-2 then nuscenes-1, the
# two arms of a seed side by side (experiments/table4_pilot.sh: every run's test reading and
# the cell's Table IV rows); then per cell and arm `pointtrack select` on the never-trained
# worlds over the runs and their hold / dead-zone variants, one test reading of a first-ranked
# variant, and the ship gate; a shipped file gets the nuScenes-A weather grid. Resumable:
# finished runs, selections and readings are kept.
#   bash experiments/table4_follow.sh [RUNS]      # default runs
#   SETTINGS=2 bash experiments/table4_follow.sh RUNS   # one setting only
#   WORLD="--dataset nuscenes --preset tiny-km --sensor hdl32 --nuscenes-frame scene" \
#     TRAIN="--epochs 1 --iters-per-epoch 1 --batch-size 2" DRY_RUN=1 bash ... /tmp/smoke
#     # a smoke test: DRY_RUN=1 prints the ship verdicts and ships nothing
set -euo pipefail
runs=${1:-runs}
read -r -a settings <<< "${SETTINGS:-2 1}"
export OMP_NUM_THREADS=1 PYTHONUNBUFFERED=1
read -r -a world <<< "${WORLD:---dataset nuscenes --preset default-km --sensor hdl32 --nuscenes-frame scene}"
source "$(dirname "$0")/table4_common.sh"
declare -A letter=([none]=u [decorrelation]=w)
train="--search-offset 4 --search-center previous --epochs 32 ${TRAIN:-}"

# the four worlds into the cache once, before two training processes would each build world 0
gen=(--layout nuscenes)
for ((i = 0; i < ${#world[@]}; i++)); do
  case ${world[i]} in --preset | --sensor) gen+=("${world[i]}" "${world[i + 1]}") ;; esac
done
for seed in 0 1 2 3; do
  pointtrack generate --cache "${gen[@]}" --seed "$seed" --no-progress > /dev/null
done

cell() {  # N ARM
  local root="$runs/table4-follow-nus$1-scene" arm=$2 candidates=() chosen
  local out="$root/select-$2" ship="p2b-nuscenes$1-${letter[$2]}"
  for seed in 0 1 2; do
    candidates+=("$root/p2b-$arm-s$seed/best.pt")
    mapfile -t -O ${#candidates[@]} candidates < <(python experiments/hold_variants.py \
      "$root/p2b-$arm-s$seed" --holds 0 2.5 --min-motions 0.5 1 2 --out "$root/deadzone" \
      --prefix follow-)
  done
  select_once "$out" "$ship" "nuscenes-$1" "$root/logs/select-$arm.log" "${candidates[@]}" \
    previous_box constant_velocity
  chosen=$(first_ranked "$out/selection.json")
  case $chosen in
    "$root"/*) ;;
    *) echo "nuscenes-$1 $arm: first-ranked $chosen is not a run's file: nothing ships"; return ;;
  esac
  read_test_once "$root" "$chosen" "nuscenes-$1"
  python experiments/table4_ship.py "$root" "$arm" "$ship" --select "select-$arm" \
    ${DRY_RUN:+--dry-run} --command "bash experiments/table4_follow.sh runs   # training, variants, select, gate"
}

for n in "${settings[@]}"; do
  WORLD="${world[*]}" ARMS="none decorrelation" PARALLEL=2 TRAIN_EXTRA="$train" \
    bash experiments/table4_pilot.sh "$runs/table4-follow-nus$n-scene" "nuscenes-$n"
  for arm in none decorrelation; do cell "$n" "$arm"; done
done
if [ -n "${DRY_RUN:-}" ]; then exit 0; fi
python scripts/backfill_provenance.py
bash experiments/weather_nuscenes.sh "$runs/weather-nus"
