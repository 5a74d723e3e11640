#!/usr/bin/env bash
# The learned trackers' loops on the lent GPU machine, with the CPU figures of the same commit
# beside them (issue 41 item 6), in one device call of under 10 minutes:
#   bash experiments/gpu_speed.sh                 # on the GPU machine: $OUT/gpu_speed.md
#   bash experiments/gpu_speed.sh --device cpu    # smoke: a tiny version, CPU only (~1 CPU min)
# Measures act frames/s at batch 1 and 32, eval frames/s, finetune env steps/s and training
# samples/s (experiments/gpu_speed.py says how); the device and the CPU measurements run side
# by side, each in its own single-threaded processes (the machine has 16 cores). Set-up (wheels,
# PYTHONPATH, $OUT): experiments/gpu_common.sh; the wheels come from `bash experiments/gpu_wheels.sh`
# here, carried along (`carry: [".whl"]`).
set -euo pipefail
DEVICE_ARG=cuda
if [ "${1:-}" = "--device" ]; then
  DEVICE_ARG=${2:?--device needs a value}
elif [ -n "${1:-}" ]; then
  echo "usage: bash experiments/gpu_speed.sh [--device cpu]" >&2
  exit 2
fi
DEVICE=$DEVICE_ARG
source experiments/gpu_common.sh
SMOKE=()
if [ "$DEVICE_ARG" = cpu ]; then
  SMOKE=(--smoke)
fi
python3 -c "from envs.synthetic import ensure_world
for preset in ('small', 'tiny'):
    print(ensure_world(preset=preset, seed=0))"
start=$SECONDS
pids=()
if [ "$DEVICE_ARG" != cpu ]; then
  python3 experiments/gpu_speed.py --device "$DEVICE_ARG" --out "$OUT/speed-device.json" \
    >"$OUT/speed-device.log" 2>&1 &
  pids+=($!)
fi
python3 experiments/gpu_speed.py --device cpu "${SMOKE[@]}" --out "$OUT/speed-cpu.json" \
  >"$OUT/speed-cpu.log" 2>&1 &
pids+=($!)
status=0
for pid in "${pids[@]}"; do
  wait "$pid" || status=1
done
if [ $status -ne 0 ]; then
  tail -n 20 "$OUT"/speed-*.log >&2
  exit 1
fi
python3 - "$OUT" "$(git rev-parse --short HEAD)" $((SECONDS - start)) <<'PY'
import json
import sys
from pathlib import Path

out, commit, seconds = Path(sys.argv[1]), sys.argv[2], sys.argv[3]
columns = [json.loads(p.read_text()) for p in (out / "speed-device.json", out / "speed-cpu.json")
           if p.exists()]
units = {"act b1": "frames/s", "eval": "frames/s (8 envs)", "finetune": "env steps/s",
         "train": "samples/s (P2B slim -U)"}
keys = [k for k in columns[0] if k != "device"]
lines = [f"Commit {commit}, measured in {seconds} s (experiments/gpu_speed.sh).", "",
         "| measure | " + " | ".join(c["device"] for c in columns) + " |",
         "| --- |" + " --- |" * len(columns)]
for key in keys:
    unit = units.get(key, "frames/s")
    cells = " | ".join(f"{c[key]:.1f}" if key in c else "-" for c in columns)
    lines.append(f"| {key} ({unit}) | {cells} |")
table = "\n".join(lines) + "\n"
(out / "gpu_speed.md").write_text(table)
print(table)
PY
