#!/usr/bin/env bash
# MBPTrack kitti-1 files at the shipped files' budget (docs/mbptrack.md, "Shipped-budget runs"):
# two -U runs (training seeds 0 and 1) side by side, the -W fine-tune of the one with the better
# trainer val Success, one `pointtrack select` beside the shipped kitti-1 P2B / BAT / GPT files,
# then the test readings the protocol names. Run again after a kill: training resumes from
# OUT/last.pt, finished steps are kept. STAGE=train stops after the -U runs; SMOKE=1 cuts every
# run to a few steps (experiments/train_commands.sh).
#   bash experiments/mbptrack_ship.sh [ROOT]    # default runs/mbptrack-ship
set -euo pipefail
root=${1:-runs/mbptrack-ship}
source experiments/mbptrack_common.sh
predecessors=(p2b-kitti1-u bat-kitti1-u gpt-kitti1-u p2b-kitti1-w bat-kitti1-w gpt-kitti1-w)
mkdir -p "$root/logs"

train_mbptrack_u_seeds slim "$root" u
if [ "${STAGE:-all}" = train ]; then exit 0; fi

# -W from the -U run with the higher trainer val Success (seed 0 on a tie)
start=$(python3 experiments/mbptrack_ship.py best-val "$root/mbptrack-u-s0" "$root/mbptrack-u-s1")
if [ ! -e "$root/mbptrack-w/done" ]; then
  # shellcheck disable=SC2046
  train_w mbptrack kitti-1 slim 0 "$start" "$root/mbptrack-w" 0 "${mbptrack[@]}" \
    $(resume_flag "$root/mbptrack-w") >"$root/logs/w.log" 2>&1 &
  # the predecessors' never-trained-world reports meanwhile, on the other core (kept in
  # select/parts and reused by the selection below)
  pointtrack select "${predecessors[@]}" previous_box --setting kitti-1 --workers 1 \
    --no-progress --out "$root/select" >"$root/logs/select-predecessors.log" 2>&1
  wait
  touch "$root/mbptrack-w/done"
fi
pointtrack select "$root"/mbptrack-u-s{0,1}/best.pt "$root/mbptrack-w/best.pt" \
  "${predecessors[@]}" previous_box --setting kitti-1 --no-progress --out "$root/select" \
  >"$root/logs/select.log" 2>&1

read -r chosen_u < <(python3 experiments/mbptrack_ship.py first "$root/select/selection.json" \
  "$root"/mbptrack-u-s{0,1}/best.pt)
# the gate: each arm's MBPTrack file against its three predecessors alone (the same pooled
# scores, from the selection's kept reports), written by --save for shipping where it ranks first
for arm in u w; do
  ours=$chosen_u
  if [ "$arm" = w ]; then ours=$root/mbptrack-w/best.pt; fi
  mkdir -p "$root/select-$arm"
  cp -rn "$root/select/parts" "$root/select-$arm/"
  pointtrack select "$ours" {p2b,bat,gpt}-kitti1-$arm --setting kitti-1 --no-progress \
    --out "$root/select-$arm" --save "$root/select-$arm/mbptrack-kitti1-$arm.safetensors" \
    >"$root/logs/select-$arm.log" 2>&1
  python3 experiments/mbptrack_ship.py ship "$root/select-$arm" "mbptrack-kitti1-$arm" \
    --command "bash experiments/mbptrack_ship.sh $root"
done
python3 scripts/backfill_provenance.py

# the test, read once: the first-ranked -U run and the -W run; beside them the shipped files
if [ ! -e "$root/test/done" ]; then
  pointtrack eval --tracker "$chosen_u" "$root/mbptrack-w/best.pt" "${world[@]}" --split test \
    --eval-seeds 0 1 2 --no-progress --out "$root/test" >"$root/logs/test.log" 2>&1
  touch "$root/test/done"
fi
for form in network-alone shipped; do  # every shipped kitti-1 P2B / BAT / GPT file, both ways
  if [ -e "$root/test-$form/done" ]; then continue; fi
  flags=()
  if [ "$form" = network-alone ]; then flags=(--network-alone); fi
  pointtrack eval --tracker "${predecessors[@]}" p2b-kitti1-u-rl gpt-kitti1-u-rl p2b-kitti1-drct \
    "${flags[@]}" "${world[@]}" --split test --eval-seeds 0 1 2 --no-progress \
    --out "$root/test-$form" >"$root/logs/test-$form.log" 2>&1
  touch "$root/test-$form/done"
done
python3 experiments/mbptrack_ship.py report "$root"
