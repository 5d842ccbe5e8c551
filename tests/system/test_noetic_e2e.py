"""A platform on Noetic machines, and mixed with Debian ones, installed from our zips as an administrator would.

Noetic machines are test hosts shaped as Ubuntu 20.04 with ROS Noetic from ROS's packages (tests/support/noetic.py):
Python 3.8 with Twisted 18.9 and cryptography 2.8, ROS only through /opt/ros/noetic/setup.bash. Debian machines are
test hosts with this machine's Debian 12 (Python 3.11, ROS in /usr). On each, the zip is installed with
``install.sh -n --skip-deps`` and the daemon started with ``service rcmpd start``; the master's installer makes the
platform's VPN (``rcmp_n vpn init`` on that machine's Python), its ``rcmp_n vpn client`` issues each robot's file,
and each robot's workspace holds robotics_test's talker, built there by the installer on that machine's ROS.

- A Noetic master (robotics.zip: FIROS, rcm_driver and robotics_msgs built in its workspace on Noetic) with a
  Noetic robot and a Debian robot: both pair over the managed VPN; each service space's rcm_driver runs on the
  master's Python 3.8 with those messages; each robot's R-side talker, and the two of a launcher the robot's agent
  read with roslaunch's loader, register with the service space's ROS master (on the master, a Noetic rosmaster on
  Python 3.8) from the robot's VPN address; the agent found the talker's file itself; on the Noetic robot the
  talker is a Python 3.8 process with ROS_DISTRO=noetic; the master's console shows what the talker says (its
  topic watcher, a rospy child of the agent, on Noetic). The robot zip made on the Noetic machine is the
  byte-identical zip this machine makes.
- A Debian master with a Noetic robot, the same way round the other way.
"""

import os
import shutil

import pytest

from tests.support.hosts import INSTALL_FRESH, INSTALL_PATHS
from tests.support.installed import ROOT_ENV, curl, log_tail, process_argv, process_env, service, stop_daemons
from tests.support.noetic import PREFIX, SETUP, add_noetic_host
from tests.support.paths import REPO
from tests.support.polling import wait_until
from tests.system.test_install import ZIP_NAMES, build_zip, unpack_zip

pytestmark = [pytest.mark.netns,
              pytest.mark.skipif(os.geteuid() != 0, reason="test hosts need root"),
              pytest.mark.skipif(not os.path.exists("/usr/sbin/update-rc.d"), reason="needs update-rc.d")]

VPN_SUBNET = "198.51.100.0/24"
TALKER = os.path.join(REPO, "tests", "ros_pkgs", "robotics_test")
# on the robot: a node, and a launcher whose nodes the robot's agent reads with roslaunch's loader on its ROS
LOGIC = {"slg_name": "talk",
         "sn_list": [{"sn_package": "robotics_test", "sn_type": "talker.py", "sn_name": "talker", "sn_params": "",
                      "sn_side": "R"}],
         "sl_list": [{"sl_package": "robotics_test", "sl_file_launcher": "two_talkers.launch", "sl_name": "pair",
                      "sl_params": "prefix:=e2e", "sl_side": "R"}]}
# run in the master's host with its python3: where the space's ROS master says a node is
LOOKUP_NODE = ("import sys, xmlrpc.client\n"
               "code, message, uri = xmlrpc.client.ServerProxy(sys.argv[1]).lookupNode('/e2e', sys.argv[2])\n"
               "print(uri if code == 1 else 'unknown: ' + message)\n")

# run in the master's host: read the console's topic stream (Server-Sent Events) until a line holds the text
READ_STREAM = ("import sys, urllib.request\n"
               "with urllib.request.urlopen(sys.argv[1], timeout=60) as stream:\n"
               "    for line in stream:\n"
               "        if sys.argv[2].encode() in line:\n"
               "            print(line.decode().strip())\n"
               "            break\n")


def debian_host(lan, name):
    return lan.add_host(name, private=INSTALL_PATHS, fresh=INSTALL_FRESH)


# on the server side of a master installed from robotics.zip: rcm_driver, with robotics_msgs built on that ROS
RCM_DRIVER = {"sn_package": "rcm", "sn_type": "rcm_driver.py", "sn_name": "rcm_driver", "sn_params": "",
              "sn_side": "S"}


def install_master(host, pkg, logic=LOGIC, *extra):
    """The master zip installed with the platform's VPN, its daemon started, ``logic`` provisioned; returns the
    RDAPI's base URL."""
    out = host.run([pkg / "install.sh", "-n", "--skip-deps", "--start", "no", "--vpn-subnet", VPN_SUBNET,
                    "--vpn-port", "1194", *extra], env=ROOT_ENV, cwd=pkg, timeout=300).stdout
    assert "Created the platform's VPN in /opt/rcm-platform/vpn" in out, out
    assert service(host, "start").returncode == 0, log_tail(host)
    base = f"http://{host.address}"
    wait_until(lambda: curl(host, base + "/")[0] == 200, timeout=90, message=f"the RDAPI\n{log_tail(host)}")
    status, reply = curl(host, base + "/service_logic/provisioning", logic)
    assert (status, reply["result"]) == (200, "OK"), reply
    return base


