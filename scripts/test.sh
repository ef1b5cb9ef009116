#!/usr/bin/env bash
# The test command: set up (idempotent) and run the whole suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
bash scripts/catalog-venv.sh                    # the reader alone (no OpenCL), tests/test_reader.py
export UCAD_REQUIRE_CATALOG_VENV=1              # ... which must then run, not skip
.venv/bin/ruff check --no-cache .               # lint rules: pyproject.toml [tool.ruff]
.venv/bin/mypy --no-incremental                 # typed modules: pyproject.toml [tool.mypy]
# kernel tests run once per OpenCL device (tests/conftest.py); "all": both PoCL builds when both
# are installed
export UCAD_TEST_DEVICES="${UCAD_TEST_DEVICES:-all}"
exec .venv/bin/python -m pytest -q -p no:cacheprovider "$@"
