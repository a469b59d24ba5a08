#!/usr/bin/env bash
# System libraries the Python wheels need but do not ship: open3d's wheel links libusb-1.0.
set -euo pipefail
if ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  exit 0
fi
echo "installing libusb-1.0-0 (needed by open3d)" >&2
SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get install -y -q libusb-1.0-0 >/dev/null 2>&1 || {
  $SUDO apt-get update -q >/dev/null
  $SUDO apt-get install -y -q libusb-1.0-0 >/dev/null
}
