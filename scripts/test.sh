#!/usr/bin/env bash
# Set up (idempotent), run the lint gate (ruff, ruff.toml), then the whole test suite.
# Extra arguments go to pytest.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
source "$ROOT/scripts/setup_env.sh"
cd "$ROOT"
echo "[lint] ruff check (rules: ruff.toml)"
if ! "$VENV/bin/ruff" check --quiet .; then
  echo "[lint] failed: fix the lines listed above (ruff.toml holds the rules)" >&2
  exit 1
fi
# pytest-xdist: one worker per core (TEST_WORKERS overrides; 0 runs in this process), each test file
# whole on one worker (its module fixtures start nodes or train once), the long files first
# (test/conftest.py: LONG_FILES, kept in that order by --no-loadscope-reorder). Each worker has its
# own ROS domain and Ray folder (test/conftest.py). nproc would count OMP_NUM_THREADS, not cores.
WORKERS="${TEST_WORKERS:-$(env -u OMP_NUM_THREADS -u OMP_THREAD_LIMIT nproc)}"
# One core per process keeps timing tests and worker pools honest on a 2-core machine.
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
exec "$PY" -m pytest test -ra -p no:cacheprovider -p no:dash --timeout=600 \
  -n "$WORKERS" --dist loadfile --no-loadscope-reorder "$@"
