#!/usr/bin/env bash
# Re-record tests/data/env_golden.json: the hashes of seeded episodes and the tiny world's
# fingerprint that tests/test_env_golden.py compares against. Only for an intended change of the
# env contract or of the synthetic generator (say which in the commit that carries the new file).
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHONPATH="$PWD" python3 tests/test_env_golden.py --write
git diff --stat -- tests/data/env_golden.json
