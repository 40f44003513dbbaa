#!/usr/bin/env bash
# Set up (or refresh) the project's virtual environment .venv with the pinned requirements.
# Sourced by scripts/run-study.sh and scripts/run-tests.sh; safe to run again (no-op when current).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
PY="${PYTHON:-python3}"
cd "$ROOT"

is_root() { [ "$(id -u)" = "0" ]; }
apt_install() {  # apt_install PKG… — only as root; otherwise explain what to install
  if is_root; then
    if ! dpkg -s "$@" >/dev/null 2>&1; then
      echo "bootstrap: installing system package(s) $* (apt-get)" >&2
      (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@") >/dev/null
    fi
  else
    echo "bootstrap: not root — please install the system package(s) '$*' (e.g. sudo apt-get install $*)" >&2
    return 1
  fi
}

if ! command -v "$PY" >/dev/null 2>&1; then
  echo "bootstrap: $PY not found; vlsforest needs Python ≥ 3.11" >&2; exit 1
fi
"$PY" - <<'PYEOF' || { echo "bootstrap: vlsforest needs Python ≥ 3.11" >&2; exit 1; }
import sys; sys.exit(0 if sys.version_info >= (3, 11) else 1)
PYEOF

# open3d links against libusb-1.0 (a system library, not on PyPI)
if command -v ldconfig >/dev/null 2>&1 && ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  apt_install libusb-1.0-0 || echo "bootstrap: without libusb-1.0-0, 'import open3d' fails (stem meshing needs it)" >&2
fi

if [ ! -x .venv/bin/python ]; then
  if ! "$PY" -m venv .venv 2>/dev/null; then
    rm -rf .venv
    ver=$("$PY" -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")')
    apt_install "python${ver}-venv" || { echo "bootstrap: cannot create a virtual environment" >&2; exit 1; }
    "$PY" -m venv .venv
  fi
fi
REQ_HASH=$(cat envs/requirements.txt pyproject.toml | sha256sum | cut -d' ' -f1)
if [ "$(cat .venv/.vlsforest-req 2>/dev/null)" != "$REQ_HASH" ]; then
  echo "bootstrap: installing pinned requirements into .venv (first run takes a few minutes)" >&2
  .venv/bin/python -m pip install -q --disable-pip-version-check --upgrade pip >/dev/null
  .venv/bin/python -m pip install -q --disable-pip-version-check -r envs/requirements.txt
  .venv/bin/python -m pip install -q --disable-pip-version-check --no-deps -e .
  echo "$REQ_HASH" > .venv/.vlsforest-req
fi
