#!/usr/bin/env bash
# Session 20's two calls on the lent GPU machine (NVIDIA H200;
# docs/notes/checkpoints-history.md "kitti-2, second attempt", docs/performance.md "GPU"), each
# one device call:
#   bash experiments/gpu_kitti2.sh check  # CUDA tests, training throughput, world 0, epoch time
#   bash experiments/gpu_kitti2.sh train  # the registered kitti-2 P2B runs, checkpoints to $OUT
# Set-up and the training commands: experiments/gpu_common.sh.
# Validation every 3rd / 6th / 2nd epoch: on that machine one val pass costs three training
# epochs (amended after the check call's timing, before any run's Success was read).
set -uo pipefail
source experiments/gpu_common.sh

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
  train_u p2b kitti-2 slim 6 90 --epochs 2 --out /tmp/smoke >"$OUT/smoke.log" 2>&1
  rc=$?
  echo "2 epochs (800 samples + 2 vals): $((SECONDS - start)) s, rc $rc"
  tail -4 "$OUT/smoke.log"
  ;;
train)
  DEADLINE=$((SECONDS + ${BUDGET_S:-480}))
  python3 -c "$WORLD"
  mkdir -p runs20
  (
    train_u p2b kitti-2 slim 6 $((DEADLINE - SECONDS - 150)) --epochs 30 \
      --set lr_step_epochs=20 --set val_every=3 --out runs20/p2b-kitti2-u >"$OUT/u30.log" 2>&1
    train_w p2b kitti-2 slim 6 runs20/p2b-kitti2-u runs20/p2b-kitti2-w \
      $((DEADLINE - SECONDS - 20)) >"$OUT/w30.log" 2>&1
  ) &
  if [ "${LONG:-1}" = 1 ]; then
    (
      train_u p2b kitti-2 slim 6 $((DEADLINE - SECONDS - 110)) --epochs 60 \
        --set lr_step_epochs=40 --set val_every=6 --out runs20/p2b-kitti2-u-60 >"$OUT/u60.log" 2>&1
      train_w p2b kitti-2 slim 6 runs20/p2b-kitti2-u-60 runs20/p2b-kitti2-w-60 \
        $((DEADLINE - SECONDS - 20)) >"$OUT/w60.log" 2>&1
    ) &
  fi
  wait
  tar_runs runs20
  tail -n 2 "$OUT"/*.log
  ls -la "$OUT"
  ;;
*)
  echo "usage: bash experiments/gpu_kitti2.sh check|train" >&2
  exit 2
  ;;
esac
