#!/usr/bin/env bash
# Table IV, which half of the 2 Hz search region moves the moving targets? (docs/table4.md,
# "The search region's two halves"): in nuscenes-2 (scene frame), P2B-U slim at the pilot's
# budget, seeds 0-2, with the region's margin alone (+4 m, samples cut around the current box)
# and with the previous-box cut alone (+2 m); then one `pointtrack select` ranks them as trained
# beside the pilot's and the search-region runs and previous_box on the never-trained worlds, and
# experiments/still_moving.py splits the ranking by standing and moving targets. A diagnostic: no
# file is chosen, no test split is read. Resumable.
#   bash experiments/table4_search_factors.sh [RUNS]   # RUNS holds table4-{pilot,search}-nus2-scene
set -euo pipefail
runs=${1:-runs}
export OMP_NUM_THREADS=1 PYTHONUNBUFFERED=1
world=(--dataset nuscenes --preset default-km --sensor hdl32 --nuscenes-frame scene)
declare -A flags=([margin]="--search-offset 4" [centre]="--search-center previous")
for half in margin centre; do  # one core each
  WORLD="${world[*]}" ARMS=none TEST=0 PARALLEL=1 TRAIN_EXTRA="${flags[$half]}" \
    bash experiments/table4_pilot.sh "$runs/table4-search-$half-nus2-scene" nuscenes-2 &
done
wait
out="$runs/table4-search-margin-nus2-scene/select-halves"
candidates=()
for root in search-margin search-centre search pilot; do
  for seed in 0 1 2; do candidates+=("$runs/table4-$root-nus2-scene/p2b-none-s$seed/best.pt"); done
done
if [ ! -e "$out/selection.json" ]; then
  pointtrack select "${candidates[@]}" previous_box --setting nuscenes-2 "${world[@]}" \
    --train-world 0 --no-progress --out "$out" > "$out.log" 2>&1 \
    || grep -q "is not a tracker file" "$out.log"
fi
python experiments/still_moving.py "$out/selection.json"
