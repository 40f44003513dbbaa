#!/usr/bin/env bash
# One command: set up everything, run the main job (the workflow's default target) on the
# embedded default data, then write the HTML report (results/report.html). Extra arguments go to
# snakemake (e.g. --configfile config/quick.yaml).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/scripts/bootstrap.sh"
cd "$ROOT"
# the workflow's jobs call the installed `vlsforest` command: the project's environment first
export PATH="$ROOT/.venv/bin:$PATH"
# a run killed with kill -9 (or a power cut) leaves Snakemake's lock behind: remove it when no
# Snakemake works in this folder any more, so that this command resumes the run
if bash "$ROOT/scripts/stale-lock.sh" "$ROOT"; then
  echo "run-study: removing the lock of a run that was killed" >&2
  .venv/bin/snakemake --unlock "$@"
fi
.venv/bin/snakemake --cores "${CORES:-all}" "$@"
.venv/bin/snakemake "$@" --report results/report.html
echo "report: $ROOT/results/report.html"
