#!/usr/bin/env bash
# Sets up the environment and runs the main job on embedded defaults (no servers): `midview demo`
# synthesises the `isprs` aerial-ground survey (`--preset small` for the older, easier one), runs the whole midview pipeline and the direct baselines
# on it, prints one table and writes runs/demo/report.html. Extra arguments go to `midview demo`.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
VENV=${MIDVIEW_VENV:-.venv}
exec "$VENV/bin/midview" demo "$@"
