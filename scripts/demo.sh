#!/usr/bin/env bash
# Sets up the environment and runs the main job on embedded defaults (no servers):
# renders the synthetic `small` survey and measures the direct-matching baselines on it.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
VENV=${MIDVIEW_VENV:-.venv}
exec "$VENV/bin/python" bench/baselines.py "$@"
