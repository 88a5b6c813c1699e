#!/usr/bin/env bash
# Set up drivebench from scratch: a virtual environment in .venv with drivebench and its test tools.
# Needs only Python >= 3.11 (set PYTHON=/path/to/python3.11 to choose one). Safe to run again.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
if ! "$PYTHON" -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null; then
  echo "drivebench needs Python >= 3.11; '$PYTHON' is $("$PYTHON" --version 2>&1). Set PYTHON=..." >&2
  exit 1
fi
if [ ! -x .venv/bin/python ]; then
  "$PYTHON" -m venv .venv
fi
.venv/bin/python -m pip install --quiet --disable-pip-version-check --upgrade pip
# Neural brains need torch. Pin the version that is installed when none is there yet: a normal torch anywhere, and
# the CPU build that machines without a GPU keep on disk (a loose requirement would fetch a multi-GB CUDA build).
if ! .venv/bin/python -c "import torch" 2>/dev/null; then
  .venv/bin/python -m pip install --quiet --disable-pip-version-check "torch==${DRIVEBENCH_TORCH_VERSION:-2.13.0}"
fi
.venv/bin/python -m pip install --quiet --disable-pip-version-check -e ".[test,ml]"
# The out-of-tree brain example (its own package, found through the drivebench.brains entry point); its tests and
# CI's smoke run of examples/my_brain/compare.yaml need it installed, as a user's package would be.
.venv/bin/python -m pip install --quiet --disable-pip-version-check -e examples/my_brain
# The independent MCAP validator (official TypeScript reader) used by the recording tests; they skip without it.
if command -v npm >/dev/null 2>&1; then
  if [ ! -d tools/mcap-validate/node_modules ] ||
    [ tools/mcap-validate/package-lock.json -nt tools/mcap-validate/node_modules/.package-lock.json ]; then
    (cd tools/mcap-validate && npm ci --silent --no-audit --no-fund)
  fi
else
  echo "npm not found: the MCAP validator tests will be skipped (install Node >= 18 and run scripts/setup.sh again)"
fi
