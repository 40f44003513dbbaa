#!/usr/bin/env bash
# Build the documentation site into site/ (git-ignored): install the pinned MkDocs packages of
# envs/docs-requirements.txt into .venv (once; again only when the pins change), generate the
# reference pages (command line, configuration, benchmark results) into docs/reference/, and run
# `mkdocs build --strict`, which fails on any warning, broken link or broken anchor.
# Sets up .venv first (scripts/bootstrap.sh, a no-op when current); VLSFOREST_DOCS_PYTHON=PATH uses
# another environment's Python instead (it needs vlsforest's requirements). Extra arguments go to
# mkdocs build; VLSFOREST_SITE_DIR=DIR writes the site elsewhere.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
if [ -z "${VLSFOREST_DOCS_PYTHON:-}" ]; then
  bash "$ROOT/scripts/bootstrap.sh"
fi
PY="${VLSFOREST_DOCS_PYTHON:-.venv/bin/python}"
if [ ! -x "$PY" ]; then
  echo "build-docs: $PY not found" >&2; exit 1
fi
MARK="$(dirname "$PY")/../.vlsforest-docs-req"
DOCS_HASH=$(sha256sum envs/docs-requirements.txt | cut -d' ' -f1)
if [ "$(cat "$MARK" 2>/dev/null)" != "$DOCS_HASH" ]; then
  echo "build-docs: installing the pinned documentation packages into $(dirname "$(dirname "$PY")")" >&2
  "$PY" -m pip install -q --disable-pip-version-check -r envs/docs-requirements.txt || {
    echo "build-docs: error: cannot install envs/docs-requirements.txt (is the package index reachable?)" >&2
    exit 1; }
  echo "$DOCS_HASH" > "$MARK"
fi
PYTHONPATH="$ROOT/workflow${PYTHONPATH:+:$PYTHONPATH}" "$PY" scripts/gen_reference.py docs/reference >/dev/null
PYTHONPATH="$ROOT/workflow${PYTHONPATH:+:$PYTHONPATH}" "$PY" -m mkdocs build --strict --clean \
  --site-dir "${VLSFOREST_SITE_DIR:-site}" "$@"
echo "build-docs: site in ${VLSFOREST_SITE_DIR:-site}/index.html"
