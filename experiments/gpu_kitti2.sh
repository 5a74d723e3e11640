#!/usr/bin/env bash
# Session 20's two calls on the lent GPU machine (NVIDIA H200; docs/checkpoints.md "kitti-2,
# second attempt", docs/performance.md "GPU"), each one device call:
#   bash experiments/gpu_kitti2.sh check  # CUDA tests, training throughput, world 0, epoch time
#   bash experiments/gpu_kitti2.sh train  # the registered kitti-2 P2B runs, checkpoints to $OUT
# The device image has torch but not gymnasium / platformdirs / stable-baselines3: those travel
# as wheels in .whl (docs/performance.md says how). Outputs under $OUT (/tmp/gpu-out elsewhere).
# Validation every 3rd / 6th / 2nd epoch: on that machine one val pass costs three training
# epochs (amended after the check call's timing, before any run's Success was read).
set -uo pipefail
OUT=${OUT:-/tmp/gpu-out}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 POINTTRACK_CACHE=/tmp/ptcache OMP_NUM_THREADS=1
if [ -d .whl ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl || exit 1
  export PYTHONPATH=/tmp/site:$PWD
else
  export PYTHONPATH=$PWD
fi
WORLD="from envs.synthetic import ensure_world; print(ensure_world(preset='default', seed=0))"

train_u() {  # the registered -U flags (docs/checkpoints.md), on the GPU; extra flags after
  python3 -m training.cli train --tracker p2b --setting kitti-2 --weighting none \
    --dataset synthetic --preset default --model-size slim --batch-size 16 \
    --iters-per-epoch 50 --lr 1e-3 --size-jitter 0.3 --ema-decay 0.995 --threads 1 \
    --val-max-tracklets 16 --val-max-frames 40 --seed 0 --device cuda --num-workers 6 \
    --no-progress "$@"
}
train_w() {  # U_RUN OUT_RUN SECONDS: the registered -W run from U_RUN's best.pt
  timeout "$3" python3 -m training.cli train --tracker p2b --setting kitti-2 \
    --weighting decorrelation --dataset synthetic --preset default --model-size slim \
    --batch-size 16 --iters-per-epoch 50 --lr 1e-4 --set lr_step_epochs=6 --epochs 8 \
    --set val_every=2 --size-jitter 0.3 --ema-decay 0.995 --threads 1 --val-max-tracklets 16 \
    --val-max-frames 40 --seed 13 --init-weights "$1/best.pt" --device cuda --num-workers 6 \
    --no-progress --out "$2"
}

case "${1:-}" in
check)
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
  python3 -c "import torch; print('torch', torch.__version__, torch.cuda.get_device_name())"
  # generated in its own session so that it outlives this call on a warm machine
  setsid python3 -c "$WORLD" >/tmp/world.log 2>&1 </dev/null &
  python3 -m pytest -q -p no:cacheprovider tests/test_cuda.py tests/test_ops.py 2>&1 |
    tee "$OUT/pytest.log" | tail -30
  for size in slim default; do
    python3 benchmarks/bench_training.py --trackers p2b,bat,gpt --modes none \
      --config "$size" --batch 16 --steps 4 --device cuda --workers 4 --recipe v1
  done 2>&1 | tee "$OUT/bench.log"
  for _ in $(seq 120); do grep -q worlds /tmp/world.log && break; sleep 1; done
  cat /tmp/world.log
  start=$SECONDS
  timeout 90 bash -c "$(declare -f train_u); train_u --epochs 2 --out /tmp/smoke" \
    >"$OUT/smoke.log" 2>&1
  rc=$?
  echo "2 epochs (800 samples + 2 vals): $((SECONDS - start)) s, rc $rc"
  tail -4 "$OUT/smoke.log"
  ;;
train)
  DEADLINE=$((SECONDS + ${BUDGET_S:-480}))
  python3 -c "$WORLD"
  mkdir -p runs20
  (
    timeout $((DEADLINE - SECONDS - 150)) bash -c "$(declare -f train_u); train_u \
      --epochs 30 --set lr_step_epochs=20 --set val_every=3 --out runs20/p2b-kitti2-u" \
      >"$OUT/u30.log" 2>&1
    train_w runs20/p2b-kitti2-u runs20/p2b-kitti2-w $((DEADLINE - SECONDS - 20)) \
      >"$OUT/w30.log" 2>&1
  ) &
  if [ "${LONG:-1}" = 1 ]; then
    (
      timeout $((DEADLINE - SECONDS - 110)) bash -c "$(declare -f train_u); train_u \
        --epochs 60 --set lr_step_epochs=40 --set val_every=6 \
        --out runs20/p2b-kitti2-u-60" >"$OUT/u60.log" 2>&1
      train_w runs20/p2b-kitti2-u-60 runs20/p2b-kitti2-w-60 $((DEADLINE - SECONDS - 20)) \
        >"$OUT/w60.log" 2>&1
    ) &
  fi
  wait
  for run in runs20/*/; do
    tar -cf "$OUT/$(basename "$run").tar" -C runs20 "$(basename "$run")"
  done
  tail -n 2 "$OUT"/*.log
  ls -la "$OUT"
  ;;
*)
  echo "usage: bash experiments/gpu_kitti2.sh check|train" >&2
  exit 2
  ;;
esac
