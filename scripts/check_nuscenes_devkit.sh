#!/usr/bin/env bash
# Cross-check envs.data.NuScenesTracking against the official nuScenes devkit.
#
# Builds a separate virtual environment with nuscenes-devkit (it pins numpy<2 and Shapely 2.0,
# so it never enters the project's environment), generates the synthetic world in nuScenes
# layout (or takes DATAROOT/VERSION), dumps what the devkit reads (every annotation's LIDAR_TOP
# box through get_sample_data, every instance's annotation count) and compares it with the
# project's reader to 1e-4. Needs PyPI (or a mirror) the first time only.
#
#   scripts/check_nuscenes_devkit.sh                       # tiny synthetic world, v1.0-mini
#   scripts/check_nuscenes_devkit.sh DATAROOT v1.0-mini    # an existing nuScenes dataroot
#
# Environment: NUSCENES_DEVKIT_VENV (default .venv-nuscenes-devkit), PYTHON (default python3,
# the project's interpreter).
set -euo pipefail
cd "$(dirname "$0")/.."
VENV="${NUSCENES_DEVKIT_VENV:-.venv-nuscenes-devkit}"
PY="${PYTHON:-python3}"
if [ ! -x "$VENV/bin/python" ] || ! "$VENV/bin/python" -c "import nuscenes" 2>/dev/null; then
    echo "building $VENV with nuscenes-devkit"
    python3 -m venv "$VENV"
    "$VENV/bin/pip" install --quiet --upgrade pip
    "$VENV/bin/pip" install --quiet nuscenes-devkit
fi
"$VENV/bin/python" -c "import importlib.metadata as m; print('nuscenes-devkit', m.version('nuscenes-devkit'))"
WORK="$(mktemp -d)"
trap 'rm -rf "$WORK"' EXIT
if [ $# -ge 2 ]; then
    ROOT="$1"; VERSION="$2"
else
    ROOT="$WORK/world"; VERSION="v1.0-mini"
    PYTHONPATH="$PWD" "$PY" -c "
from envs.synthetic.nuscenes_layout import generate_nuscenes_world
generate_nuscenes_world('$ROOT', 'tiny', version='$VERSION', progress=False)"
fi
"$VENV/bin/python" scripts/nuscenes_devkit_dump.py "$ROOT" "$VERSION" "$WORK/devkit.json"
PYTHONPATH="$PWD" "$PY" scripts/nuscenes_devkit_compare.py "$ROOT" "$VERSION" "$WORK/devkit.json"
