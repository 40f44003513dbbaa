#!/usr/bin/env bash
# One command: set up everything, build the documentation (scripts/build-docs.sh: fails on any
# warning or broken link) and run the test suite (slow end-to-end tests excluded unless
# VLSFOREST_SLOW=1). Extra arguments go to pytest.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/scripts/bootstrap.sh"
bash "$ROOT/scripts/test-deps.sh"
bash "$ROOT/scripts/build-docs.sh" >/dev/null || { echo "run-tests: the documentation does not build" >&2; exit 1; }
cd "$ROOT"
# the workflow's jobs call the installed `vlsforest` command: the project's environment first
export PATH="$ROOT/.venv/bin:$PATH"
MARK=(-m "not slow")
[ "${VLSFOREST_SLOW:-0}" = "1" ] && MARK=()
set +e
# two pytest-xdist workers (one per core of the CI machines; VLSFOREST_TEST_WORKERS=0 runs in one
# process); --dist loadgroup hands the tests out one at a time, the longest first (tests/conftest.py);
# --durations: the slowest tests at the end of the log (the suite must stay near 20 min on 2 cores)
WORKERS="${VLSFOREST_TEST_WORKERS:-2}"
.venv/bin/python -m pytest -q -p no:cacheprovider -n "$WORKERS" --dist loadgroup --durations=15 \
  "${MARK[@]}" "$@"
rc=$?
set -e
[ $rc -eq 5 ] && { echo "run-tests: pytest collected no tests — failing" >&2; exit 1; }
exit $rc
