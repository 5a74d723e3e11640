# The registered -U / -W training commands (docs/notes/checkpoints-history.md), sourced by the
# experiments scripts after their set-up: DEVICE (cpu | cuda) must be set; SMOKE=1 cuts every run
# to a few steps. A SECONDS argument of 0 means no deadline (coreutils' timeout).
DEVICE=${DEVICE:?set DEVICE (cpu or cuda) before sourcing experiments/train_commands.sh}
if [ "${SMOKE:-0}" = 1 ]; then
  SMOKE_FLAGS=(--epochs 1 --iters-per-epoch 2 --val-max-tracklets 2 --val-max-frames 5)
else
  SMOKE_FLAGS=()
fi

train_u() {  # TRACKER SETTING SIZE WORKERS SECONDS [flags]: the registered -U run from scratch
  local tracker=$1 setting=$2 size=$3 workers=$4 seconds=$5
  shift 5
  timeout "$seconds" python3 -m training.cli train --tracker "$tracker" --setting "$setting" \
    --weighting none --dataset synthetic --preset default --model-size "$size" --batch-size 16 \
    --iters-per-epoch 50 --lr 1e-3 --size-jitter 0.3 --ema-decay 0.995 --threads 1 \
    --val-max-tracklets 16 --val-max-frames 40 --seed 0 --device "$DEVICE" \
    --num-workers "$workers" --no-progress "$@" "${SMOKE_FLAGS[@]}"
}
train_w() {  # TRACKER SETTING SIZE WORKERS U_RUN OUT_RUN SECONDS [flags]: the registered -W fine-tune
  timeout "$7" python3 -m training.cli train --tracker "$1" --setting "$2" \
    --weighting decorrelation --dataset synthetic --preset default --model-size "$3" \
    --batch-size 16 --iters-per-epoch 50 --lr 1e-4 --set lr_step_epochs=6 --epochs 8 \
    --set val_every=2 --size-jitter 0.3 --ema-decay 0.995 --threads 1 --val-max-tracklets 16 \
    --val-max-frames 40 --seed 13 --init-weights "$5/best.pt" --device "$DEVICE" \
    --num-workers "$4" --no-progress "${@:8}" "${SMOKE_FLAGS[@]}" --out "$6"
}
