#!/usr/bin/env bash
# Refresh requirements.lock from requirements.txt: every package the project installs, at an exact
# version, with the sha256 hashes the index gives (pip-compile --generate-hashes, pip-tools).
# Run after changing requirements.txt; commit both files. Needs Python 3.11 (the target interpreter).
# torch resolves to the CPU wheel 2.13.0+cpu that pip's find-links folder on this kind of machine holds.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
TOOLS="${PERCEPTION_CONFIG_LOCK_VENV:-$ROOT/.venv-lock}"
PYTHON_BIN="${PYTHON:-python3.11}"
if [ ! -x "$TOOLS/bin/pip-compile" ]; then
  "$PYTHON_BIN" -m venv "$TOOLS"
  "$TOOLS/bin/python" -m pip install -q pip==26.3 pip-tools==7.6.2
fi
cd "$ROOT"
CUSTOM_COMPILE_COMMAND="./scripts/lock.sh" "$TOOLS/bin/pip-compile" --quiet --generate-hashes --allow-unsafe \
  --strip-extras --no-emit-index-url --no-emit-find-links --output-file requirements.lock requirements.txt
echo "[lock] wrote requirements.lock ($(grep -c '^[A-Za-z0-9]' requirements.lock) packages)"
