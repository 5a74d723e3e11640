# Sourced by the experiments/gpu_*.sh scripts: set-up on the lent GPU machine, then the
# registered -U / -W training commands (experiments/train_commands.sh). The device image has torch
# but not gymnasium / platformdirs / stable-baselines3: those travel as wheels in .whl
# (`bash experiments/gpu_wheels.sh`; docs/performance.md, "GPU"). Outputs go under $OUT (/tmp/gpu-out elsewhere).
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
source experiments/train_commands.sh

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
