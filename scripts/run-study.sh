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
.venv/bin/snakemake --cores "${CORES:-all}" "$@"
.venv/bin/snakemake "$@" --report results/report.html
echo "report: $ROOT/results/report.html"
