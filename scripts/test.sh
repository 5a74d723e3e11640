#!/usr/bin/env bash
# One command: install (CPU torch pinned first), check formatting and lint, run the test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m pip install --quiet torch==2.13.0
# the sweep extra too, so the Ray tests (tests/test_sweep.py) run instead of skipping
python3 -m pip install --quiet -e ".[test,sweep]"
python3 -m ruff format --check .
python3 -m ruff check .
# CI runs the slow tests too; plain `pytest` runs the fast set.
python3 -m pytest -q -m "slow or not slow"
