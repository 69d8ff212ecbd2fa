#!/usr/bin/env bash
# Sets up the environment, lints, and runs the whole test suite. Extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
VENV=${MIDVIEW_VENV:-.venv}
"$VENV/bin/ruff" check .
set +e
"$VENV/bin/python" -m pytest -ra "$@"
rc=$?
set -e
if [ $rc -eq 5 ]; then echo "pytest collected no tests"; exit 0; fi
exit $rc
