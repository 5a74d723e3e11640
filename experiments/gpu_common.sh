# Sourced by the experiments/gpu_*.sh scripts: set-up on the lent GPU machine and the
# registered -U / -W training commands (docs/checkpoints.md). The device image has torch but not
# gymnasium / platformdirs / stable-baselines3: those travel as wheels in .whl
# (docs/performance.md, "GPU"). Outputs go under $OUT (/tmp/gpu-out elsewhere).
# DEVICE=cpu SMOKE=1 runs the same commands for a few steps on the CPU, to check a script
# before spending device time on it.
OUT=${OUT:-/tmp/gpu-out}
DEVICE=${DEVICE:-cuda}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 POINTTRACK_CACHE=${POINTTRACK_CACHE:-/tmp/ptcache} OMP_NUM_THREADS=1
if [ -d .whl ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl || exit 1
  export PYTHONPATH=/tmp/site:$PWD
else
  export PYTHONPATH=$PWD
fi
WORLD="from envs.synthetic import ensure_world; print(ensure_world(preset='default', seed=0))"
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
train_w() {  # TRACKER SETTING SIZE WORKERS U_RUN OUT_RUN SECONDS: the registered -W fine-tune
  timeout "$7" python3 -m training.cli train --tracker "$1" --setting "$2" \
    --weighting decorrelation --dataset synthetic --preset default --model-size "$3" \
    --batch-size 16 --iters-per-epoch 50 --lr 1e-4 --set lr_step_epochs=6 --epochs 8 \
    --set val_every=2 --size-jitter 0.3 --ema-decay 0.995 --threads 1 --val-max-tracklets 16 \
    --val-max-frames 40 --seed 13 --init-weights "$5/best.pt" --device "$DEVICE" \
    --num-workers "$4" --no-progress "${SMOKE_FLAGS[@]}" --out "$6"
}
tar_runs() {  # DIR [tar flags]: each run directory under DIR as one tar in $OUT
  local run
  for run in "$1"/*/; do
    tar -cf "$OUT/$(basename "$run").tar" "${@:2}" -C "$1" "$(basename "$run")"
  done
}
export_weights() {  # RUN NAME...: RUN/NAME.pt's validated weights as RUN/NAME.safetensors
  # A papers'-width training checkpoint (weights, EMA, Adam state: ~21 MB) is over the 16 MiB a
  # file may weigh on its way back from the device machine; the tracker file is ~5.5 MB.
  # (`pointtrack train --export` writes best-else-last only, and not for a run its deadline cut.)
  python3 - "$@" <<'PY'
import sys
from pathlib import Path

import trackers
from training.checkpoint import tracker_from_checkpoint

run = Path(sys.argv[1])
for name in sys.argv[2:]:
    if (run / f"{name}.pt").exists():
        trackers.save(tracker_from_checkpoint(run / f"{name}.pt"), run / f"{name}.safetensors")
PY
}