def add_robot(master, base, name, tmp_path):
    """Provision ``name`` on the master and issue its VPN client file there; returns the file, carried out."""
    status, reply = curl(master, base + "/platform_instance/provisioning",
                         {"pi_name": name, "pi_service_logic": LOGIC["slg_name"]})
    assert (status, reply["result"]) == (200, "OK"), reply
    master.run(["rcmp_n", "vpn", "client", name, "-o", f"/root/{name}.conf"], env=ROOT_ENV)
    carried = tmp_path / f"{name}.conf"
    shutil.copy(master.private_path(f"/root/{name}.conf"), carried)
    os.chmod(carried, 0o600)
    return carried


def install_robot(host, pkg, name, client_file, *extra):
    """robotics_test put into the robot's workspace, then the robot zip installed (the installer builds the
    workspace on this machine's ROS) and its daemon started; returns the installer's output."""
    host.run(["mkdir", "-p", "/root/rcmp_ws/src"])
    host.run(["cp", "-r", TALKER, "/root/rcmp_ws/src/"])
    out = host.run([pkg / "install.sh", "-n", "--skip-deps", "--start", "no", "--replace-ws", "no", "--name", name,
                    "--vpn-config", client_file, *extra], env=ROOT_ENV, cwd=pkg, timeout=300).stdout
    assert "Building the workspace /root/rcmp_ws with catkin_make" in out, out
    assert service(host, "start").returncode == 0, log_tail(host)
    return out


def robot_row(master, base, name):
    status, reply = curl(master, base + "/platform_instance/read")
    rows = reply.get("reason", []) if status == 200 and isinstance(reply, dict) else []
    return next((r for r in rows if r["pi_name"] == name), {})


def wait_paired(master, base, robots):
    """Wait until each robot of ``robots`` ({pi_name: host}) is paired."""
    for name, robot in robots.items():
        try:
            wait_until(lambda: robot_row(master, base, name).get("paired"), timeout=180, interval=0.5,
                       message=f"{name} to pair")
        except AssertionError as exc:
            raise AssertionError(f"{exc}; {robot_row(master, base, name)}\n{log_tail(master)}\n"
                                 f"{log_tail(robot)}") from None


def vpn_address(host):
    parts = host.run(["ip", "-4", "-o", "addr", "show", "dev", "tun0"]).stdout.split()
    return parts[parts.index("inet") + 1].split("/")[0]


def space(master, base, name):
    status, reply = curl(master, base + f"/service_space/read?ss_name={name}")
    assert status == 200, reply
    return reply["reason"]


def node_uri(master, base, name, node):
    """``node``'s URI as the ROS master of service space ``name`` knows it (asked from the master's host)."""
    uri = space(master, base, name)["ros_master_uri"]
    return master.run(["python3", "-c", LOOKUP_NODE, uri, node], env=ROOT_ENV).stdout.strip()


def talker_process(host):
    """(pid, argv) of the node ``talker`` running in ``host``."""
    for pid in host.pids():
        argv = process_argv(pid)
        if argv and "__name:=talker" in argv and any(w.endswith("robotics_test/scripts/talker.py") for w in argv):
            return pid, argv
    raise AssertionError(f"no talker runs in {host.name}\n{log_tail(host)}")


def executable(pid):
    return os.path.basename(os.readlink(f"/proc/{pid}/exe"))


def assert_talker_runs_from(master, base, name, robot, noetic):
    """The robot's talker registered from its VPN address; on a Noetic robot, Python 3.8 and Noetic's ROS."""
    address = vpn_address(robot)
    assert address.startswith("198.51.100.")
    for node in ("/talker", "/e2e_talker_a", "/e2e_talker_b"):
        assert node_uri(master, base, name, node).startswith(f"http://{address}:"), (node, log_tail(robot))
    launchers = space(master, base, name)["r_launchers"]
    assert [sorted(l["associated_r_nodes"]) for l in launchers] == [["e2e_talker_a", "e2e_talker_b"]], launchers
    # the agent found the node's file itself (roslib.packages.find_node on that machine's ROS), not through rosrun
    log = robot.run(["cat", "/opt/rcm-platform/log/rcmp.log"]).stdout
    assert (f"process robot/{name}/node/talker started: pid " in log and
            "argv ['/root/rcmp_ws/src/robotics_test/scripts/talker.py', '__name:=talker']" in log), log
    pid, argv = talker_process(robot)
    env = process_env(pid)
    assert env["ROS_IP"] == address and env["ROS_MASTER_URI"].startswith(f"http://{vpn_address(master)}:")
    if noetic:
        assert executable(pid) == "python3.8", argv
        assert env["ROS_DISTRO"] == "noetic" and f"{PREFIX}/lib/python3/dist-packages" in env["PYTHONPATH"]
    else:
        assert executable(pid) != "python3.8" and "ROS_DISTRO" not in env, (argv, env)


