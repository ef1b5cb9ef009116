#!/usr/bin/env bash
# The test command: set up (idempotent) and run the whole suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
bash scripts/catalog-venv.sh                    # the reader alone (no OpenCL), tests/test_reader.py
export UCAD_REQUIRE_CATALOG_VENV=1              # ... which must then run, not skip
exec .venv/bin/python -m pytest -q -p no:cacheprovider "$@"
