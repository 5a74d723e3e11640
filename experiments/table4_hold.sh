#!/usr/bin/env bash
# Table IV pilot, the still-target test of the nuScenes scene-frame cells (docs/table4.md):
# per cell, the three seeds' best.pt as trained and with hold_chamfer_m 0.15 / 0.3 / 0.6
# (experiments/hold_variants.py), ranked by `pointtrack select` on never-trained worlds; the
# first-ranked gets one test reading; experiments/table4_ship.py ships it if it beats both
# baselines, then scripts/backfill_provenance.py. Resumable: finished steps are kept.
#   bash experiments/table4_hold.sh [RUNS]   # RUNS holds table4-pilot-nus1-scene, -nus2-scene
#   ROUND=2 HOLDS="0.6 1 1.5 2.5" bash experiments/table4_hold.sh RUNS   # the second grid: only
#       the variants (not the runs as trained), selections in ROOT/select-hold2-ARM
set -euo pipefail
runs=${1:-runs}
read -r -a holds <<< "${HOLDS:-0.15 0.3 0.6}"
round=${ROUND:-1}
select=$([ "$round" = 1 ] && echo select-hold || echo "select-hold$round")
export OMP_NUM_THREADS=1 PYTHONUNBUFFERED=1
world=(--dataset nuscenes --preset default-km --sensor hdl32 --nuscenes-frame scene)
source "$(dirname "$0")/table4_common.sh"

cell() {  # ROOT SETTING ARM NAME
  local root=$1 setting=$2 arm=$3 name=$4 out="$1/$select-$3" seed
  local candidates=()
  if [ "$round" = 1 ]; then  # the runs as trained (hold 0) compete in the first grid
    for seed in 0 1 2; do candidates+=("$root/p2b-$arm-s$seed/best.pt"); done
  fi
  mkdir -p "$root/hold"
  python experiments/hold_variants.py "$root/p2b-$arm-s0" "$root/p2b-$arm-s1" \
    "$root/p2b-$arm-s2" --holds "${holds[@]}" --out "$root/hold" > "$root/hold/$arm-$round.txt"
  mapfile -t -O ${#candidates[@]} candidates < "$root/hold/$arm-$round.txt"
  select_once "$out" "$name" "$setting" "$root/logs/$select-$arm.log" "${candidates[@]}"
  read_test_once "$root" "$(first_ranked "$out/selection.json")" "$setting"
  python experiments/table4_ship.py "$root" "$arm" "$name" --select "$select-$arm" \
    --command "WORLD=\"${world[*]}\" bash experiments/table4_pilot.sh runs/$(basename "$root") $setting" \
    --command "ROUND=$round HOLDS=\"${holds[*]}\" bash experiments/table4_hold.sh runs   # hold variants, select, gate"
}

for n in 1 2; do
  for arm in none decorrelation; do
    suffix=$([ "$arm" = none ] && echo u || echo w)
    cell "$runs/table4-pilot-nus$n-scene" "nuscenes-$n" "$arm" "p2b-nuscenes$n-$suffix"
  done
done
python scripts/backfill_provenance.py
