#!/usr/bin/env bash
# Installs everything the project needs on a fresh Debian machine (run as root or with sudo):
# Debian packages with apt, the Python package and its dependencies into .venv/ in the checkout
# (never into the system's Python: Debian 12 and Ubuntu 23.04+ mark theirs externally managed,
# PEP 668, and pip refuses it), the page's modules with npm. Afterwards run .venv/bin/python, or
# `. .venv/bin/activate` first.
set -euo pipefail
cd "$(dirname "$0")/.."

SUDO=""
[ "$(id -u)" -eq 0 ] || SUDO="sudo"

# open3d needs libusb at import time. The server runs on jemalloc, which gives freed memory
# back to the system (glibc's malloc let a long-running server grow; see server/memory.py).
# The web client's browser tests drive Debian's chromium with Playwright (Playwright's own
# browser download does not work here); npm installs the page's modules.
PACKAGES=()
ldconfig -p | grep -q libusb-1.0.so.0 || PACKAGES+=(libusb-1.0-0)
ldconfig -p | grep -q libjemalloc.so.2 || PACKAGES+=(libjemalloc2)
[ -x /usr/bin/chromium ] || PACKAGES+=(chromium chromium-driver)
command -v npm >/dev/null || PACKAGES+=(nodejs npm)
# Debian's python3 makes virtual environments only with python3-venv (it brings ensurepip).
python3 -c "import ensurepip, venv" 2>/dev/null || PACKAGES+=(python3-venv)
if [ ${#PACKAGES[@]} -gt 0 ]; then
  $SUDO apt-get update -qq
  $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${PACKAGES[@]}" >/dev/null
fi

# --system-site-packages: what the machine's Python already has at a version that fits (a
# distribution's numpy, an image's preinstalled stack) is used, not downloaded again; pip inside
# the environment installs the rest, and a newer version where one is needed, into .venv/.
if [ ! -x .venv/bin/python ]; then
  python3 -m venv --system-site-packages .venv
fi
# constraints.txt: the versions the suite passed with (scripts/lock.py writes it), for the
# CPython it was written on; another Python resolves the newest versions that fit it.
CONSTRAINTS=()
if .venv/bin/python -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
  CONSTRAINTS=(-c constraints.txt)
fi
.venv/bin/python -m pip install -q --disable-pip-version-check "${CONSTRAINTS[@]}" -e ".[dev]"

# The page's JavaScript modules (three, @msgpack/msgpack) at the locked versions; the server
# serves them from client_web/node_modules, so the page needs no internet.
if [ ! -d client_web/node_modules/three ] || [ client_web/package-lock.json -nt client_web/node_modules/.package-lock.json ]; then
  (cd client_web && npm ci --no-audit --no-fund --loglevel=error)
fi
