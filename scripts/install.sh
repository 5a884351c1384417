#!/usr/bin/env bash
# Installs everything monovoc_ros needs into ./.venv (Python 3.11): the pinned wheels, the
# monovoc_interfaces package (rosidl-generated, built with cmake into the venv prefix), the project
# itself (editable), and the offline embedding and segmenter models (exported once to ONNX).
# Idempotent: each step is skipped when its inputs have not changed since it last succeeded.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
cd "$root"
venv="$root/.venv"
python=${PYTHON:-python3.11}
command -v "$python" >/dev/null || python=python3

stamp() { sha256sum "$@" | sha256sum | cut -c1-16; }

# System tools the interfaces build needs (Debian/Ubuntu: apt-get install python3.11-venv cmake g++ make).
for tool in "$python" cmake c++ make; do
  command -v "$tool" >/dev/null || { echo "[install] missing $tool (apt-get install python3.11-venv cmake g++ make)" >&2; exit 1; }
done

if [ ! -x "$venv/bin/python" ]; then
  echo "[install] creating $venv"
  "$python" -m venv "$venv"
fi
export VIRTUAL_ENV="$venv" PATH="$venv/bin:$PATH"
export PIP_DISABLE_PIP_VERSION_CHECK=1

req_stamp=$(stamp requirements.txt)
if [ "$(cat "$venv/.req_stamp" 2>/dev/null)" != "$req_stamp" ]; then
  echo "[install] pip install -r requirements.txt"
  # The machine's pip config lists local indexes that may be absent: drop those warnings.
  pip install --quiet --upgrade "pip==26.3" 2>&1 | { grep -v "^WARNING: Location" || true; }
  pip install --quiet -r requirements.txt 2>&1 | { grep -v "^WARNING: Location" || true; }
  # launch_ros (installed below from ../shared/ros2_tools) names ament_index_python, which PyPI spells
  # ros-jazzy-ament-index-python: the one harmless line when requirements change after the tools are in.
  problems=$(pip check 2>&1 | grep -v "^launch-ros .* ament-index-python" | grep -v "^No broken requirements" || true)
  [ -z "$problems" ] || { echo "$problems" >&2; exit 1; }
  echo "$req_stamp" > "$venv/.req_stamp"
fi

if [ -d monovoc_interfaces ]; then
  if_stamp=$(stamp $(find monovoc_interfaces -type f | sort))
  if [ "$(cat "$venv/.interfaces_stamp" 2>/dev/null)" != "$if_stamp" ]; then
    echo "[install] building monovoc_interfaces into $venv"
    export AMENT_PREFIX_PATH="$venv"
    build="$root/build/monovoc_interfaces"
    rm -rf "$build"
    mkdir -p "$build"
    cmake -S monovoc_interfaces -B "$build" -DCMAKE_INSTALL_PREFIX="$venv" \
      -DCMAKE_PREFIX_PATH="$venv" -DPython3_EXECUTABLE="$venv/bin/python" \
      -DBUILD_TESTING=OFF > "$root/build/monovoc_interfaces.cmake.log" 2>&1 \
      || { cat "$root/build/monovoc_interfaces.cmake.log"; exit 1; }
    cmake --build "$build" -j2 >> "$root/build/monovoc_interfaces.cmake.log" 2>&1 \
      || { tail -50 "$root/build/monovoc_interfaces.cmake.log"; exit 1; }
    cmake --install "$build" >> "$root/build/monovoc_interfaces.cmake.log" 2>&1
    echo "$if_stamp" > "$venv/.interfaces_stamp"
  fi
fi

# The editable install maps top-level packages found at install time: re-run it when one appears.
proj_stamp=$( (cat setup.py setup.cfg package.xml; ls -d */__init__.py) | sha256sum | cut -c1-16)
if [ "$(cat "$venv/.project_stamp" 2>/dev/null)" != "$proj_stamp" ]; then
  echo "[install] pip install -e . (monovoc_ros)"
  pip install --quiet --no-deps --no-build-isolation -e . 2>&1 | { grep -vE "^WARNING: Location|^ " || true; }
  echo "$proj_stamp" > "$venv/.project_stamp"
