#!/usr/bin/env bash
# Set up flamenerf (scripts/setup.sh) and everything its tests need, then run them.
# The viewer's browser test drives Debian's Chromium headless, and the hash-grid kernel
# needs a C compiler: both are installed with apt when missing (through sudo only when not
# root). Extra arguments go to pytest, e.g.
#   bash scripts/test.sh -m "not slow"      # the quick loop: ~70 s on 2 cores, no end-to-end runs
set -euo pipefail
cd "$(dirname "$0")/.."
SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
PACKAGES=()
if [ -z "${FLAMENERF_CHROMIUM:-}" ] && ! command -v chromium >/dev/null 2>&1 \
    && ! command -v chromium-browser >/dev/null 2>&1; then
  PACKAGES+=(chromium)
fi
# the C kernels (cpu_kernels.py: the hash grid, the nearest mesh vertices) are built with
# cc; the tests check they build and agree with the PyTorch reference and SciPy's k-d tree
# (a slim image may lack a compiler)
if ! command -v cc >/dev/null 2>&1 && ! command -v gcc >/dev/null 2>&1; then
  PACKAGES+=(gcc libc6-dev)
fi
if [ ${#PACKAGES[@]} -gt 0 ]; then
  echo "installing ${PACKAGES[*]} for the tests (apt-get install)"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${PACKAGES[@]}" >/dev/null
fi
bash scripts/setup.sh
.venv/bin/python -m pytest "$@"
