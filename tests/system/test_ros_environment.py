"""rcmp_service_item.ros_environment: the ROS installation's setup script (``ros_setup``) run by bash, a child
process, in an empty environment, with no arguments, its path never part of a command line; and the agent that
cannot use its setup script stopping with one line. A whole Noetic machine is tests/system/test_noetic_e2e.py's."""

import os
import subprocess

import pytest

from rcm_platform import rcmp_service_item
from tests.support.rcmp_agent import PYTHON, REPO

SETUP = """
printf '%s\\n' "$#" > "$(dirname "${BASH_SOURCE[0]}")/arguments"
env > "$(dirname "${BASH_SOURCE[0]}")/environment-seen"
echo "setup scripts talk"
echo "and complain" >&2
export ROS_DISTRO=testdistro
export ROS_MASTER_URI=http://localhost:11311
export ROS_PACKAGE_PATH=/tr/share
export PYTHONPATH=/tr/lib/python3/dist-packages
export PATH=/tr/bin:$PATH
export UNRELATED=1
"""


@pytest.fixture
def ros_prefix(tmp_path):
    # a folder name a shell would run something for, were the path ever part of a command line
    prefix = tmp_path / "ros $(touch pwned); `touch pwned2`"
    prefix.mkdir()
    (prefix / "setup.bash").write_text(SETUP)
    rcmp_service_item._ros_environments.clear()
    yield prefix
    rcmp_service_item._ros_environments.clear()


def test_setup_script_is_sourced_in_an_empty_environment_without_arguments(ros_prefix, tmp_path):
    ros = rcmp_service_item.ros_environment(str(ros_prefix / "setup.bash"))
    assert ros.variables == {"ROS_DISTRO": "testdistro", "ROS_PACKAGE_PATH": "/tr/share",
                             "PYTHONPATH": "/tr/lib/python3/dist-packages", "PATH": "/tr/bin"}
    assert (ros_prefix / "arguments").read_text() == "0\n"   # nothing handed on to a catkin _setup_util.py
    seen = dict(line.split("=", 1) for line in (ros_prefix / "environment-seen").read_text().splitlines()
                if "=" in line)
    assert seen["PATH"] == rcmp_service_item.SYSTEM_PATH and seen["LC_ALL"] == "C"
    assert not {k for k in seen if k.startswith(("ROS_", "PYTHON", "RCMP_"))}   # nothing of ours leaked in
    assert not list(tmp_path.glob("**/pwned*")) and not os.path.exists("pwned")
    # once per path: the script does not run again
    (ros_prefix / "arguments").unlink()
    assert rcmp_service_item.ros_environment(str(ros_prefix / "setup.bash")) is ros
    assert not (ros_prefix / "arguments").exists()


def test_a_setup_script_that_exits_is_an_error_not_an_empty_ros(ros_prefix):
    (ros_prefix / "setup.bash").write_text("export ROS_DISTRO=x\nexit 0\n")
    with pytest.raises(OSError, match="ended the shell that sourced it"):
        rcmp_service_item.ros_environment(str(ros_prefix / "setup.bash"))


def run_agent(home):
    env = {"PATH": "/usr/bin:/bin", "HOME": str(home), "LANG": "C.UTF-8", "PYTHONPATH": REPO}
    return subprocess.run([PYTHON, "-m", "rcm_platform", "--home", str(home)], capture_output=True, text=True,
                          timeout=60, env=env, cwd=REPO)


def test_an_agent_whose_setup_script_fails_stops_with_one_line(ros_prefix, tmp_path):
    setup = ros_prefix / "setup.bash"
    setup.write_text("return 1\n")
    home = tmp_path / "home"
    home.mkdir()
    (home / "init.cfg").write_text(f"[main]\nname=robot1\nvpn_address=127.0.0.1\nros_setup={setup}\n")
    done = run_agent(home)
    assert done.returncode == 2, done.stderr
    assert done.stderr == f"rcmp_n: {home}/init.cfg: key 'ros_setup': {setup} failed (exit status 3)\n"
    assert f"cannot start: {home}/init.cfg: key 'ros_setup'" in (home / "log" / "rcmp.log").read_text()
