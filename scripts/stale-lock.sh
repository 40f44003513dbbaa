#!/usr/bin/env bash
# Exit 0 when the folder DIR holds Snakemake's locks but no Snakemake process works in DIR any
# more (a run killed with kill -9 or a power cut leaves its lock behind); exit 1 otherwise.
# scripts/run-study.sh uses it to remove such a lock before it runs, so that its command resumes
# a killed run.
#   bash scripts/stale-lock.sh DIR
set -euo pipefail
dir="$(cd "${1:?usage: stale-lock.sh DIR}" && pwd -P)"
locks="$dir/.snakemake/locks"
[ -d "$locks" ] && [ -n "$(ls -A "$locks" 2>/dev/null)" ] || exit 1
for proc in /proc/[0-9]*; do
  [ "$(readlink "$proc/cwd" 2>/dev/null)" = "$dir" ] || continue
  if tr '\0' ' ' < "$proc/cmdline" 2>/dev/null | grep -q "snakemake"; then
    exit 1  # a run is still working here: its lock is not stale
  fi
done
exit 0
