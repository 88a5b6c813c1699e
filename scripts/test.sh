#!/usr/bin/env bash
# Set up, then run the whole test suite (real processes, real Zenoh on loopback, real PyBullet).
# Extra arguments go to pytest (e.g. -m "not slow", -k stack).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/python -m pytest "$@"
