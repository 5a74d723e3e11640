#!/usr/bin/env bash
# One command: install (CPU torch pinned first) and run the test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m pip install --quiet torch==2.13.0
python3 -m pip install --quiet -e ".[test]"
# CI runs the slow tests too (about a minute more); plain `pytest` runs the fast set.
python3 -m pytest -q -m "slow or not slow"
