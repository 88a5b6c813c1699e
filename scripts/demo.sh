#!/usr/bin/env bash
# Set up what the demo needs (once; a quiet no-op after), then drive one lap of the simple circuit with the
# explicit brain, every component its own process.
# Extra arguments go to `drivebench run` (e.g. --camera 640x480 --json).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh demo  # the stack only: no torch, Ray, onnxruntime or Node (scripts/setup.sh adds them)
exec .venv/bin/drivebench run --circuit simple --brain explicit --laps 1 "$@"
