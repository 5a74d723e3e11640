#!/usr/bin/env bash
# MBPTrack's `light` size at the shipped budget (docs/mbptrack.md, "A `light` size for the speed
# goal"): -U runs (training seeds 0 and 1, side by side) as experiments/mbptrack_ship.sh trains
# the slim file, one `pointtrack select` of them beside `mbptrack-kitti1-u` and the three shipped
# -U predecessors, the gate (the first-ranked light run above the three predecessors), then for a
# shipped `mbptrack-kitti1-u-light` its one test reading and the act-speed reading against P2B.
# Run again after a kill: training resumes from OUT/last.pt, finished steps are kept.
# STAGE=train stops after the runs; SMOKE=1 cuts every run to a few steps.
#   bash experiments/mbptrack_light.sh [ROOT]    # default runs/mbptrack-light
set -euo pipefail
root=${1:-runs/mbptrack-light}
source experiments/mbptrack_common.sh
predecessors=(p2b-kitti1-u bat-kitti1-u gpt-kitti1-u)
name=mbptrack-kitti1-u-light
mkdir -p "$root/logs"

train_mbptrack_u_seeds light "$root" light
if [ "${STAGE:-all}" = train ]; then exit 0; fi

runs=("$root"/mbptrack-light-s{0,1}/best.pt)
if [ ! -e "$root/select/selection.json" ]; then
  pointtrack select "${runs[@]}" mbptrack-kitti1-u "${predecessors[@]}" previous_box \
    --setting kitti-1 --no-progress --out "$root/select" >"$root/logs/select.log" 2>&1
fi
read -r chosen < <(python3 experiments/mbptrack_ship.py first "$root/select/selection.json" \
  "${runs[@]}")
# the gate: the chosen run against the three predecessors alone (the kept reports), written by
# --save for shipping where it ranks first
if [ ! -e "$root/select-gate/selection.json" ]; then
  mkdir -p "$root/select-gate"
  cp -rn "$root/select/parts" "$root/select-gate/"
  pointtrack select "$chosen" "${predecessors[@]}" --setting kitti-1 --no-progress \
    --out "$root/select-gate" --save "$root/select-gate/$name.safetensors" \
    >"$root/logs/select-gate.log" 2>&1
fi
python3 experiments/mbptrack_ship.py ship "$root/select-gate" "$name" \
  --command "bash experiments/mbptrack_light.sh $root" >"$root/logs/ship.log"
cat "$root/logs/ship.log"
if ! grep -q ": shipped" "$root/logs/ship.log"; then exit 0; fi  # nothing is read on test
python3 scripts/backfill_provenance.py
if [ ! -e "$root/test/done" ]; then
  pointtrack eval --tracker "$name" "${world[@]}" --split test --eval-seeds 0 1 2 --no-progress \
    --out "$root/test" >"$root/logs/test.log" 2>&1
  touch "$root/test/done"
fi
python3 benchmarks/bench_mbptrack.py --steps 30 --repeats 3 --mbptrack "$name" \
  | tee "$root/logs/speed.log"
