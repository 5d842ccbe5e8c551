"""Our zips installed into test hosts (tests/support/hosts.py), as an administrator would on real machines.

Each host has its own network namespace (``eth0`` on the test LAN) and its own copy of the folders an installation
writes (overlays over /usr/local, /etc, /root, /var/log, /run and /home, and an empty /opt and dist-packages of
its own, inside the host's mount namespace), so this machine's real installation paths are never touched, whatever
else runs at the same time; every daemon is stopped and every namespace removed at the end, even when a test fails.

- The master zip and the robot zip installed with the VPN flags into two hosts, ``service rcmpd start`` in each:
  the robot pairs over the platform's own VPN (issue 9).
- The root daemon and a user-owned workspace, as that user would attack it (issue 12 row 14): rcmpd sources
  nothing of the workspace, runs its setup script only as its owner, refuses settings, program or package files
  others can change; the agent's umask is 027, its data and logs not world-readable, its fd limit raised.
- robotics.zip with a user-owned workspace: the FIWARE items of a paired robot's service space run as the
  workspace's owner, with the workspace's code paths (issue 12 ``run_as``, end to end from rcmpd).
"""

import os
import resource
import shutil

import pytest

from tests.support.hosts import INSTALL_FRESH, INSTALL_PATHS
from tests.support.installed import (ROOT_ENV, USER_PATH, agent_pid, curl, log_tail, process_env, service,
                                     stop_daemons)
from tests.support.paths import REPO
from tests.support.polling import wait_until
from tests.system.test_install import build_zip

pytestmark = [pytest.mark.netns,
              pytest.mark.skipif(os.geteuid() != 0, reason="test hosts need root"),
              pytest.mark.skipif(not os.path.exists("/usr/sbin/update-rc.d"), reason="needs update-rc.d")]

HOST_PATHS = {"private": INSTALL_PATHS + ("/home",), "fresh": INSTALL_FRESH}
VPN_SUBNET = "198.51.100.0/24"
PY = "/usr/bin/python3"
ROOT = REPO


def file_mode(host, path):
    """(uid, mode bits) of ``path`` as the host sees it."""
    uid, mode = host.run(["stat", "-c", "%u %a", path]).stdout.split()
    return int(uid), int(mode, 8)


def proc_field(pid, name, field):
    with open(f"/proc/{pid}/{name}") as f:
        for line in f:
            if line.startswith(field):
                return line[len(field):].split()
    return None


# ---------------------------------------------------------------------------------------------------------------

