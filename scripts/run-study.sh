#!/usr/bin/env bash
# One command: set up everything and run the main job (the workflow's default target) on the
# embedded default data. Extra arguments go to snakemake (e.g. --configfile config/quick.yaml).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/scripts/bootstrap.sh"
cd "$ROOT"
exec .venv/bin/snakemake --cores "${CORES:-all}" "$@"
