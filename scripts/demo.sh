#!/usr/bin/env bash
# One command: install (CPU torch pinned first) and run the demo.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m pip install --quiet torch==2.13.0
python3 -m pip install --quiet -e ".[fast]"  # numba: the compiled point ops
pointtrack demo "$@"
