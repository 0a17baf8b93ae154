#!/usr/bin/env bash
# Installs everything the project needs on a fresh Debian machine (run as root or with sudo).
set -euo pipefail
cd "$(dirname "$0")/.."

SUDO=""
[ "$(id -u)" -eq 0 ] || SUDO="sudo"

# open3d needs libusb at import time; nothing else from Debian is needed yet.
if ! ldconfig -p | grep -q libusb-1.0.so.0; then
  $SUDO apt-get update -qq
  $SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null
fi

python3 -m pip install -q --disable-pip-version-check -e ".[dev]"
