#!/usr/bin/env bash
# The reader's own environment: .venv-catalog with ONLY ucad_catalog installed (numpy, OpenEXR,
# pyarrow for Parquet; no pyopencl, no trimesh), editable so it always runs the current code.
# Created once and kept; tests/test_reader.py runs the standalone reader in it.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
here=$(pwd)
# (re)create it when missing, broken, or pointing at another checkout's ucad_catalog
if ! .venv-catalog/bin/python -I -c "import sys, numpy, OpenEXR, pyarrow, ucad_catalog as u
sys.exit(0 if u.__file__.startswith('$here/') else 1)" 2>/dev/null; then
  rm -rf .venv-catalog
  "$PY" -m venv .venv-catalog
  log=$(mktemp)
  if ! .venv-catalog/bin/python -m pip install -q -e "./ucad_catalog[parquet]" >"$log" 2>&1; then
    cat "$log" >&2
    exit 1
  fi
  rm -rf "$log" ucad_catalog/build             # the in-tree build folder of that install
fi
