#!/usr/bin/env bash
# One command: install (CPU torch pinned first), check formatting and lint, build the docs site
# (warnings are errors), run the test suite. The optional extras are installed so that their
# tests run here rather than skip.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m pip install --quiet torch==2.13.0
# every extra, so the tests of each (video, viewer, Ray sweeps, ...) run instead of skipping
python3 -m pip install --quiet -e ".[test,video,viewer,tensorboard,docs,fast,sweep]"
python3 -m ruff format --check .
python3 -m ruff check .
site_dir="$(mktemp -d)"
NO_MKDOCS_2_WARNING=1 python3 -m mkdocs build --strict --quiet --site-dir "$site_dir"
rm -rf "$site_dir"
# CI runs the slow tests too; plain `pytest` runs the fast set. -rs: one line per skipped test
# with its reason (a skip is legitimate only for a missing machine feature: CUDA, shared data).
python3 -m pytest -q -rs -m "slow or not slow"
