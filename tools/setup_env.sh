#!/usr/bin/env bash
# Creates .venv and installs everything ooi_seg_ros needs; safe to run again (make calls it
# only when requirements change or .venv is missing).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
VENV=.venv

# 1. Python 3.11+
if ! "$PY" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else 1)' 2>/dev/null; then
  echo "setup: Python 3.11 or newer is needed (found: $("$PY" --version 2>&1)); install it or" \
       "run 'make PYTHON=/path/to/python3.11 ...'" >&2
  exit 1
fi

# 2. System libraries open3d needs.
missing=()
ldconfig -p | grep -q 'libusb-1.0.so.0' || missing+=(libusb-1.0-0)
ldconfig -p | grep -q 'libGL.so.1' || missing+=(libgl1)
ldconfig -p | grep -q 'libgomp.so.1' || missing+=(libgomp1)
if [ ${#missing[@]} -gt 0 ]; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "setup: installing system libraries for open3d: ${missing[*]}"
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/dev/null
  else
    echo "setup: open3d needs system libraries that are missing: ${missing[*]}." >&2
    echo "       Install them with: sudo apt-get install -y ${missing[*]}" >&2
    exit 1
  fi
fi

# 2b. A C++ compiler for the training rasteriser's compiled kernel (built once on first use
#     into ~/.cache/ooi_seg_ros/kernels). Optional: without one, training falls back to the
#     ~10x slower pure-torch path and logs it, so this only warns when it cannot install one.
if ! command -v g++ >/dev/null && ! command -v c++ >/dev/null && ! command -v clang++ >/dev/null
then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "setup: installing g++ for the compiled training kernel"
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq g++ >/dev/null \
      || echo "setup: warning: g++ could not be installed; training uses the slower torch path" >&2
  else
    echo "setup: warning: no C++ compiler; training will use the ~10x slower torch path." \
         "Install one with: sudo apt-get install -y g++" >&2
  fi
fi

# 3. ROS 2: a sourced Jazzy installation wins over the PyPI wheels.
use_system_ros=0
if [ "${ROS_DISTRO:-}" = "jazzy" ] && "$PY" -c 'import rclpy' 2>/dev/null; then
  use_system_ros=1
fi

# 4. The virtual environment.
if [ ! -x "$VENV/bin/python" ]; then
  if [ $use_system_ros = 1 ]; then
    echo "setup: using the sourced ROS 2 Jazzy (venv with system site packages)"
    "$PY" -m venv --system-site-packages "$VENV"
  else
    "$PY" -m venv "$VENV"
  fi
fi
"$VENV/bin/python" -m pip install -q --disable-pip-version-check --upgrade pip
echo "setup: installing Python dependencies (first time: a few minutes, torch is large)"
"$VENV/bin/python" -m pip install -q --disable-pip-version-check -r requirements.txt
if [ $use_system_ros = 0 ]; then
  "$VENV/bin/python" -m pip install -q --disable-pip-version-check -r requirements-ros.txt
fi
"$VENV/bin/python" -m pip install -q --disable-pip-version-check --no-deps \
  --no-build-isolation -e . 2>/dev/null

# 5. Check that it all imports.
"$VENV/bin/python" - <<'PYCHECK'
import importlib, sys
mods = ["rclpy", "sensor_msgs.msg", "open3d", "pycolmap", "torch", "mcap", "sklearn",
        "ooi_seg_ros"]
bad = []
for m in mods:
    try:
        importlib.import_module(m)
    except Exception as exc:  # report every failure, not only the first
        bad.append(f"{m}: {exc}")
if bad:
    print("setup: these imports fail after installation:\n  " + "\n  ".join(bad), file=sys.stderr)
    sys.exit(1)
print("setup: environment ready (.venv)")
PYCHECK
