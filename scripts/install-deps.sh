#!/usr/bin/env bash
# Install, with apt-get, everything development, tests, benchmarks and the demo need.
# Idempotent: a second run installs nothing new. Needs root (CI and the README run it as root).
set -euo pipefail

PACKAGES=(
  # ROS 1 (Noetic line) from Debian's own packages
  ros-core rosbash rospack-tools python3-rospy python3-roslaunch python3-rosmaster python3-rosgraph python3-rostopic
  python3-rosnode python3-rosservice python3-rosparam python3-std-msgs python3-geometry-msgs
  python3-sensor-msgs python3-genpy python3-genmsg catkin python3-catkin-pkg ros-message-generation
  ros-message-runtime libstd-msgs-dev libgeometry-msgs-dev libroscpp-dev cmake g++
  # the agent, the RDAPI and FIROS
  python3-twisted python3-netifaces python3-yaml sqlite3
  # the master's /metrics (Prometheus text; a robot never needs it)
  python3-prometheus-client
  # the platform's VPN (rcmp_vpn: PKI with python3-cryptography, OpenVPN run by the agent)
  python3-cryptography openvpn
  # tests and benchmarks
  python3-pytest python3-pytest-timeout python3-hypothesis wrk curl iproute2 procps net-tools
  # the common message types FIROS's conversion is tested on, every type of each package
  python3-nav-msgs python3-trajectory-msgs python3-diagnostic-msgs python3-actionlib-msgs python3-visualization-msgs
  # the console's browser tests (headless Chromium driven by Selenium)
  chromium chromium-driver python3-selenium
  # distribution
  zip unzip
)

missing=()
for p in "${PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q 'install ok installed' || missing+=("$p")
done
if [ ${#missing[@]} -eq 0 ]; then
  echo "deps: all ${#PACKAGES[@]} packages already installed"
  exit 0
fi
if [ "$(id -u)" -ne 0 ]; then
  echo "deps: missing packages (${missing[*]}); run this as root" >&2
  exit 1
fi
echo "deps: installing ${missing[*]}"
export DEBIAN_FRONTEND=noninteractive
apt-get update -qq
apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
echo "deps: done"
