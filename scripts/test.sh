#!/usr/bin/env bash
# One command: install (CPU torch pinned first), check formatting and lint, run the test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m pip install --quiet torch==2.13.0
python3 -m pip install --quiet -e ".[test]"
python3 -m ruff format --check .
python3 -m ruff check .
# CI runs the slow tests too; plain `pytest` runs the fast set. -rs: one line per skipped test
# with its reason (a skip is legitimate only for a missing machine feature: CUDA, shared data).
python3 -m pytest -q -rs -m "slow or not slow"
