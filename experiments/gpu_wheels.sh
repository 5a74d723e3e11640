#!/usr/bin/env bash
# The wheels the lent GPU machine's image lacks (Python 3.12, torch with CUDA, no gymnasium /
# farama-notifications / platformdirs / stable-baselines3: docs/performance.md, "GPU"), into
# .whl (ignored by git). Run it here before a device call and name .whl in the call's `carry`;
# experiments/gpu_common.sh installs them there with --target. numba is left out (its llvmlite
# wheel alone is ~42 MB, most of what a call may carry): without numba on the device the point
# ops take their torch paths there, on the GPU and in gpu_speed.sh's CPU column alike.
#   bash experiments/gpu_wheels.sh [PYTHON_VERSION]      # default 3.12
set -euo pipefail
PYTHON_VERSION=${1:-3.12}
rm -rf .whl
mkdir -p .whl
python3 -m pip download --quiet --no-deps --only-binary=:all: --python-version "$PYTHON_VERSION" \
  -d .whl gymnasium==1.4.0 farama-notifications==0.0.6 platformdirs==4.14.9 \
  stable_baselines3==2.9.2
ls .whl
