#!/usr/bin/env bash
# Install torchsoil and everything it needs on a fresh machine (Debian/Ubuntu, Python >= 3.10).
# Idempotent: fast when everything is already there.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}

# System libraries: Open3D's wheel links libusb-1.0 and libgomp.
missing=()
for lib in usb-1.0 gomp; do
  "$PY" -c "import ctypes.util, sys; sys.exit(0 if ctypes.util.find_library('$lib') else 1)" \
    || missing+=("$lib")
done
if [ ${#missing[@]} -gt 0 ]; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  echo "[setup] installing system libraries: libusb-1.0-0 libgomp1"
  $SUDO apt-get update -qq >/dev/null
  $SUDO apt-get install -y -qq libusb-1.0-0 libgomp1 >/dev/null
fi

# torch: the CPU build 2.13.0 when none is installed (an unpinned torch pulls a CUDA build).
if ! "$PY" -c "import torch" 2>/dev/null; then
  echo "[setup] installing torch==2.13.0"
  "$PY" -m pip install -q torch==2.13.0
fi
# torchsoil from this checkout (an editable install of another checkout does not count)
if ! "$PY" -c "
import pathlib, shutil, sys
sys.path.pop(0)  # not the current directory: scripts/*.py must find the installed package
import open3d, rosbags, gymnasium, numba, pytest, xdist, hypothesis, pydantic, ray, sphinx, myst_parser, furo, torchsoil
import pyproj, rasterio, shapely, geopandas, pyogrio, mcap, mcap_ros2  # export, and its second reader in the tests
here = pathlib.Path(torchsoil.__file__).resolve().parents[1] == pathlib.Path.cwd().resolve()
sys.exit(not here or shutil.which('torchsoil') is None)  # the command comes with the install
" 2>/dev/null; then
  echo "[setup] installing torchsoil and its dependencies (with Ray and the manual's tools: extras fleet, docs)"
  "$PY" -m pip install -q -e ".[dev,fleet,docs]"
fi
