#!/usr/bin/env bash
# One command: set up everything, build the documentation (scripts/build-docs.sh: fails on any
# warning or broken link) and run the test suite: both tiers, the slow tests left out
# (scripts/run-slow-tests.sh runs those). VLSFOREST_TEST_TIER=unit or e2e runs one tier
# (tests/conftest.py says which tests are e2e). Extra arguments go to pytest.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
TIER="${VLSFOREST_TEST_TIER:-all}"
case "$TIER" in
  unit) MARK="not e2e and not slow" ;;
  e2e) MARK="e2e and not slow" ;;
  all) MARK="not slow" ;;
  *) echo "run-tests: error: VLSFOREST_TEST_TIER must be unit, e2e or all, got '$TIER'" >&2; exit 2 ;;
esac
bash "$ROOT/scripts/bootstrap.sh"
bash "$ROOT/scripts/test-deps.sh"
bash "$ROOT/scripts/build-docs.sh" >/dev/null || { echo "run-tests: the documentation does not build" >&2; exit 1; }
cd "$ROOT"
# the workflow's jobs call the installed `vlsforest` command: the project's environment first
export PATH="$ROOT/.venv/bin:$PATH"
set +e
# two pytest-xdist workers (one per core of the CI machines; VLSFOREST_TEST_WORKERS=0 runs in one
# process); --dist loadgroup hands the tests out one at a time, the longest first (tests/conftest.py);
# the quick study is built once for both workers (tests/runwide.py);
# --durations: the slowest tests at the end of the log
WORKERS="${VLSFOREST_TEST_WORKERS:-2}"
.venv/bin/python -m pytest -q -p no:cacheprovider -n "$WORKERS" --dist loadgroup --durations=15 \
  -m "$MARK" "$@"
rc=$?
set -e
[ $rc -eq 5 ] && { echo "run-tests: pytest collected no tests — failing" >&2; exit 1; }
exit $rc
