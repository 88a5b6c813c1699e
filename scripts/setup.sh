#!/usr/bin/env bash
# Set up drivebench from scratch: a virtual environment in .venv with drivebench and its test tools.
# Needs only Python >= 3.11 (set PYTHON=/path/to/python3.11 to choose one). Safe to run again: when nothing it
# installs from has changed since the last run (pyproject files, this script, the Python), it does nothing.
# pip's output goes to .venv/setup.log; on failure its last lines are shown.
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
LOG=.venv/setup.log
STAMP=.venv/.drivebench-setup
# Editable installs: source edits need no reinstall, only changes to what pip reads.
DIGEST='import hashlib, sys; print(hashlib.sha256(sys.stdin.buffer.read()).hexdigest(), sys.version)'
wanted=$(cat pyproject.toml examples/my_brain/pyproject.toml scripts/setup.sh tools/mcap-validate/package-lock.json |
         .venv/bin/python -c "$DIGEST")
validator_ready() { ! command -v npm >/dev/null 2>&1 || [ -d tools/mcap-validate/node_modules ]; }
if [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$wanted" ] && validator_ready &&
  .venv/bin/python -c "import orchestrator, my_brain" 2>/dev/null; then
  exit 0  # nothing changed since the last set-up
fi

pip_install() {
  if ! .venv/bin/python -m pip install --disable-pip-version-check "$@" >>"$LOG" 2>&1; then
    echo "scripts/setup.sh: pip install $* failed; the end of $LOG:" >&2
    tail -n 20 "$LOG" >&2
    exit 1
  fi
}

echo "setting up .venv (log: $LOG) ..." >&2
: >"$LOG"
pip_install --upgrade pip
# Neural brains need torch. Pin the version that is installed when none is there yet: a normal torch anywhere, and
# the CPU build that machines without a GPU keep on disk (a loose requirement would fetch a multi-GB CUDA build).
if ! .venv/bin/python -c "import torch" 2>/dev/null; then
  pip_install "torch==${DRIVEBENCH_TORCH_VERSION:-2.13.0}"
fi
pip_install -e ".[stack,test,ml,gl,cluster,bm,rl]"  # cluster: Ray, so CI tests --ray; bm: BM's perturbations; rl: Gymnasium
# The out-of-tree brain example (its own package, found through the drivebench.brains entry point); its tests and
# CI's smoke run of examples/my_brain/compare.yaml need it installed, as a user's package would be.
pip_install -e examples/my_brain
# The independent MCAP validator (official TypeScript reader) used by the recording tests; they skip without it.
if command -v npm >/dev/null 2>&1; then
  if [ ! -d tools/mcap-validate/node_modules ] ||
    [ tools/mcap-validate/package-lock.json -nt tools/mcap-validate/node_modules/.package-lock.json ]; then
    (cd tools/mcap-validate && npm ci --silent --no-audit --no-fund) >>"$LOG" 2>&1
  fi
else
  echo "npm not found: the MCAP validator tests will be skipped (install Node >= 18 and run scripts/setup.sh again)"
fi
echo "$wanted" >"$STAMP"
echo "set up .venv: done" >&2