def test_master_and_robot_zips_installed_in_two_hosts_pair_over_the_platforms_vpn(lan, tmp_path):
    master = lan.add_host("master", **HOST_PATHS)
    robot = lan.add_host("robot", **HOST_PATHS)
    master_pkg = build_zip(tmp_path / "m", "master")
    robot_pkg = build_zip(tmp_path / "r", "robot")
    try:
        # -- the master: its wizard makes the platform's VPN; the daemon starts it --------------------------------
        out = master.run([master_pkg / "install.sh", "-n", "--skip-deps", "--start", "no",
                          "--vpn-subnet", VPN_SUBNET, "--vpn-port", "1194"], env=ROOT_ENV, cwd=master_pkg,
                         timeout=300).stdout
        assert "Created the platform's VPN in /opt/rcm-platform/vpn" in out
        assert file_mode(master, "/opt/rcm-platform/vpn") == (0, 0o700)
        assert os.path.isfile(master.private_path("/opt/rcm-platform/vpn/server.conf"))  # in the master's copy
        assert service(master, "start").returncode == 0, log_tail(master)
        base = f"http://{master.address}"
        wait_until(lambda: curl(master, base + "/")[0] == 200, timeout=60,
                   message=f"the RDAPI on the master's eth0\n{log_tail(master)}")
        status, reply = curl(master, base + "/service_logic/provisioning",
                             {"slg_name": "hosts_test", "sn_list": [], "sl_list": []})
        assert (status, reply["result"]) == (200, "OK"), reply
        status, reply = curl(master, base + "/platform_instance/provisioning",
                             {"pi_name": "robot1", "pi_service_logic": "hosts_test"})
        assert (status, reply["result"]) == (200, "OK"), reply

        # -- the administrator issues robot1's client file on the master and carries it to the robot ------------
        master.run(["rcmp_n", "vpn", "client", "robot1", "-o", "/root/robot1.conf"], env=ROOT_ENV)
        carried = tmp_path / "robot1.conf"
        shutil.copy(master.private_path("/root/robot1.conf"), carried)
        os.chmod(carried, 0o600)
        assert f"remote {master.address} 1194" in carried.read_text()  # the default remote: the master's eth0

        # -- the robot: installed with the client file, started, paired over the VPN --------------------------
        out = robot.run([robot_pkg / "install.sh", "-n", "--skip-deps", "--start", "no", "--name", "robot1",
                         "--vpn-config", carried], env=ROOT_ENV, cwd=robot_pkg, timeout=300).stdout
        assert "Installed the VPN client file as /opt/rcm-platform/vpn/client.conf" in out
        assert file_mode(robot, "/opt/rcm-platform/vpn") == (0, 0o700)
        assert file_mode(robot, "/opt/rcm-platform/vpn/client.conf") == (0, 0o600)
        assert "ip_master" not in robot.run(["cat", "/opt/rcm-platform/init.cfg"]).stdout
        assert master.run(["test", "-e", "/opt/rcm-platform/init.cfg"], check=False).returncode == 1  # hosts apart
        assert service(robot, "start").returncode == 0, log_tail(robot)

        def robot_row():
            status, reply = curl(master, base + "/platform_instance/read")
            rows = reply.get("reason", []) if status == 200 else []
            return next((r for r in rows if r["pi_name"] == "robot1"), None)

        try:
            wait_until(lambda: (robot_row() or {}).get("paired"), timeout=90, message="robot1 to pair")
        except AssertionError as exc:
            raise AssertionError(f"{exc}; robot1: {robot_row()}\n{log_tail(master)}\n{log_tail(robot)}") from None
        listed = master.run(["rcmp_n", "vpn", "list"], env=ROOT_ENV).stdout.split()
        assert listed[:1] == ["robot1"] and listed[2:3] == ["connected"], listed
        tun = robot.run(["ip", "-o", "-4", "addr", "show", "dev", "tun0"]).stdout
        assert f" inet {listed[1]}/" in tun  # robot1's fixed address
        assert " inet 198.51.100." in tun
        master_tun = master.run(["ip", "-o", "-4", "addr", "show", "dev", "tun0"]).stdout
        assert " inet 198.51.100.1/24" in master_tun

        # the master's daemon restarted (its VPN folder now holds OpenVPN's runtime files): robot1 pairs again
        assert service(master, "restart").returncode == 0, log_tail(master)
        try:
            wait_until(lambda: (robot_row() or {}).get("paired"), timeout=90, message="robot1 to pair again")
        except AssertionError as exc:
            raise AssertionError(f"{exc}; robot1: {robot_row()}\n{log_tail(master)}\n{log_tail(robot)}") from None

        # -- the robot leaves: uninstall.sh removes its VPN and stops its OpenVPN -----------------------------------
        out = robot.run([robot_pkg / "uninstall.sh"], env=ROOT_ENV, cwd=robot_pkg, timeout=300).stdout
        assert "Removed the platform's VPN" in out
        assert robot.run(["test", "-e", "/opt/rcm-platform"], check=False).returncode == 1
        assert robot.run(["ip", "link", "show", "tun0"], check=False).returncode != 0
        wait_until(lambda: robot_row() and not robot_row()["connected"], timeout=60,
                   message="the master to see robot1 gone")

        out = master.run([master_pkg / "uninstall.sh"], env=ROOT_ENV, cwd=master_pkg, timeout=300).stdout
        assert "Removed the platform's VPN" in out
        assert master.run(["test", "-e", "/opt/rcm-platform"], check=False).returncode == 1
        assert master.run(["ip", "link", "show", "tun0"], check=False).returncode != 0
    finally:
        stop_daemons(robot, master)


