#!/usr/bin/env bash
# System packages that only the test suite needs (sourced by scripts/run-tests.sh after bootstrap):
#   chromium            — renders the HTML report headless (tests/test_report_browser.py)
#   slurm-wlm, munge    — a single-node SLURM cluster on localhost (tests/test_slurm_cluster.py)
# As root they are installed from Debian's packages; otherwise the tests that need them skip and
# say which package is missing. Set VLSFOREST_NO_SYSTEM_TEST_DEPS=1 to skip this step.
set -euo pipefail
[ "${VLSFOREST_NO_SYSTEM_TEST_DEPS:-0}" = "1" ] && exit 0
PKGS=(chromium slurm-wlm munge)
missing=()
for p in "${PKGS[@]}"; do dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p"); done
[ ${#missing[@]} -eq 0 ] && exit 0
if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
  echo "test-deps: installing ${missing[*]} (apt-get; needed by the browser and SLURM tests)" >&2
  if ! (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}") >/dev/null 2>&1; then
    echo "test-deps: could not install ${missing[*]}; the tests that need them will skip" >&2
  fi
else
  echo "test-deps: not root — install ${missing[*]} (e.g. sudo apt-get install ${missing[*]}) to run the browser and SLURM tests; they skip otherwise" >&2
fi
exit 0
