#!/usr/bin/env bash
# Build the catkin workspace WS (default build/rcmp_ws) whose src/ links to this tree's catkin packages.
# catkin_make is run with /usr/bin first on PATH and /usr/bin/python3, so that a pyenv python3 on PATH
# (README.md, "Working on it": the PATH trap) cannot break parse_package_xml.py, inside the ROS installation's
# setup script when there is one.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
ws=${1:-build/rcmp_ws}
case "$ws" in /*) ;; *) ws="$root/$ws" ;; esac
export PATH=/usr/bin:/bin:/usr/sbin:/sbin:$PATH
mkdir -p "$ws/src"
# the product's packages, the demo robot, and (never shipped) the test suite's own package
for pkg in robotics_msgs rcm firos demo/robotics_demo tests/ros_pkgs/robotics_test; do
  if [ -f "$root/$pkg/package.xml" ]; then ln -sfn "$root/$pkg" "$ws/src/$(basename "$pkg")"; fi
done
# ROS as an installation finds it (sub_inst.sh ros-setup): RCMP_ROS_SETUP (a setup script, or none), else the first
# /opt/ros/*/setup.bash (noetic first), else none: ROS on the system's paths, as Debian's packages put it. The
# workspace built inside that script's environment chains onto it.
ros_setup=$(bash "$root/sub_inst.sh" ros-setup "${RCMP_ROS_SETUP:-}")
if [ "$ros_setup" != none ]; then
  echo "build-workspace: inside $ros_setup"
  set --          # a sourced catkin setup.bash takes the caller's arguments as its own
  set +eu
  # shellcheck disable=SC1090
  source "$ros_setup" || { echo "build-workspace: $ros_setup failed" >&2; exit 1; }
  set -eu
fi
cd "$ws"
catkin_make -DPYTHON_EXECUTABLE=/usr/bin/python3 -DCATKIN_ENABLE_TESTING=OFF > build.log 2>&1 || {
  tail -40 build.log >&2; echo "build-workspace: catkin_make failed, full log in $ws/build.log" >&2; exit 1; }
touch devel/setup.bash
echo "build-workspace: $ws built (overlay: $ws/devel/setup.bash)"
