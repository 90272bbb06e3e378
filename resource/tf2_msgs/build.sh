#!/usr/bin/env bash
# Generate and install tf2_msgs/msg/TFMessage into a pip-installed ROS 2 Jazzy venv that
# has no tf2_msgs (there is no tf2_msgs wheel), with the rosidl generator and ament_cmake
# wheels of requirements.txt: the node then publishes /tf there too. The definition is
# tf2_msgs' own, so the type (and its RIHS01 type hash) is the one a Jazzy install has.
# A ROS install already has tf2_msgs and never runs this (COLCON_IGNORE keeps colcon away).
#
#   resource/tf2_msgs/build.sh VENV
set -euo pipefail
if ! command -v cmake > /dev/null || ! command -v cc > /dev/null; then
    echo "warning: cmake or a C compiler is missing: tf2_msgs is not generated, and the" \
         "node will not publish /tf in this venv (install them, then run: $0 VENV)" >&2
    exit 0
fi
venv=$(cd "$1" && pwd)
src=$(cd "$(dirname "$0")" && pwd)
build=$(mktemp -d)
trap 'rm -rf "$build"' EXIT
export AMENT_PREFIX_PATH="$venv" PATH="$venv/bin:$PATH"
cmake -S "$src" -B "$build" -DCMAKE_PREFIX_PATH="$venv" -DCMAKE_INSTALL_PREFIX="$venv" \
    -DPython3_EXECUTABLE="$venv/bin/python" -DBUILD_TESTING=OFF -DCMAKE_BUILD_TYPE=Release \
    > "$build/configure.log" 2>&1 || { cat "$build/configure.log"; exit 1; }
cmake --build "$build" -j "$(nproc)" > "$build/build.log" 2>&1 || { tail -50 "$build/build.log"; exit 1; }
cmake --install "$build" > /dev/null
"$venv/bin/python" -c "from tf2_msgs.msg import TFMessage"
echo "tf2_msgs/msg/TFMessage generated into $venv"
