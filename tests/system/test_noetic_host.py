"""tests/support/noetic.py: a test host that looks like Ubuntu 20.04 with ROS Noetic from ROS's own packages.

With /opt/ros/noetic/setup.bash sourced, ROS's tools and Python packages are there and run on Python 3.8 with
Twisted 18.9 and cryptography 2.8; without it, neither is found, as on a Noetic robot. The machine's own
/usr/bin and Python are untouched outside the host.
"""

import os
import subprocess

import pytest

from tests.support.noetic import PLAIN_ENV, PREFIX, SETUP, add_noetic_host, sourced
from tests.support.polling import wait_until

pytestmark = [pytest.mark.netns, pytest.mark.skipif(os.geteuid() != 0, reason="test hosts need root")]

PORT = 11311  # the host has its own network namespace: nothing else listens there
ASK_MASTER = ("import sys, xmlrpc.client; code, _, _ = xmlrpc.client.ServerProxy(sys.argv[1]).getSystemState('/t');"
              "print('master answers' if code == 1 else 'master refuses')")


def test_sourced_setup_gives_ros_on_python_3_8_and_nothing_without_it(lan):
    robot = add_noetic_host(lan, "robot")

    # the system: Ubuntu 20.04, python3 is 3.8 with Ubuntu 20.04's libraries
    assert 'VERSION_ID="20.04"' in robot.run(["cat", "/etc/os-release"]).stdout
    versions = robot.run(["python3", "-c", "import sys, twisted, cryptography, netifaces; "
                          "print(sys.version_info[:2], twisted.__version__, cryptography.__version__, "
                          "netifaces.version)"], env=PLAIN_ENV).stdout.split("\n")[0]
    assert versions == "(3, 8) 18.9.0 2.8 0.10.4", versions

    # not sourced: no ROS program, no ROS module, no ROS variable
    missing = robot.run(["rosmaster", "--core", "-p", PORT], env=PLAIN_ENV, check=False)
    assert missing.returncode != 0 and "No such file" in missing.stdout, missing.stdout
    for tool in ("roscore", "rosrun", "catkin_make", "rostopic"):
        found = robot.run(["bash", "-c", 'command -v "$1"', "bash", tool], env=PLAIN_ENV, check=False)
        assert found.returncode != 0, (tool, found.stdout)
    no_rospy = robot.run(["python3", "-c", "import rospy"], env=PLAIN_ENV, check=False)
    assert no_rospy.returncode != 0 and "No module named 'rospy'" in no_rospy.stdout, no_rospy.stdout

    # sourced: ROS's environment, rospy on 3.8 from the prefix, a ROS master that answers
    env = robot.run(sourced(["env"]), env=PLAIN_ENV).stdout.splitlines()
    assert "ROS_DISTRO=noetic" in env
    assert f"ROS_PACKAGE_PATH={PREFIX}/share" in env
    assert f"CMAKE_PREFIX_PATH={PREFIX}" in env
    assert any(line.startswith(f"PATH={PREFIX}/bin:") for line in env), env
    rospy = robot.run(sourced(["python3", "-c", "import sys, rospy, std_msgs.msg; "
                                                "print(sys.version_info[:2], rospy.__file__)"]),
                      env=PLAIN_ENV).stdout.strip().splitlines()[-1]
    assert rospy.startswith(f"(3, 8) {PREFIX}/lib/python3/dist-packages/rospy/"), rospy
    package = robot.run(sourced(["rospack", "find", "rospy"]), env=PLAIN_ENV).stdout.strip()
    assert package == f"{PREFIX}/share/rospy", package

    master = robot.start(sourced(["rosmaster", "--core", "-p", PORT]), env=PLAIN_ENV, name="noetic-rosmaster")
    uri = f"http://127.0.0.1:{PORT}/"

    def answers():
        return robot.run(["python3", "-c", ASK_MASTER, uri], env=PLAIN_ENV, check=False).stdout.strip()

    wait_until(lambda: answers() == "master answers", timeout=30, message="the Noetic host's rosmaster")
    with open(f"/proc/{master.pid}/cmdline", "rb") as f:  # bash and nsenter exec'd: the same pid
        argv = f.read().decode().split("\0")
    assert argv[1:5] == [f"{PREFIX}/bin/rosmaster", "--core", "-p", str(PORT)], argv
    assert os.path.basename(os.readlink(f"/proc/{master.pid}/exe")) == "python3.8"
    robot.lan.procs.stop(master)

    # outside the host, this machine is as it was
    outside = subprocess.run(["/usr/bin/python3", "-c", "import rospy, sys; print(sys.version_info[:2])"],
                             stdout=subprocess.PIPE, universal_newlines=True, env=PLAIN_ENV)
    assert outside.stdout.strip() != "(3, 8)" and outside.returncode == 0
    assert os.path.exists("/usr/bin/rosmaster") and not os.path.exists(PREFIX)
