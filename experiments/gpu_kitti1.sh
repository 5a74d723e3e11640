#!/usr/bin/env bash
# kitti-1 -U and -W runs for P2B, BAT and GPT on the lent GPU machine
# (docs/notes/checkpoints-history.md "kitti-1 on the GPU machine", protocol written before any
# run). One device call:
#   bash experiments/gpu_kitti1.sh train
# SIZE=default (the papers' widths; default) or slim. The three chains run side by side (4 loader
# workers each on the machine's 16 cores); a -U run (EPOCHS x 800 samples, default 48, lr x0.2
# after two thirds) stops at its share of BUDGET_S (default 560 s, world generation included)
# and its -W starts from its best.pt. Each run comes back as a tar in $OUT: its log, config and
# validated weights as tracker files (-U: best and last, -W: best); the six training logs as
# logs.tar. Set-up and the training commands: experiments/gpu_common.sh (DEVICE=cpu SMOKE=1
# checks this script on the CPU in a few minutes).
set -uo pipefail
source experiments/gpu_common.sh

case "${1:-}" in
train)
  DEADLINE=$((SECONDS + ${BUDGET_S:-560}))
  EPOCHS=${EPOCHS:-48}
  SIZE=${SIZE:-default}
  python3 -c "$WORLD"
  root=runs/gpu-kitti1
  logs=$root/logs
  mkdir -p "$logs"
  for tracker in p2b bat gpt; do
    (
      run=$root/$tracker-kitti1-$SIZE
      train_u "$tracker" kitti-1 "$SIZE" 4 $((DEADLINE - SECONDS - 150)) --epochs "$EPOCHS" \
        --set lr_step_epochs=$((EPOCHS * 2 / 3)) --set val_every=10 --out "$run-u" \
        >"$logs/$tracker-u.log" 2>&1
      train_w "$tracker" kitti-1 "$SIZE" 4 "$run-u" "$run-w" $((DEADLINE - SECONDS - 45)) \
        >"$logs/$tracker-w.log" 2>&1
    ) &
  done
  wait
  # The files back from the device machine: at most 8, of 16 MiB each, 64 MiB together (here:
  # six run tars of 5-12 MB and logs.tar).
  for tracker in p2b bat gpt; do
    export_weights "$root/$tracker-kitti1-$SIZE-u" best last
    export_weights "$root/$tracker-kitti1-$SIZE-w" best
  done
  tar_runs "$root" --exclude=*.pt
  tail -n 2 "$logs"/*.log
  ls -la "$OUT"
  ;;
*)
  echo "usage: bash experiments/gpu_kitti1.sh train" >&2
  exit 2
  ;;
esac
