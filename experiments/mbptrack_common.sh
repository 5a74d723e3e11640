# Sourced by experiments/mbptrack_ship.sh and experiments/mbptrack_light.sh: the set-up of the
# kitti-1 MBPTrack runs at the shipped files' budget (docs/mbptrack.md, "Shipped-budget runs").
export DEVICE=${DEVICE:-cpu} OMP_NUM_THREADS=1 PYTHONUNBUFFERED=1
source experiments/train_commands.sh
# MBPTrack's reference optimiser settings; its memory samples refuse the size jitter
mbptrack=(--size-jitter 0 --set adam_beta1=0.5 --set adam_eps=1e-6)
world=(--preset default --seed 0 --setting kitti-1)

resume_flag() {  # OUT: --resume where OUT holds an unfinished run
  if [ -e "$1/config.yaml" ]; then echo --resume; fi
}

train_mbptrack_u() {  # SIZE SEED OUT LOG: a -U run at the shipped budget, kept once done
  if [ -e "$3/done" ]; then return; fi
  # shellcheck disable=SC2046 # an empty or one-word flag
  train_u mbptrack kitti-1 "$1" 0 0 --epochs 32 --set lr_step_epochs=21 --set val_every=4 \
    "${mbptrack[@]}" --seed "$2" --out "$3" $(resume_flag "$3") >"$4" 2>&1
  touch "$3/done"
}

train_mbptrack_u_seeds() {  # SIZE ROOT TAG: seeds 0 and 1 side by side into ROOT/mbptrack-TAG-sSEED
  local seed
  for seed in 0 1; do
    train_mbptrack_u "$1" "$seed" "$2/mbptrack-$3-s$seed" "$2/logs/$3-s$seed.log" &
  done
  wait
}
