"""`create_robotics_pkg demo`: the demo robot as its own zip, and that zip installed as its README says.

The listing is written out here, not taken from create_robotics_pkg, so a drift on either side fails. The
installation test does what the package's README tells a robot's owner: a workspace built before the package
came (as the installer leaves it), the zip unpacked into its ``src`` and built with ``catkin_make`` in a plain
environment, then both nodes run with the environment the agent computed for that workspace *before* the package
was added (``rcmp_node.workspace_overlay``: a running agent needs no restart), and the robot circles.
"""

import os
import re
import subprocess
import zipfile

import pytest

from rcm_platform.rcmp_service_item import workspace_overlay
from tests.support.polling import wait_until
from tests.support.rosmaster import RosMaster

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
TOOL = os.path.join(ROOT, "create_robotics_pkg")
PLAIN_PATH = "/usr/bin:/bin:/usr/sbin:/sbin"

DEMO_LISTING = ["robotics_demo/", "robotics_demo/CMakeLists.txt", "robotics_demo/README.md",
                "robotics_demo/package.xml", "robotics_demo/scripts/", "robotics_demo/scripts/patrol_brain.py",
                "robotics_demo/scripts/sim_robot.py"]
EXECUTABLE = {"robotics_demo/scripts/patrol_brain.py", "robotics_demo/scripts/sim_robot.py"}


def build_demo_zip(outdir):
    result = subprocess.run(["/usr/bin/python3", TOOL, "demo", "-o", str(outdir)], capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stderr == ""              # every file of demo/robotics_demo is listed: no "left out" warning
    path = os.path.join(str(outdir), "robotics_demo.zip")
    assert result.stdout.strip() == f"create_robotics_pkg: created {path}"
    return path


def test_the_demo_zip_holds_the_package_and_its_page_and_is_reproducible(tmp_path):
    path = build_demo_zip(tmp_path / "a")
    with zipfile.ZipFile(path) as zf:
        assert sorted(zf.namelist()) == DEMO_LISTING
        for info in zf.infolist():
            mode = (info.external_attr >> 16) & 0o777
            expected = 0o755 if info.filename.endswith("/") or info.filename in EXECUTABLE else 0o644
            assert mode == expected, (info.filename, oct(mode))
        readme = zf.read("robotics_demo/README.md").decode()
        for name in ("cmd_vel", "geometry_msgs/Twist", "pose", "geometry_msgs/Pose2D", "~/rcmp_ws/src",
                     "catkin_make", "/service_logic/provisioning", '"sn_side": "R"', '"sn_side": "S"'):
            assert name in readme, name
        with open(os.path.join(ROOT, "demo", "robotics_demo", "scripts", "sim_robot.py"), "rb") as f:
            assert zf.read("robotics_demo/scripts/sim_robot.py") == f.read()
    with open(path, "rb") as first, open(build_demo_zip(tmp_path / "b"), "rb") as second:
        assert first.read() == second.read()


def test_the_other_zips_do_not_carry_the_demo(tmp_path):
    result = subprocess.run(["/usr/bin/python3", TOOL, "-o", str(tmp_path)], capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0, result.stderr
    with zipfile.ZipFile(os.path.join(str(tmp_path), "robotics.zip")) as zf:
        assert not [n for n in zf.namelist() if "robotics_demo" in n or "sim_robot" in n]


def catkin_make(workspace, home):
    result = subprocess.run(["catkin_make", "-DPYTHON_EXECUTABLE=/usr/bin/python3"], cwd=workspace,
                            env={"PATH": PLAIN_PATH, "HOME": home, "LC_ALL": "C"}, stdin=subprocess.DEVNULL,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]


@pytest.mark.slow
def test_installed_as_its_readme_says_the_robot_circles_without_restarting_the_agent(procs, tmp_path):
    home = str(tmp_path)
    workspace = os.path.join(home, "rcmp_ws")
    os.makedirs(os.path.join(workspace, "src"))
    catkin_make(workspace, home)                      # what the installer leaves on a robot: empty, built
    overlay = workspace_overlay(workspace)            # what a running agent computed at its start
    assert overlay is not None

    zip_path = build_demo_zip(tmp_path / "dist")
    unzipped = subprocess.run(["unzip", "-q", zip_path, "-d", os.path.join(workspace, "src")], capture_output=True,
                              text=True, timeout=60)
    assert unzipped.returncode == 0, unzipped.stderr
    catkin_make(workspace, home)

    master = RosMaster(procs).start()
    env = overlay.for_child({"PATH": PLAIN_PATH, "HOME": home, "ROS_MASTER_URI": master.uri, "ROS_IP": "127.0.0.1",
                             "ROS_LOG_DIR": os.path.join(home, "roslog")}, as_owner=True)
    # only this workspace and the system: the clone's own robotics_demo is out of sight
    assert ROOT not in env.get("ROS_PACKAGE_PATH", "") + env.get("CMAKE_PREFIX_PATH", "") + env.get("PATH", "")
    for node in ("sim_robot.py", "patrol_brain.py"):
        procs.start(["rosrun", "robotics_demo", node], env=env, name=node)

    def moved():
        out = subprocess.run(["rostopic", "echo", "-n", "1", "/pose"], env=env, capture_output=True, text=True,
                             timeout=20).stdout
        x = re.search(r"^x: (\S+)", out, re.M)
        return x and float(x.group(1)) > 0.05
    wait_until(moved, timeout=40, message="the demo robot, installed from its zip, to move")
    types = master.topic_types()
    assert types.get("/pose") == "geometry_msgs/Pose2D" and types.get("/cmd_vel") == "geometry_msgs/Twist"
    assert {p.rsplit("/", 1)[-1] for p in master.nodes()} >= {"sim_robot", "patrol_brain"}
