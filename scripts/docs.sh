#!/usr/bin/env bash
# The documentation site (mkdocs, material theme; mkdocs.yml at the root, pages under docs/).
#   bash scripts/docs.sh          build it into site/ with --strict: a broken link or a missing page fails
#   bash scripts/docs.sh serve    serve it at http://127.0.0.1:8000, rebuilt on every save
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
if [ "${1:-build}" = serve ]; then
  NO_MKDOCS_2_WARNING=1 exec .venv/bin/mkdocs serve "${@:2}"
fi
# Not --quiet: it hides the warnings that --strict counts, and the build then passes with broken links.
NO_MKDOCS_2_WARNING=1 exec .venv/bin/mkdocs build --strict "$@"