fi

# The real ROS 2 command line (ros2 run / launch / service / topic / param / node / pkg): on a robot from apt,
# here the upstream wheels in ../shared/ros2_tools (see its README; --no-deps: they name ROS packages that
# PyPI spells ros-jazzy-*).
tools="$root/../shared/ros2_tools"
if [ -d "$tools" ]; then
  tools_stamp=$(stamp "$tools"/*.whl)
  if [ "$(cat "$venv/.tools_stamp" 2>/dev/null)" != "$tools_stamp" ]; then
    echo "[install] ROS 2 command-line tools from $tools"
    pip install --quiet psutil osrf-pycommon packaging setuptools 2>&1 | { grep -v "^WARNING: Location" || true; }
    pip install --quiet --no-deps "$tools"/*.whl 2>&1 | { grep -v "^WARNING: Location" || true; }
    # launch_ros names ament_index_python, which PyPI spells ros-jazzy-ament-index-python: the one harmless line.
    problems=$(pip check 2>&1 | grep -v "^launch-ros .* ament-index-python" | grep -v "^No broken requirements" || true)
    [ -z "$problems" ] || { echo "$problems" >&2; exit 1; }
    echo "$tools_stamp" > "$venv/.tools_stamp"
  fi
else
  echo "[install] $tools not found: no ros2 command line in the venv (tests that run it will fail)" >&2
fi

# The development install registered in the venv's ament index, as a colcon install space registers it, so
# `ros2 run / launch / pkg monovoc_ros ...` find it: links to the repository's files (edits take effect at
# once) and, in lib/monovoc_ros, the executables ros2 run looks for.
share="$venv/share/monovoc_ros"
mkdir -p "$venv/share/ament_index/resource_index/packages" "$share" "$venv/lib/monovoc_ros"
: > "$venv/share/ament_index/resource_index/packages/monovoc_ros"
for item in package.xml config rviz; do ln -sfn "$root/$item" "$share/$item"; done
# ros2 launch finds launch files by walking the share directory, which does not enter linked directories.
rm -rf "$share/launch" && mkdir -p "$share/launch"
for file in "$root"/launch/*.py; do ln -sfn "$file" "$share/launch/"; done
for exe in semantic_mapper mapping_node segmenter monovoc; do
  printf '#!/bin/sh\nexec "%s" "$@"\n' "$venv/bin/$exe" > "$venv/lib/monovoc_ros/$exe"
  chmod +x "$venv/lib/monovoc_ros/$exe"
done

# Offline embedding models and the segmenter's default models: exported once to ONNX into the model cache
# (each a no-op when up to date).
"$venv/bin/python" -m monovoc_ros.embed.export --quiet
"$venv/bin/python" -m monovoc_ros.segment.export --quiet
# The numba kernels compiled into their on-disk cache now, so that no node pays it on its first keyframe
# (~20-40 s on 2 cores; ~2 s when already cached). numba keys a kernel's cache on its own file only: a constant or
# a kernel it takes from another module (the raster constants, sorting's radix_argsort) would stay as first
# compiled, so when any source changed since the last warm-up, every cached kernel goes first. (A test or benchmark
# run straight after editing such a module, without this script, can still load the stale kernel.)
src_stamp=$(stamp $(find monovoc_ros msg_adapters -name '*.py' | sort))
if [ "$(cat "$venv/.numba_stamp" 2>/dev/null)" != "$src_stamp" ]; then
  find monovoc_ros msg_adapters -path '*/__pycache__/*' \( -name '*.nbi' -o -name '*.nbc' \) -delete
fi
"$venv/bin/monovoc" warm-up
echo "$src_stamp" > "$venv/.numba_stamp"
echo "[install] done: $venv"
