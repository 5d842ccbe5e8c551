"""install.sh on each kind of ROS installation: which setup script and which package names it chooses.

- A test host made an Ubuntu 20.04 + ROS Noetic robot (tests/support/noetic.py): the dry run says it uses
  /opt/ros/noetic/setup.bash and names the ros-noetic-* packages it would install, none of Debian's; a real
  installation (--skip-deps: no ROS archive here) builds the workspace inside that setup script's environment,
  so the workspace chains onto /opt/ros/noetic.
- A Debian host whose package database lacks two of Debian's ROS packages: the dry run names exactly those, under
  Debian's names; with nothing missing it says it installs nothing (it used to list the step regardless).
- No host: --ros-setup's values (a file, none, wrong ones) and a ROS that is not from packages.
"""

import os
import subprocess

import pytest

from tests.support.hosts import INSTALL_FRESH, INSTALL_PATHS
from tests.support.noetic import PLAIN_ENV, PREFIX, SETUP, add_noetic_host, sourced
from tests.system.test_install import build_zip

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
needs_root = pytest.mark.skipif(os.geteuid() != 0, reason="test hosts need root")
DEBIAN_ROS_NAMES = ("ros-core", "python3-rospy", "python3-rosmaster", "catkin", "python3-std-msgs")


def step_line(out, start):
    return next((line for line in out.splitlines() if line.startswith(start)), None)


def missing_packages(out):
    line = step_line(out, "  - install the missing dependencies of the rcm ")
    return line.split(" with apt-get: ", 1)[1].split() if line else []


@needs_root
@pytest.mark.netns
def test_noetic_robot_uses_opt_ros_names_ross_packages_and_builds_its_workspace_on_top(lan, tmp_path):
    robot = add_noetic_host(lan, "robot")
    pkg = build_zip(tmp_path, "robot")
    answers = ["-n", "--name", "robot1", "--ip-master", "198.51.100.1", "--start", "no"]

    out = robot.run([pkg / "install.sh", "--dry-run", *answers], env=PLAIN_ENV, cwd=pkg).stdout
    assert f"ROS setup script: {SETUP} (found in /opt/ros" in out, out
    assert "System: Ubuntu 20.04.6 LTS\n" in out, out
    assert "ROS packages: ROS's own for noetic, from ROS's apt repository" in out, out
    missing = missing_packages(out)
    assert {"ros-noetic-rospy", "ros-noetic-rosmaster", "ros-noetic-catkin", "ros-noetic-roscpp"} <= set(missing), out
    assert all(name.startswith("ros-noetic-") for name in missing), missing  # the rest is installed here
    assert not set(DEBIAN_ROS_NAMES) & set(out.replace(":", " ").split()), out
    assert f"  - build the workspace with catkin_make in the environment of {SETUP}" in out
    assert "ros_setup" not in out.split("  - write ", 1)[1]  # found, not given: not written into init.cfg

    out = robot.run([pkg / "install.sh", "--skip-deps", *answers], env=PLAIN_ENV, cwd=pkg, timeout=300).stdout
    assert "Building the workspace /root/rcmp_ws with catkin_make" in out, out
    chained = robot.run(sourced(["env"], setup="/root/rcmp_ws/devel/setup.bash"), env=PLAIN_ENV).stdout.splitlines()
    assert f"CMAKE_PREFIX_PATH=/root/rcmp_ws/devel:{PREFIX}" in chained, chained
    assert f"ROS_PACKAGE_PATH=/root/rcmp_ws/src:{PREFIX}/share" in chained, chained
    assert f"PYTHONPATH={PREFIX}/lib/python3/dist-packages" in chained, chained  # an empty devel space adds none
    assert "ROS_DISTRO=noetic" in chained
    built_with = robot.run(["grep", "-m1", "PYTHON_EXECUTABLE:", "/root/rcmp_ws/build/CMakeCache.txt"]).stdout
    assert "=/usr/bin/python3" in built_with, built_with
    # the agent went into the site folder of Ubuntu's python3 (3.8), its #! line that python3
    site = robot.run(["python3", "-c", "import site; print(site.getsitepackages()[0])"], env=PLAIN_ENV).stdout.strip()
    assert "python3.8" in site and robot.run(["test", "-f", f"{site}/rcm_platform/rcmp_node.py"], check=False).returncode == 0
    assert robot.run(["head", "-1", "/usr/local/bin/rcmp_n"]).stdout.strip() == "#!/usr/bin/python3"
    helped = robot.run(["rcmp_n", "--help"], env=PLAIN_ENV).stdout   # the installed agent runs on Python 3.8
    assert helped.startswith("usage: rcmp_n ") and "--home DIR" in helped, helped
    assert robot.run(["python3", "-c", "import sys; print(sys.version_info[:2])"], env=PLAIN_ENV).stdout == "(3, 8)\n"


