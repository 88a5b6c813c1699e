#!/usr/bin/env bash
# Set up, then drive one lap of the simple circuit with the explicit brain, every component its own process.
# Extra arguments go to `drivebench run` (e.g. --camera 640x480 --json).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/drivebench run --circuit simple --brain explicit --laps 1 "$@"
