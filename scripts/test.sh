#!/usr/bin/env bash
# Set up, then run the whole test suite (real processes, real Zenoh on loopback, real PyBullet).
# Extra arguments go to pytest (e.g. -m "not slow", -k stack).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
# Where Node is, the MCAP validator must have been installed: its checks fail instead of skipping.
if command -v node >/dev/null 2>&1; then export DRIVEBENCH_REQUIRE_MCAP_VALIDATOR=1; fi
# Lint first: a minute of tests is not worth spending on a file that does not pass it.
.venv/bin/ruff check --quiet . || { echo "scripts/test.sh: ruff found the problems above" >&2; exit 1; }
.venv/bin/ruff format --check --quiet . || { echo "scripts/test.sh: run .venv/bin/ruff format . (files above)" >&2; exit 1; }
# Types of every package ([tool.mypy] in pyproject.toml names them).
.venv/bin/mypy --no-error-summary || { echo "scripts/test.sh: mypy found the problems above" >&2; exit 1; }
# The documentation site, strict: a broken link, anchor or a page a hook cannot generate fails here (seconds).
if ! docs_log=$(NO_MKDOCS_2_WARNING=1 .venv/bin/mkdocs build --strict 2>&1); then
  echo "$docs_log" >&2; echo "scripts/test.sh: the docs build failed (above; bash scripts/docs.sh serve to look)" >&2; exit 1
fi
exec .venv/bin/python -m pytest "$@"
