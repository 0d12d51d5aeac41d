#!/usr/bin/env bash
# Set up flamenerf (scripts/setup.sh) and everything its tests need, then run them.
# The viewer's browser test drives Debian's Chromium headless: it is installed with apt when
# missing (through sudo only when not root). Extra arguments go to pytest, e.g.
#   bash scripts/test.sh -m "not slow"      # the one-minute loop
set -euo pipefail
cd "$(dirname "$0")/.."
if [ -z "${FLAMENERF_CHROMIUM:-}" ] && ! command -v chromium >/dev/null 2>&1 \
    && ! command -v chromium-browser >/dev/null 2>&1; then
  SUDO=""
  if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
  echo "installing Chromium for the viewer test (apt-get install chromium)"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq chromium >/dev/null
fi
bash scripts/setup.sh
.venv/bin/python -m pytest "$@"
