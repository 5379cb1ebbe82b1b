#!/usr/bin/env bash
# The main job on a fresh machine: install (CPU torch first), then benchmark, controllers and report.
set -euo pipefail
cd "$(dirname "$0")/.."
python -m pip install --quiet --upgrade pip
python -m pip install --quiet torch==2.13.0
python -m pip install --quiet -e ".[dev]"
wl run --out results "$@"