# ---------------------------------------------------------------------------------------------------------------

EVIL_SETUP = """
# appended by the workspace's owner, who wants root
id -u >> "$HOME/sourced-by"
export PYTHONPATH=/home/alice/evil${PYTHONPATH:+:$PYTHONPATH}
export LD_LIBRARY_PATH=/home/alice/evil
export PATH=/home/alice/evil:$PATH
"""
EVIL_SITECUSTOMIZE = "import os\nopen('/home/alice/evil/imported-by-%d' % os.getuid(), 'w').close()\n"


def test_root_daemon_keeps_away_from_a_user_owned_workspace(lan, tmp_path):
    host = lan.add_host("master", **HOST_PATHS)
    pkg = build_zip(tmp_path, "master")
    host.run(["useradd", "-m", "-s", "/bin/bash", "alice"])
    uid = int(host.run(["id", "-u", "alice"]).stdout)
    ws = "/home/alice/rcmp_ws"

    def as_alice(argv, **kwargs):
        return host.run(["setpriv", f"--reuid={uid}", f"--regid={uid}", "--init-groups", "--", *argv],
                        env={"PATH": USER_PATH, "HOME": "/home/alice"}, cwd="/", **kwargs)

    try:
        host.run([pkg / "install.sh", "-n", "--skip-deps", "--start", "no", "--no-vpn",
                  "--vpn-address", host.address, "--workspace", ws], env=ROOT_ENV, cwd=pkg, timeout=300)
        host.run(["chown", "-R", "alice:alice", ws])  # alice's workspace, as her own install.sh run makes it
        # alice plants code where a root that sources or imports her files would run it
        as_alice(["mkdir", "/home/alice/evil"])
        as_alice([PY, "-c", "import sys; open(sys.argv[1], 'a').write(sys.argv[2])", f"{ws}/devel/setup.bash",
                  EVIL_SETUP])
        as_alice([PY, "-c", "import sys; open(sys.argv[1], 'w').write(sys.argv[2])",
                  "/home/alice/evil/sitecustomize.py", EVIL_SITECUSTOMIZE])
        for tool in ("rosrun", "rosmaster", "setsid", "openvpn"):  # commands a root agent might look up on PATH
            as_alice([PY, "-c", "import os, sys; open(sys.argv[1], 'w').write('#!/bin/sh\\nid -u >> "
                      "/home/alice/evil/ran-as\\n'); os.chmod(sys.argv[1], 0o755)", f"/home/alice/evil/{tool}"])
        # and a line in the settings file that would run were the file sourced
        host.run([PY, "-c", "import sys; open(sys.argv[1], 'a').write('touch /root/pwned-by-settings\\n')",
                  "/etc/default/rcmpd"])

        # started from a shell whose open-file limit is the old default 1024 (#8: 1,100 idle connections)
        hard = resource.getrlimit(resource.RLIMIT_NOFILE)[1]
        started = host.run(["prlimit", f"--nofile=1024:{hard}", "service", "rcmpd", "start"],
                           env={"PATH": USER_PATH, "LANG": "C"}, check=False, timeout=120)
        assert started.returncode == 0, started.stdout + log_tail(host)
        wait_until(lambda: curl(host, f"http://{host.address}/")[0] == 200, timeout=60,
                   message=f"the RDAPI\n{log_tail(host)}")
        pid = agent_pid(host)
        assert pid

        # the workspace's script ran, but only as alice; nothing of hers ran or was imported as root
        wait_until(lambda: host.run(["cat", "/home/alice/sourced-by"], check=False).stdout.split(), timeout=10)
        assert set(host.run(["cat", "/home/alice/sourced-by"]).stdout.split()) == {str(uid)}
        assert host.run(["test", "-e", "/home/alice/evil/imported-by-0"], check=False).returncode == 1
        assert host.run(["test", "-e", "/home/alice/evil/ran-as"], check=False).returncode == 1
        assert host.run(["test", "-e", "/root/pwned-by-settings"], check=False).returncode == 1
        env = process_env(pid)
        assert env["RCMP_WS"] == ws
        assert "/home/alice" not in env.get("PYTHONPATH", "") and "LD_LIBRARY_PATH" not in env
        assert "/home/alice" not in env["PATH"]
        assert f"workspace {ws} (owner uid {uid}): not root's" in host.run(
            ["cat", "/opt/rcm-platform/log/rcmp.log"]).stdout

        # umask 027, files 0640 and folders 0750, nothing world-readable; a raised fd limit
        assert proc_field(pid, "status", "Umask:") == ["0027"]
        soft, hard_seen = proc_field(pid, "limits", "Max open files")[:2]
        assert int(soft) == min(65536, int(hard_seen)) and int(soft) > 1024 * 4, (soft, hard_seen)
        assert file_mode(host, "/opt/rcm-platform/log") == (0, 0o750)
        for path in ("/opt/rcm-platform/robotics_data.db", "/opt/rcm-platform/log/rcmp.log",
                     "/opt/rcm-platform/log/rcmpd.out"):
            assert file_mode(host, path) == (0, 0o640), path
        for path in ("/opt/rcm-platform/robotics_data.db", "/opt/rcm-platform/log/rcmp.log"):
            denied = as_alice(["cat", path], check=False)
            assert denied.returncode != 0 and "Permission denied" in denied.stdout
        # files an older version left world-readable are tightened at the next start
        host.run(["chmod", "0644", "/opt/rcm-platform/log/rcmp.log", "/opt/rcm-platform/robotics_data.db"])
        assert service(host, "restart").returncode == 0, log_tail(host)
        assert file_mode(host, "/opt/rcm-platform/log/rcmp.log") == (0, 0o640)
        assert file_mode(host, "/opt/rcm-platform/robotics_data.db") == (0, 0o640)

        # what the root daemon runs or reads must be root's alone: each change below makes start refuse
        site = host.run([PY, "-c", "import site; print(site.getsitepackages()[0])"]).stdout.strip()
        attacks = [
            (["chown", "alice", "/etc/default/rcmpd"], ["chown", "root", "/etc/default/rcmpd"],
             "refusing /etc/default/rcmpd: /etc/default/rcmpd belongs to uid"),
            (["chmod", "o+w", f"{site}/rcm_platform/rcmp_node.py"], ["chmod", "o-w", f"{site}/rcm_platform/rcmp_node.py"],
             "rcmp_node.py is not root's or is writable by group or others"),
            (["chown", "alice", "/usr/local/bin/rcmp_n"], ["chown", "root", "/usr/local/bin/rcmp_n"],
             "/usr/local/bin/rcmp_n belongs to uid"),
            (["chmod", "g+w", "/opt/rcm-platform"], ["chmod", "g-w", "/opt/rcm-platform"],
             "/opt/rcm-platform is writable by group or others"),
        ]
        assert service(host, "stop").returncode == 0
        for attack, repair, message in attacks:
            host.run(attack)
            refused = service(host, "start")
            assert refused.returncode != 0 and message in refused.stdout, (attack, refused.stdout)
            assert agent_pid(host) is None or not os.path.exists(f"/proc/{agent_pid(host)}")
            host.run(repair)
        assert service(host, "start").returncode == 0, log_tail(host)
    finally:
        stop_daemons(host)


