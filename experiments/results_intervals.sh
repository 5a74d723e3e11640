#!/usr/bin/env bash
# docs/results.md's tables with 90 % intervals: every shipped file and the baselines on the
# `default` world's test split (world 0), eval seeds 0-2 in one report per setting (the mean,
# each seed's value, a tracklet bootstrap interval per number). One process, one torch thread;
# a finished setting is kept on a rerun.
#   bash experiments/results_intervals.sh [ROOT]      # ROOT defaults to runs/results-intervals
set -euo pipefail
root=${1:-runs/results-intervals}
export OMP_NUM_THREADS=1 PYTHONUNBUFFERED=1
mkdir -p "$root"

run_setting() {  # SETTING TRACKER...
  local out="$root/$1"
  if [ -e "$out/done" ]; then return; fi
  local setting=$1
  shift
  pointtrack eval --tracker "$@" --dataset synthetic --preset default --seed 0 --split test \
    --setting "$setting" --eval-seeds 0 1 2 --workers 1 --no-progress --out "$out" \
    > "$root/$setting.txt" 2> "$root/$setting.log"
  touch "$out/done"
}

run_setting kitti-1 p2b-kitti1-u p2b-kitti1-w bat-kitti1-u bat-kitti1-w gpt-kitti1-u gpt-kitti1-w \
  p2b-kitti1-u-rl gpt-kitti1-u-rl p2b-kitti1-drct m2track-kitti1-u m2track-kitti1-w \
  mbptrack-kitti1-u mbptrack-kitti1-w previous_box constant_velocity
run_setting kitti-2 p2b-kitti2-u p2b-kitti2-w previous_box constant_velocity
