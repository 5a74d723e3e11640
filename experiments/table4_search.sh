#!/usr/bin/env bash
# Table IV, the search region at 2 Hz in the nuScenes scene-frame cells (docs/table4.md, "The
# search region at 2 Hz"): P2B-U slim at the pilot's budget, seeds 0-2, trained with the search
# region +4 m a side cut around the previous box (experiments/table4_pilot.sh, no test reading),
# both settings side by side; per cell `pointtrack select` on the never-trained worlds ranks the
# new runs as trained and with hold {0, 2.5} x dead zone {0.5, 1, 2} m beside the pilot's -U runs
# as trained, the previous selection's first-ranked file and the baselines; the paired
# comparison (question 1) is printed; a first-ranked new file gets one test reading and the ship
# gate. Resumable.
#   bash experiments/table4_search.sh [RUNS]   # RUNS holds table4-pilot-nus{1,2}-scene
# "Budget and region" (the same section): one seed at the budget pilot's 25,600 samples, ranked
# beside the budget run as trained and the first selection's first-ranked file:
#   TAG=budget-search SEEDS=0 EPOCHS=32 PREVIOUS=table4-search-nus@-scene/select \
#     REFERENCE=table4-budget-nus@-scene bash experiments/table4_search.sh RUNS
# ARM=decorrelation (or sam) trains and ranks that arm instead of -U (selection in select-ARM;
# PREVIOUS defaults to the pilot's dead-zone selection of that arm).
set -euo pipefail
runs=${1:-runs}
export OMP_NUM_THREADS=1 PYTHONUNBUFFERED=1
world=(--dataset nuscenes --preset default-km --sensor hdl32 --nuscenes-frame scene)
source "$(dirname "$0")/table4_common.sh"
tag=${TAG:-search}
arm=${ARM:-none}
suffix=$([ "$arm" = none ] && echo "" || echo "-$arm")  # -U keeps the first runs' names
declare -A letter=([none]=u [decorrelation]=w [sam]=s)
read -r -a seeds <<< "${SEEDS:-0 1 2}"
previous_select=${PREVIOUS:-table4-pilot-nus@-scene/select-deadzone-$arm}  # @: the setting
reference=${REFERENCE:-table4-pilot-nus@-scene}  # its p2b-none-sK runs, as trained
train="--search-offset 4 --search-center previous --epochs ${EPOCHS:-8}"

for n in 1 2; do  # one core a setting
  WORLD="${world[*]}" ARMS=$arm TEST=0 PARALLEL=1 TRAIN_EXTRA="$train" SEEDS="${seeds[*]}" \
    bash experiments/table4_pilot.sh "$runs/table4-$tag-nus$n-scene" "nuscenes-$n" &
done
wait

cell() {  # N
  local pilot="$runs/table4-pilot-nus$1-scene" root="$runs/table4-$tag-nus$1-scene"
  local reference_root="$runs/${reference//@/$1}"
  local out="$root/select$suffix" ship="p2b-nuscenes$1-${letter[$arm]}"
  local candidates=() previous chosen
  previous=$(first_ranked "$runs/${previous_select//@/$1}/selection.json")
  for seed in "${seeds[@]}"; do
    candidates+=("$root/p2b-$arm-s$seed/best.pt" "$reference_root/p2b-$arm-s$seed/best.pt")
    mapfile -t -O ${#candidates[@]} candidates < <(python experiments/hold_variants.py \
      "$root/p2b-$arm-s$seed" --holds 0 2.5 --min-motions 0.5 1 2 --out "$root/deadzone" \
      --prefix "$tag-")
  done
  if [ "$previous" != previous_box ]; then candidates+=("$previous"); fi
  candidates+=(previous_box constant_velocity)
  select_once "$out" "$ship" "nuscenes-$1" "$root/logs/select$suffix.log" "${candidates[@]}"
  python experiments/search_lever.py "$out/selection.json" "$root" "$reference_root" \
    --seeds "${seeds[@]}" --arm "$arm"
  chosen=$(first_ranked "$out/selection.json")
  case $chosen in
    "$root"/*) ;;
    *) echo "nuscenes-$1: first-ranked $chosen is not a new run's file: no test reading"; return ;;
  esac
  mkdir -p "$root/test"
  ln -sfn "$(realpath "$pilot/test/baselines")" "$root/test/baselines"
  read_test_once "$root" "$chosen" "nuscenes-$1"
  python experiments/table4_ship.py "$root" "$arm" "$ship" --select "$(realpath "$out")" \
    --command "ARM=$arm TAG=$tag SEEDS=\"${seeds[*]}\" EPOCHS=${EPOCHS:-8} PREVIOUS=$previous_select \
REFERENCE=$reference bash experiments/table4_search.sh runs   # training, variants, select, gate"
}

for n in 1 2; do cell "$n"; done
python scripts/backfill_provenance.py