# ---------------------------------------------------------------------------------------------------------------

ROBOT_AGENT_ENV = {"PATH": USER_PATH, "HOME": "/root", "LANG": "C", "PYTHONPATH": ROOT}


def space_processes(host, owner_uid):
    """argv of the processes in ``host`` running as ``owner_uid`` (the service space's, on a master)."""
    found = []
    for pid in host.pids():
        try:
            with open(f"/proc/{pid}/status") as f:
                uid = next(int(line.split()[1]) for line in f if line.startswith("Uid:"))
            with open(f"/proc/{pid}/cmdline", "rb") as f:
                argv = [a.decode("utf-8", "replace") for a in f.read().split(b"\0") if a]
        except (OSError, StopIteration):
            continue
        if uid == owner_uid:
            found.append(argv)
    return found


def test_fiware_items_of_a_user_owned_workspace_run_as_its_owner_with_its_code(lan, tmp_path):
    """robotics.zip (FIROS, rcm_driver, robotics_msgs built into alice's workspace) on a master host; a robot
    pairs with fiware_base: FIROS and rcm_driver run as alice, and FIROS imports robotics_msgs from her
    workspace (its code paths reach her children only). The root agent itself never ran her code."""
    master = lan.add_host("master", **HOST_PATHS)
    robot = lan.add_host("robot")
    pkg = build_zip(tmp_path)  # robotics.zip
    master.run(["useradd", "-m", "-s", "/bin/bash", "alice"])
    uid = int(master.run(["id", "-u", "alice"]).stdout)
    ws = "/home/alice/rcmp_ws"
    try:
        master.run([pkg / "install.sh", "-n", "--skip-deps", "--start", "no", "--no-vpn", "--fiware", "yes",
                    "--vpn-address", master.address, "--workspace", ws], env=ROOT_ENV, cwd=pkg, timeout=600)
        master.run(["chown", "-R", "alice:alice", ws])
        assert service(master, "start").returncode == 0, log_tail(master)
        base = f"http://{master.address}"
        wait_until(lambda: curl(master, base + "/")[0] == 200, timeout=60, message=f"the RDAPI\n{log_tail(master)}")
        log = master.run(["cat", "/opt/rcm-platform/log/rcmp.log"]).stdout
        assert f"workspace {ws} (owner uid {uid}): not root's" in log
        status, reply = curl(master, base + "/platform_instance/provisioning",
                             {"pi_name": "robot1", "pi_service_logic": "fiware_base"})
        assert (status, reply["result"]) == (200, "OK"), reply

        home = tmp_path / "robot-home"
        home.mkdir()
        (home / "init.cfg").write_text(f"[main]\nname=robot1\nrobot=yes\nip_master={master.address}\n"
                                       f"vpn_address={robot.address}\n")
        robot.start([PY, "-m", "rcm_platform", "--home", home], env=ROBOT_AGENT_ENV, name="robot-agent")

        def space():
            status, reply = curl(master, base + "/service_space/read?ss_name=robot1")
            return reply.get("reason") if status == 200 and isinstance(reply, dict) else None

        try:
            wait_until(lambda: (space() or {}).get("paired"), timeout=120, message="robot1 paired with fiware_base")
        except AssertionError as exc:
            raise AssertionError(f"{exc}: {space()}\n{log_tail(master)}") from None
        argvs = space_processes(master, uid)
        assert any("core.py" in " ".join(a) and "firos" in " ".join(a) for a in argvs), argvs
        assert any("rcm_driver.py" in " ".join(a) for a in argvs), argvs
        assert any("rosmaster" in " ".join(a) for a in argvs), argvs  # the space's own ROS master too
        # nothing of the space runs as root: root's processes in the host are the agent and the holder only
        root_argvs = space_processes(master, 0)
        assert not [a for a in root_argvs if any(w in " ".join(a) for w in ("firos", "rcm_driver", "rosmaster"))]
    finally:
        lan.procs.stop_all()
        stop_daemons(master)
