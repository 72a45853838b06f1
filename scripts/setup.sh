#!/usr/bin/env bash
# Install torchsoil and everything it needs on a fresh machine (Debian/Ubuntu, Python >= 3.10).
# Idempotent: fast when everything is already there.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}

SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
APT_UPDATED=""
apt_install() {  # Debian packages, one `apt-get update` per run
  [ -n "$APT_UPDATED" ] || { $SUDO apt-get update -qq >/dev/null; APT_UPDATED=1; }
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "$@" >/dev/null
}

# System libraries: Open3D's wheel links libusb-1.0 and libgomp.
missing=()
for lib in usb-1.0 gomp; do
  "$PY" -c "import ctypes.util, sys; sys.exit(0 if ctypes.util.find_library('$lib') else 1)" \
    || missing+=("$lib")
done
if [ ${#missing[@]} -gt 0 ]; then
  echo "[setup] installing system libraries: libusb-1.0-0 libgomp1"
  apt_install libusb-1.0-0 libgomp1
fi

# ROS 1 from Debian's packages, for `torchsoil node --ros 1` and its tests against a real roscore
# (TORCHSOIL_NO_ROS=1 leaves ROS out: the node's tests then fail, nothing else needs it)
ROS1_DEBS=(ros-core python3-rospy python3-rosbag python3-rostopic python3-roslaunch python3-sensor-msgs
           python3-tf2-msgs python3-nav-msgs python3-diagnostic-msgs python3-std-msgs python3-geometry-msgs)
if [ -z "${TORCHSOIL_NO_ROS:-}" ] && command -v apt-get >/dev/null \
   && ! { command -v roscore >/dev/null && [ -d /usr/lib/python3/dist-packages/tf2_msgs ] \
          && [ -d /usr/lib/python3/dist-packages/diagnostic_msgs ]; }; then
  echo "[setup] installing ROS 1 (Debian's ros-core, rospy, rosbag and message packages)"
  apt_install "${ROS1_DEBS[@]}"
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

# ROS 2 (rclpy, Fast DDS and the message packages from PyPI) in an environment of its own, .ros2/,
# that sees this one's packages: its message packages share names with ROS 1's, which the main
# environment reads from Debian's dist-packages. `torchsoil node --ros 2` and its tests run there.
ROS2_PIP=(ros-rclpy ros-rmw-fastrtps-cpp ros-rmw-implementation ros-sensor-msgs ros-diagnostic-msgs ros-nav-msgs
          ros-std-msgs ros-geometry-msgs)
if [ -z "${TORCHSOIL_NO_ROS:-}" ] && ! .ros2/bin/python -c "import rclpy, torchsoil, diagnostic_msgs.msg" 2>/dev/null; then
  echo "[setup] installing ROS 2 (rclpy and message packages from PyPI) into .ros2/"
  "$PY" -m venv --system-site-packages .ros2
  .ros2/bin/python -m pip install -q "${ROS2_PIP[@]}" 2>&1 | { grep -v "^WARNING: Location" || true; }
fi