# ---------------------------------------------------------------------------------------------------------------

def test_noetic_master_pairs_a_noetic_robot_and_a_debian_robot_over_its_vpn(lan, tmp_path):
    master = add_noetic_host(lan, "master")
    noetic = add_noetic_host(lan, "noetic")
    debian = debian_host(lan, "debian")
    master_pkg = build_zip(tmp_path / "m")   # robotics.zip: FIROS, rcm_driver and robotics_msgs too
    # the robot zip made on the Noetic machine (Python 3.8) is the one this machine makes, byte for byte
    build_zip(tmp_path / "r", "robot")
    made_here = tmp_path / "r" / "dist" / ZIP_NAMES["robot"]
    master.run(["python3", os.path.join(REPO, "create_robotics_pkg"), "robot", "-o", tmp_path / "noetic-dist"],
               env=ROOT_ENV, cwd=REPO)
    made_on_noetic = tmp_path / "noetic-dist" / ZIP_NAMES["robot"]
    assert made_on_noetic.read_bytes() == made_here.read_bytes()
    robot_pkg = unpack_zip(made_on_noetic, tmp_path / "noetic-unpacked")
    try:
        logic = dict(LOGIC, sn_list=LOGIC["sn_list"] + [RCM_DRIVER])
        base = install_master(master, master_pkg, logic, "--fiware", "yes")
        log = master.run(["cat", "/opt/rcm-platform/log/rcmp.log"]).stdout
        assert f"ROS from {SETUP} (found in /opt/ros): ROS_DISTRO=noetic" in log, log

        out = install_robot(noetic, robot_pkg, "robot1", add_robot(master, base, "robot1", tmp_path),
                            "--ros-setup", SETUP)
        assert f"ROS setup script: {SETUP} (given as ros_setup)" in out
        assert f"ros_setup={SETUP}\n" in noetic.run(["cat", "/opt/rcm-platform/init.cfg"]).stdout
        install_robot(debian, robot_pkg, "robot2", add_robot(master, base, "robot2", tmp_path))
        wait_paired(master, base, {"robot1": noetic, "robot2": debian})

        log = noetic.run(["cat", "/opt/rcm-platform/log/rcmp.log"]).stdout
        assert f"ROS from {SETUP} (ros_setup): ROS_DISTRO=noetic" in log, log
        assert "ROS from " not in debian.run(["cat", "/opt/rcm-platform/log/rcmp.log"]).stdout  # ROS in /usr
        assert_talker_runs_from(master, base, "robot1", noetic, noetic=True)
        assert_talker_runs_from(master, base, "robot2", debian, noetic=False)
        # the service spaces' ROS masters are Noetic's, on the master's Python 3.8
        masters = [pid for pid in master.pids() if f"{PREFIX}/bin/rosmaster" in (process_argv(pid) or [])]
        assert len(masters) == 2, [process_argv(pid) for pid in master.pids()]
        assert {executable(pid) for pid in masters} == {"python3.8"}
        assert {process_env(pid)["ROS_DISTRO"] for pid in masters} == {"noetic"}
        # rcm_driver runs on Python 3.8 with robotics_msgs as the master's workspace built them on Noetic, and
        # was told that each robot connected (the agent reached its port once it ran)
        drivers = [pid for pid in master.pids() if any(w.endswith("/rcm_driver.py")
                                                       for w in process_argv(pid) or [])]
        assert len(drivers) == 2 and {executable(pid) for pid in drivers} == {"python3.8"}, drivers
        for name in ("robot1", "robot2"):
            assert node_uri(master, base, name, "/rcm_driver").startswith(f"http://{vpn_address(master)}:")
        log = master.run(["cat", "/opt/rcm-platform/log/rcmp.log"]).stdout
        for name in ("robot1", "robot2"):
            assert f"service space {name}: told rcm_driver (port " in log, log
        # the console's topic watcher (rospy in a child of the master's agent) reads the robot's talker
        seen = master.run(["python3", "-c", READ_STREAM, f"{base}/console/api/topic?ss_name=robot1&topic=/chatter",
                           "hello from /talker"], env=ROOT_ENV, timeout=90).stdout
        assert "hello from /talker" in seen, seen + log_tail(master)
    finally:
        stop_daemons(noetic, debian, master)


def test_debian_master_pairs_a_noetic_robot_over_its_vpn(lan, tmp_path):
    master = debian_host(lan, "master")
    robot = add_noetic_host(lan, "robot")
    master_pkg = build_zip(tmp_path / "m", "master")
    robot_pkg = build_zip(tmp_path / "r", "robot")
    try:
        base = install_master(master, master_pkg)
        out = install_robot(robot, robot_pkg, "robot1", add_robot(master, base, "robot1", tmp_path))
        assert f"ROS setup script: {SETUP} (found in /opt/ros" in out
        wait_paired(master, base, {"robot1": robot})
        assert_talker_runs_from(master, base, "robot1", robot, noetic=True)
    finally:
        stop_daemons(robot, master)
