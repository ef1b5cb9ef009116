#!/usr/bin/env bash
# Set up ucad-cl on a fresh machine: a virtual environment in .venv with the package (editable)
# and its test extras, and the fast OpenCL runtime.
#
# OpenCL comes from PyPI (pyopencl[pocl]), but the PoCL that pyopencl's wheels bundle (3.0-rc2,
# LLVM 14) runs our kernels several times slower than Debian/Ubuntu's PoCL 3.1 (LLVM 15), and
# cannot compile at all on CPUs newer than LLVM 14 knows (e.g. AMD Zen 5, pocl issue #1049).
# Measured on an AMD EPYC Zen 3: exact search 8.2x, Canny 3.3-3.9x (docs/OPENCL.md). So,
# wherever apt-get works, this installs Debian/Ubuntu's pocl-opencl-icd, which the same pyopencl
# finds as a second platform and ucad-index then picks by default (`ucad-index info` says which
# and why). Idempotent: nothing is installed twice, and it is quiet when all is in place.
#
#   EXTRAS=bench bash scripts/setup.sh    # also the bench peers (open3d, faiss-cpu)
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip >/dev/null
.venv/bin/python -m pip install -q -e ".[test${EXTRAS:+,$EXTRAS}]"

SUDO=""; [ "$(id -u)" = 0 ] || SUDO="sudo"
apt_install() {            # apt_install PACKAGE...: quiet; a failure is reported, not fatal
  command -v apt-get >/dev/null || return 1
  { $SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "$@"; } \
    >/dev/null 2>&1
}
if ! dpkg -s pocl-opencl-icd >/dev/null 2>&1; then
  if command -v apt-get >/dev/null; then
    echo "setup: installing Debian/Ubuntu's pocl-opencl-icd (PoCL built for this CPU family)" >&2
    apt_install pocl-opencl-icd ||
      echo "setup: apt-get install pocl-opencl-icd failed; ucad-index falls back to the PyPI PoCL" >&2
  elif ! .venv/bin/ucad-index info >/dev/null 2>&1; then
    echo "setup: no apt-get and no OpenCL device that compiles; install a PoCL or vendor OpenCL" \
         "ICD by hand (see docs/OPENCL.md)" >&2
  fi
fi
if [[ ",${EXTRAS:-}," == *",bench,"* ]] && ! .venv/bin/python -c "import open3d" 2>/dev/null; then
  apt_install libusb-1.0-0 || true          # Open3D's wheel links libusb-1.0 (Debian: libusb-1.0-0)
fi
.venv/bin/ucad-index info
