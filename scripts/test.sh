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
# a module at a time on MIDVIEW_TEST_WORKERS processes (2: the cores of the usual machine; the tests run
# their pipelines on one thread each, so two modules share the machine), the end-to-end modules first
# (tests/conftest.py); then the tests that assert a latency (marker `alone`), with nothing beside them.
# --durations: the 25 slowest tests, where the suite's time goes. Arguments: one pass with them instead.
pytest_run() {
  set +e
  "$VENV/bin/python" -m pytest -ra --durations=25 "$@"
  local rc=$?
  set -e
  if [ $rc -eq 5 ]; then rc=0; fi  # no test collected (a filter that selects none)
  return $rc
}
parallel=(-n "${MIDVIEW_TEST_WORKERS:-2}" --dist loadfile --no-loadscope-reorder)
if [ $# -gt 0 ]; then
  pytest_run "${parallel[@]}" "$@"
  exit $?
fi
rc=0
pytest_run "${parallel[@]}" -m "not alone" || rc=$?
pytest_run -m alone || rc=$?
exit $rc
