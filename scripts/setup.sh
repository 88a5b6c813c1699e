#!/usr/bin/env bash
# Set up drivebench from scratch: a virtual environment in .venv.
#   bash scripts/setup.sh        everything: the whole stack, torch, onnxruntime, Ray, the test and docs tools, the
#                                Node MCAP validator (scripts/test.sh and CI)
#   bash scripts/setup.sh demo   only what a stack on this machine needs (drivebench[stack]: the simulator,
#                                recorder, live view, reports): no torch, Ray, onnxruntime or Node (scripts/demo.sh)
# Needs only Python >= 3.11 (set PYTHON=/path/to/python3.11 to choose one). Safe to run again: when nothing it
# installs from has changed since the last run (pyproject files, this script, the Python) and what is there covers
# what is asked (the full set covers the demo's), it does nothing and prints nothing.
# pip's output goes to .venv/setup.log, and the packages it fetches are named on stderr as it goes; on failure the
# log's last lines are shown.
set -euo pipefail
cd "$(dirname "$0")/.."
PROFILE=${1:-full}
case "$PROFILE" in full | demo) ;; *) echo "scripts/setup.sh: unknown set '$PROFILE' (full or demo)" >&2; exit 2 ;; esac
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
have=$(cat "$STAMP" 2>/dev/null || true)
if [ "$have" = "$wanted full" ] && validator_ready && .venv/bin/python -c "import orchestrator, my_brain" 2>/dev/null; then
  exit 0  # nothing changed since the last full set-up, which covers the demo's
fi
if [ "$PROFILE" = demo ] && [ "$have" = "$wanted demo" ] && .venv/bin/python -c "import orchestrator" 2>/dev/null; then
  exit 0
fi

pip_install() {
  # pip's whole output to the log; the packages it collects, one line each, to stderr (progress for a first install).
  if ! .venv/bin/python -m pip install --disable-pip-version-check "$@" 2>&1 | tee -a "$LOG" |
    { grep --line-buffered -E '^(Collecting|Installing collected)' | sed -u -E 's/^(.{0,110}).*/  \1/' >&2 || true; }; then
    echo "scripts/setup.sh: pip install $* failed; the end of $LOG:" >&2
    tail -n 20 "$LOG" >&2
    exit 1
  fi
}

echo "setting up .venv ($PROFILE; pip's log: $LOG) ..." >&2
: >"$LOG"
.venv/bin/python -m pip install --disable-pip-version-check --quiet --upgrade pip >>"$LOG" 2>&1
trim_pybullet() {
  # As the Docker image does: pybullet's wheel carries ~126 MB of debug symbols and ~170 MB of example robots and
  # environments that drivebench never loads (it builds its own scene). Checked by connecting once afterwards.
  local site
  site=$(.venv/bin/python -c "import sysconfig; print(sysconfig.get_paths()['purelib'])")
  rm -rf "$site"/pybullet_data "$site"/pybullet_envs "$site"/pybullet_examples "$site"/pybullet_robots \
    "$site"/pybullet_utils
  if command -v strip >/dev/null 2>&1; then strip --strip-unneeded "$site"/pybullet*.so; fi
  .venv/bin/python -c "import pybullet; pybullet.connect(pybullet.DIRECT); pybullet.disconnect()" >>"$LOG" 2>&1
}

if [ "$PROFILE" = demo ]; then
  pip_install -e ".[stack]"
  trim_pybullet
  echo "$wanted demo" >"$STAMP"
  echo "set up .venv (demo): done; bash scripts/setup.sh adds torch, Ray and the test tools" >&2
  exit 0
fi
# Neural brains need torch. Pin the version that is installed when none is there yet: a normal torch anywhere, and
# the CPU build that machines without a GPU keep on disk (a loose requirement would fetch a multi-GB CUDA build).
if ! .venv/bin/python -c "import torch" 2>/dev/null; then
  pip_install "torch==${DRIVEBENCH_TORCH_VERSION:-2.13.0}"
fi
pip_install -e ".[stack,test,docs,ml,gl,cluster,bm,rl,board]"  # cluster: Ray, for --ray; docs: mkdocs --strict; bm, rl; board
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
# A sandboxed brain host (drivebench run --sandbox, a challenge server) runs inside bubblewrap, a system package.
if ! command -v bwrap >/dev/null 2>&1; then
  echo "bwrap not found: --sandbox and its tests need bubblewrap (Debian: apt-get install bubblewrap; .ci/run installs it)"
fi
echo "$wanted full" >"$STAMP"
echo "set up .venv: done" >&2
