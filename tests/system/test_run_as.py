"""Service items run as ``run_as``, not root, and stored params cannot steer roslaunch (issue 12 row 2, CONTRACTS §10).

A master and a robot agent run as root (this test needs root: it checks that the agent drops to another user),
with ``run_as=nobody``; a service logic with a node and a launcher on each side is paired, and every process of
the service space is looked up in ``/proc``: its real, effective, saved and file-system uids are nobody's, and
its environment has nobody's own HOME and ROS_HOME. Configuration mistakes stop the agent with one line.
"""

import os
import pwd

import pytest

from tests.support.lifecycle import Platform, processes_mentioning
from tests.support.polling import wait_until
from tests.support.rcmp_agent import RcmpAgent

needs_root = pytest.mark.skipif(os.geteuid() != 0, reason="switching users needs a root agent")

NOBODY = pwd.getpwnam("nobody")


def status_ids(pid, field):
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return [int(v) for v in line.split()[1:]]
    raise AssertionError(f"no {field} in /proc/{pid}/status")


def environ(pid):
    with open(f"/proc/{pid}/environ", "rb") as f:
        return dict(item.split(b"=", 1) for item in f.read().split(b"\0") if b"=" in item)


@pytest.fixture
def platform(procs, tmp_path):
    plat = Platform(procs, tmp_path, run_as="nobody")
    try:
        yield plat
    finally:
        plat.stop_all_and_check_nothing_left()
        for pid, _ in processes_mentioning("runas_marker_"):
            os.kill(pid, 9)


@needs_root
def test_items_run_as_the_run_as_user(platform):
    platform.master.start()
    assert "service items run as nobody" in platform.master.log_text()
    platform.provision_logic("as_nobody", sn_list=[
        {"sn_package": "robotics_test", "sn_type": "talker.py", "sn_name": "s_node",
         "sn_params": "_topic:=runas_marker_s", "sn_side": "S"},
        {"sn_package": "robotics_test", "sn_type": "talker.py", "sn_name": "r_node",
         "sn_params": "_topic:=runas_marker_r", "sn_side": "R"}],
        sl_list=[{"sl_package": "robotics_test", "sl_file_launcher": "two_talkers.launch", "sl_name": "pair",
                  "sl_params": "prefix:=runas_marker_l", "sl_side": "S"}])
    platform.provision_robot("robot1", "as_nobody")
    robot = platform.robot("robot1", "127.0.0.2", run_as="nobody").start()
    platform.wait_state("robot1", True, True)

    def space_processes():
        found = processes_mentioning("runas_marker_")
        names = " ".join(cmd for _, cmd in found)
        return all(m in names for m in ("runas_marker_s", "runas_marker_r", "runas_marker_l")) and found
    found = wait_until(space_processes, timeout=20, message="the nodes and the launcher in /proc")
    for pid, cmdline in found:
        for field in ("Uid", "Gid"):
            expected = NOBODY.pw_uid if field == "Uid" else NOBODY.pw_gid
            assert status_ids(pid, field) == [expected] * 4, (field, pid, cmdline)
        env = environ(pid)
        assert env[b"USER"] == b"nobody", cmdline
        home = env[b"HOME"].decode()
        assert os.stat(home).st_uid == NOBODY.pw_uid and home != "/root"
        assert env[b"ROS_HOME"].decode() == os.path.join(home, ".ros")
    # the ROS masters of the space too: nothing of it runs as root
    master_uri = platform.space("robot1")[1]["ros_master_uri"]
    port = master_uri.rsplit(":", 1)[1].strip("/")
    rosmasters = [pid for pid, cmd in processes_mentioning(port) if "rosmaster" in cmd and f"-p {port}" in cmd]
    assert rosmasters and all(status_ids(pid, "Uid") == [NOBODY.pw_uid] * 4 for pid in rosmasters)
    assert robot.stop() == 0
    platform.wait_state("robot1", False, False)
    assert platform.master.stop() == 0
    wait_until(lambda: not processes_mentioning("runas_marker_"), timeout=15, message="the items to be gone")


@pytest.mark.parametrize("role,value,expected", [
    ("master", "no_such_user_x", "no user 'no_such_user_x'"),
    ("robot", "no_such_user_x", "no user 'no_such_user_x'"),
    ("master", "Bad User", "not a user name"),
])
def test_run_as_mistakes_stop_the_agent_with_one_line(procs, tmp_path, role, value, expected):
    keys = {"run_as": value}
    if role == "robot":
        keys.update(name="r1", ip_master="127.0.0.1", ic_port=1)
    agent = RcmpAgent(procs, tmp_path / role, role=role, **keys)
    agent.start(wait=False)
    wait_until(lambda: agent.process.poll() is not None, timeout=20, message="the agent to refuse to start")
    assert agent.process.returncode == 2
    lines = agent.output().strip().splitlines()
    assert len(lines) == 1 and "run_as" in lines[0] and expected in lines[0], lines


def test_stored_params_from_an_older_version_cannot_steer_roslaunch(procs, tmp_path):
    """Row 2 once more, for a service logic stored before the rules: its space is refused, nothing is run."""
    import sqlite3
    victim = tmp_path / "victim"
    victim.write_text("keep me\n")
    evil = tmp_path / "evil.launch"
    evil.write_text(f'<launch><param name="x" command="/bin/rm -f {victim}"/></launch>\n')
    plat = Platform(procs, tmp_path / "plat")
    try:
        plat.master.start()
        plat.provision_logic("legacy", sl_list=[{"sl_package": "robotics_test", "sl_file_launcher": "two_talkers.launch",
                                                 "sl_name": "pair", "sl_params": "prefix:=x", "sl_side": "S"}])
        db = sqlite3.connect(plat.master.db_path)
        db.execute("UPDATE service_launcher SET sl_params = ? WHERE slg_name = 'legacy'",
                   (f"--pid={victim} {evil}",))
        db.commit()
        db.close()
        plat.master.restart()   # the read cache is gone with the old process
        plat.provision_robot("robot1", "legacy")
        plat.robot("robot1", "127.0.0.2").start()
        wait_until(lambda: "sl_params" in plat.master.log_text() and "arg:=value" in plat.master.log_text(),
                   timeout=30, message="the master to refuse the stored launcher")
        assert plat.state("robot1") != (True, True)
        assert victim.read_text() == "keep me\n"
        assert not processes_mentioning(str(evil))
    finally:
        plat.stop_all_and_check_nothing_left()
