#!/usr/bin/env bash
# The slow tests, which scripts/run-tests.sh (and CI) leave out: every test marked `slow` (the
# default forest's workflow run and its checks in tests/test_default_forest.py, strict xfail
# included; the documentation's workflow runs): long (the default forest's workflow run alone takes
# about 20 min on 2 cores), in one pytest process, so that the default forest is built once.
# The outcome is recorded as data: benchmarks/results/slow_tests.jsonl (or VLSFOREST_SLOW_RESULTS)
# is replaced by one JSON row per test of this run (date, commit, machine, command, exit code,
# test, outcome, seconds, message; tests/outcome_record.py). Extra arguments go to pytest, e.g.
# tests/test_default_forest.py for that module only; VLSFOREST_DEFAULT_RESULTS=DIR checks an
# existing default-config run instead of building one (tests/test_default_forest.py).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/scripts/bootstrap.sh"
cd "$ROOT"
# the workflow's jobs call the installed `vlsforest` command: the project's environment first
export PATH="$ROOT/.venv/bin:$PATH"
# tests/ holds the recording plugin (loaded by -p before pytest reads tests/conftest.py)
export PYTHONPATH="$ROOT/tests${PYTHONPATH:+:$PYTHONPATH}"
RESULTS="${VLSFOREST_SLOW_RESULTS:-$ROOT/benchmarks/results/slow_tests.jsonl}"
set +e
.venv/bin/python -m pytest -p no:cacheprovider -p no:xdist -p outcome_record --record-outcomes "$RESULTS" \
  -m slow -rA --durations=0 "$@"
rc=$?
set -e
[ $rc -eq 5 ] && { echo "run-slow-tests: pytest collected no tests — failing" >&2; exit 1; }
exit $rc
