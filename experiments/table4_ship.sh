#!/usr/bin/env bash
# Table IV pilot, shipping (docs/table4.md, "Shipping"): per cell without a shipped file,
# `pointtrack select` over the three seeds' best.pt on never-trained worlds, then
# experiments/table4_ship.py ships the first-ranked file if its pilot test reading beats both
# baselines (and writes its recipe); then scripts/backfill_provenance.py records the recipes in
# the files and the manifest. Resumable: a finished selection (its selection.json) is kept.
#   bash experiments/table4_ship.sh [RUNS]   # RUNS holds table4-pilot, table4-pilot-nus1/-nus2
#   bash experiments/table4_ship.sh RUNS scene   # the scene-frame nuScenes cells instead
#                                                # (table4-pilot-nus1-scene, -nus2-scene)
#   bash experiments/table4_ship.sh RUNS last-s  # the -S cells of P2B kitti-2 and BAT kitti-1
#                                                # (table4-pilot-kitti2-s, -bat-kitti1-s)
set -euo pipefail
runs=${1:-runs}
cells=${2:-lidar}
export OMP_NUM_THREADS=1 PYTHONUNBUFFERED=1

ship() {  # ROOT SETTING ARM NAME WORLD-FLAGS... (the tracker: NAME's prefix; PILOT: the
  local root=$1 setting=$2 arm=$3 name=$4  # variables table4_pilot.sh ran with, if any)
  shift 4
  local out="$root/select-$arm" seed tracker=${name%%-*}
  for seed in 0 1 2; do
    if [ ! -e "$root/$tracker-$arm-s$seed/done" ]; then
      echo "$root/$tracker-$arm-s$seed: training not finished (no done marker)" >&2
      return 1
    fi
  done
  if [ ! -e "$out/selection.json" ]; then
    pointtrack select "$root/$tracker-$arm-s0/best.pt" "$root/$tracker-$arm-s1/best.pt" \
      "$root/$tracker-$arm-s2/best.pt" --setting "$setting" "$@" --train-world 0 --workers 1 \
      --no-progress --out "$out" --save "$out/$name.safetensors" > "$root/logs/select-$arm.log" 2>&1
  fi
  python experiments/table4_ship.py "$root" "$arm" "$name" \
    --command "${PILOT:+$PILOT }WORLD=\"$*\" bash experiments/table4_pilot.sh runs/$(basename "$root") $setting" \
    --command "bash experiments/table4_ship.sh runs $cells   # pointtrack select $*, then the gate"
}

nus=(--dataset nuscenes --preset default-km --sensor hdl32)
case $cells in
  lidar)
    ship "$runs/table4-pilot" kitti-1 sam p2b-kitti1-s --dataset synthetic --preset small-km
    for n in 1 2; do
      ship "$runs/table4-pilot-nus$n" "nuscenes-$n" none "p2b-nuscenes$n-u" "${nus[@]}"
      ship "$runs/table4-pilot-nus$n" "nuscenes-$n" decorrelation "p2b-nuscenes$n-w" "${nus[@]}"
    done ;;
  scene)
    for n in 1 2; do
      if [ ! -d "$runs/table4-pilot-nus$n-scene" ]; then continue; fi
      for arm in none decorrelation; do
        suffix=$([ "$arm" = none ] && echo u || echo w)
        ship "$runs/table4-pilot-nus$n-scene" "nuscenes-$n" "$arm" "p2b-nuscenes$n-$suffix" \
          "${nus[@]}" --nuscenes-frame scene
      done
    done ;;
  last-s)
    small=(--dataset synthetic --preset small-km)
    PILOT='ARMS="none sam" PARALLEL=3' ship "$runs/table4-pilot-kitti2-s" kitti-2 sam \
      p2b-kitti2-s "${small[@]}"
    PILOT='TRACKER=bat ARMS="none sam" PARALLEL=3' ship "$runs/table4-pilot-bat-kitti1-s" \
      kitti-1 sam bat-kitti1-s "${small[@]}" ;;
  *) echo "table4_ship.sh: CELLS must be lidar, scene or last-s, got '$cells'" >&2; exit 2 ;;
esac
python scripts/backfill_provenance.py
