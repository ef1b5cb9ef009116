#!/usr/bin/env bash
# Set up ucad-cl on a fresh machine: a virtual environment in .venv with the package (editable)
# and its test extras, then make sure an OpenCL device can really compile kernels.
#
# OpenCL comes from PyPI (pyopencl[pocl]). The PoCL that pyopencl's wheels bundle (3.0-rc2, LLVM 14)
# cannot compile for CPUs newer than LLVM 14 (e.g. AMD Zen 5: "unknown target CPU 'generic'",
# pocl issue #1049). When `ucad-index info` finds no working device, this script installs
# Debian/Ubuntu's pocl-opencl-icd (PoCL 3.1, LLVM 15) with apt-get, which the same pyopencl finds.
#
#   EXTRAS=bench bash scripts/setup.sh    # also the bench peers (open3d, faiss-cpu)
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip >/dev/null
.venv/bin/python -m pip install -q -e ".[test${EXTRAS:+,$EXTRAS}]"

if ! .venv/bin/ucad-index info >/dev/null 2>&1; then
  echo "setup: no OpenCL device compiles kernels with the PyPI PoCL; installing pocl-opencl-icd" >&2
  SUDO=""; [ "$(id -u)" = 0 ] || SUDO="sudo"
  if command -v apt-get >/dev/null; then
    $SUDO apt-get update -qq >/dev/null
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq pocl-opencl-icd >/dev/null
  else
    echo "setup: apt-get not found; install a PoCL or vendor OpenCL ICD by hand" >&2
  fi
fi
if [[ ",${EXTRAS:-}," == *",bench,"* ]] && ! .venv/bin/python -c "import open3d" 2>/dev/null; then
  # Open3D's wheel links libusb-1.0 (Debian: libusb-1.0-0)
  SUDO=""; [ "$(id -u)" = 0 ] || SUDO="sudo"
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null || true
fi
.venv/bin/ucad-index info
