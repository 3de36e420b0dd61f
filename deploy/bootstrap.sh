#!/usr/bin/env bash
# Make this checkout runnable: system libraries, .venv, pinned Python dependencies.
# Idempotent and quick when everything is in place (a stamp keyed on the lock file's hash).
set -euo pipefail
cd "$(dirname "$0")/.."

# open3d needs these shared libraries; the dashboard's browser test drives Debian's chromium (never a
# downloaded browser). Install the missing ones (we may be root on a fresh Debian).
missing=()
for pkg in libusb-1.0-0 libgl1 libgomp1 chromium; do
  dpkg -s "$pkg" >/dev/null 2>&1 || missing+=("$pkg")
done
if [ ${#missing[@]} -gt 0 ]; then
  echo "bootstrap: installing system packages: ${missing[*]}"
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  export DEBIAN_FRONTEND=noninteractive
  $SUDO apt-get install -y -q "${missing[@]}" >/dev/null 2>&1 \
    || { $SUDO apt-get update -q >/dev/null && $SUDO apt-get install -y -q "${missing[@]}" >/dev/null; }
fi

PY="${PYTHON:-}"
if [ -z "$PY" ]; then
  for cand in python3.11 python3; do command -v "$cand" >/dev/null 2>&1 && { PY="$cand"; break; }; done
fi
[ -x .venv/bin/python ] || "$PY" -m venv .venv

stamp=".venv/.deps-$(cat requirements.lock pyproject.toml | sha256sum | cut -c1-16)"
if [ ! -f "$stamp" ]; then
  echo "bootstrap: installing Python dependencies into .venv (first run takes a few minutes)"
  .venv/bin/python -m pip install -q --upgrade pip
  # torch==2.13.0 in the lock is the CPU build that lies on this machine's disk.
  .venv/bin/python -m pip install -q -r requirements.lock
  .venv/bin/python -m pip install -q --no-deps --no-build-isolation -e .
  rm -f .venv/.deps-*
  touch "$stamp"
fi
