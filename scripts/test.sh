#!/usr/bin/env bash
# Sets up the environment, lints, and runs the whole test suite. Extra arguments go to pytest
# (the inner loop: bash scripts/test.sh -m "not slow").
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
VENV=${MIDVIEW_VENV:-.venv}
"$VENV/bin/ruff" check .
"$VENV/bin/ruff" format --check .  # the formatting is ruff's (pre-commit formats on commit)
"$VENV/bin/lint-imports"  # the architecture contracts of pyproject.toml
"$VENV/bin/deptry" .  # no missing, unused or transitive-only dependency
"$VENV/bin/mypy"  # types of api/, workers/, shared/, client/ and services/pipeline/ ([tool.mypy])
# the compose file is validated by tests/test_deploy.py with Debian's docker-compose (no engine needed)
if ! command -v docker-compose >/dev/null && command -v apt-get >/dev/null; then
  (apt-get install -y -qq docker-compose >/dev/null 2>&1 \
    || (apt-get update -qq && apt-get install -y -qq docker-compose >/dev/null 2>&1)) \
    || echo "test: docker-compose could not be installed; the compose check will be skipped"
fi
# headless Chromium and its driver for the dashboard's browser tests (tests/test_dashboard.py)
if ! { command -v chromium && command -v chromedriver; } >/dev/null && command -v apt-get >/dev/null; then
  (apt-get install -y -qq chromium chromium-driver >/dev/null 2>&1 \
    || (apt-get update -qq && apt-get install -y -qq chromium chromium-driver >/dev/null 2>&1)) \
    || echo "test: chromium could not be installed; the browser tests will be skipped"
fi
# a redis-server the fault tests can crash and restart (tests/test_service_faults.py)
if ! command -v redis-server >/dev/null && command -v apt-get >/dev/null; then
  (apt-get install -y -qq redis-server >/dev/null 2>&1 \
    || (apt-get update -qq && apt-get install -y -qq redis-server >/dev/null 2>&1)) \
    || echo "test: redis-server could not be installed; the fault tests will be skipped"
fi
set +e
"$VENV/bin/python" -m pytest -ra --durations=25 "$@"  # the 25 slowest tests: where the suite's time goes
rc=$?
set -e
if [ $rc -eq 5 ]; then echo "pytest collected no tests"; exit 0; fi
exit $rc