def _forget_packages(host, names):
    """Make the host's package database say ``names`` are not installed (its own copy of /var/lib/dpkg)."""
    code = ("import sys\n"
            "path = '/var/lib/dpkg/status'\n"
            "stanzas = open(path).read().split('\\n\\n')\n"
            "keep = [s for s in stanzas if not any(s.startswith('Package: ' + n + '\\n') for n in sys.argv[1:])]\n"
            "open(path, 'w').write('\\n\\n'.join(keep))\n")
    host.run(["/usr/bin/python3", "-c", code, *names])


@needs_root
@pytest.mark.netns
def test_debian_with_its_own_ros_names_debians_packages_and_only_the_missing_ones(lan, tmp_path):
    host = lan.add_host("debian", private=INSTALL_PATHS + ("/var/lib/dpkg",), fresh=INSTALL_FRESH)
    pkg = build_zip(tmp_path, "master")
    answers = ["-n", "--no-vpn", "--start", "no"]

    out = host.run([pkg / "install.sh", "--dry-run", *answers], env=PLAIN_ENV, cwd=pkg).stdout
    assert "ROS setup script: none (no /opt/ros/*/setup.bash): ROS is on the system's paths" in out, out
    assert "System: Debian GNU/Linux 12 (bookworm)\n" in out or "System: Debian GNU/Linux 13" in out, out
    assert "ROS packages: the system's own" in out, out
    assert "  - install no dependencies: everything the rcm master needs is installed" in out, out
    assert "install the missing dependencies" not in out

    _forget_packages(host, ["python3-rospy", "ros-core", "sqlite3"])
    out = host.run([pkg / "install.sh", "--dry-run", *answers], env=PLAIN_ENV, cwd=pkg).stdout
    assert missing_packages(out) == ["ros-core", "python3-rospy", "sqlite3"], out
    assert "ros-noetic" not in out
    robot_pkg = build_zip(tmp_path / "robot", "robot")
    out = host.run([robot_pkg / "install.sh", "--dry-run", "-n", "--name", "robot1", "--ip-master", "198.51.100.1"],
                   env=PLAIN_ENV, cwd=robot_pkg).stdout
    assert missing_packages(out) == ["ros-core", "python3-rospy"], out  # a robot needs no sqlite3 tool


# --- no host: what --ros-setup takes -------------------------------------------------------------------------

def dry_run(pkg, home, *extra):
    env = {"PATH": "/usr/bin:/bin:/usr/sbin:/sbin", "HOME": str(home), "LC_ALL": "C"}
    return subprocess.run([str(pkg / "install.sh"), "--dry-run", "-n", "--home", str(home / "platform"),
                           "--name", "robot1", "--ip-master", "198.51.100.1", *map(str, extra)],
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE, universal_newlines=True, env=env,
                          stdin=subprocess.DEVNULL, timeout=60)


@pytest.fixture(scope="module")
def robot_pkg(tmp_path_factory):
    return build_zip(tmp_path_factory.mktemp("robot-zip"), "robot")


def test_a_ros_that_is_not_from_packages_gets_no_ros_packages_and_is_written_into_the_configuration(robot_pkg, tmp_path):
    setup = tmp_path / "ros_catkin_ws" / "install_isolated" / "setup.bash"
    setup.parent.mkdir(parents=True)
    setup.write_text("# a source build's setup script\n")
    done = dry_run(robot_pkg, tmp_path, "--ros-setup", setup)
    assert done.returncode == 0, done.stderr
    assert f"ROS setup script: {setup} (given as ros_setup)" in done.stdout
    assert f"ROS packages: none ({setup} is not a ROS from packages" in done.stdout
    assert f"    ros_setup={setup}" in done.stdout  # given: the agent reads it from init.cfg
    assert f"build the workspace with catkin_make in the environment of {setup}" in done.stdout

    done = dry_run(robot_pkg, tmp_path, "--ros-setup", "none", "--skip-deps")
    assert done.returncode == 0, done.stderr
    assert "ROS setup script: none (given as ros_setup): ROS is on the system's paths" in done.stdout
    assert "  - not install dependencies (--skip-deps)" in done.stdout
    assert "    ros_setup=none" in done.stdout


@pytest.mark.parametrize("value, problem", [
    ("opt/ros/noetic/setup.bash", "is not a readable setup script given by its absolute path"),
    ("/nonexistent/setup.bash", "is not a readable setup script given by its absolute path"),
    ("", "is not a readable setup script given by its absolute path"),
])
def test_a_wrong_ros_setup_is_one_line_and_changes_nothing(robot_pkg, tmp_path, value, problem):
    done = dry_run(robot_pkg, tmp_path, "--ros-setup", value)
    assert done.returncode == 2
    assert f"install.sh: error: --ros-setup: '{value}' {problem}" in done.stderr
    assert "Traceback" not in done.stderr and not (tmp_path / "platform").exists()
