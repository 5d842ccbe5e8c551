"""What a real master (``python3 -m rcm_platform``) does with a robot agent's answers, probed as an attacker would.

Issue 18, "also reported": an ``ss_side R`` robot's ``ros_master_uri`` answer steered the master's S-side items and
its XML-RPC polling to any URL it named. Here a protocol-level robot (``tests/support/fake_agent.py``, a real TCP
connection from the robot's address) answers ``start_items`` with the URI of another host, where the test listens
to see whether anything of the master arrives. The legitimate case (the robot's own address) is
``tests/system/test_lifecycle_processes.py::test_ss_side_r_puts_the_ros_master_on_the_robot``; every shape of URI
the master refuses is in ``tests/unit/rcm_platform/test_rcmp_ms.py``.
"""

import socket

import pytest

from tests.support.fake_agent import FakeAgent
from tests.support.lifecycle import Platform
from tests.support.polling import wait_until

ROBOT = "127.0.0.2"
ELSEWHERE = "127.0.0.9"          # the host the robot names: not its own


@pytest.fixture
def platform(procs, tmp_path):
    plat = Platform(procs, tmp_path, inbound_ports=0)
    try:
        yield plat
    finally:
        plat.stop_all_and_check_nothing_left()


class Trap:
    """A listening socket on another loopback host: any connection to it (XML-RPC polling, a node registering)
    waits in its backlog, where ``reached()`` finds it."""

    def __init__(self):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.bind((ELSEWHERE, 0))
        self.sock.listen(16)
        self.sock.setblocking(False)
        self.port = self.sock.getsockname()[1]

    def reached(self):
        try:
            conn, _ = self.sock.accept()
        except BlockingIOError:
            return False
        conn.close()
        return True


@pytest.fixture
def trap():
    t = Trap()
    try:
        yield t
    finally:
        t.sock.close()


def test_a_robot_naming_another_hosts_ros_master_is_refused_and_nothing_runs_against_it(platform, trap):
    platform.master.start()
    platform.provision_logic("head_on_robot", ss_side="R", sn_list=[
        {"sn_package": "robotics_test", "sn_type": "talker.py", "sn_name": "brain", "sn_params": "_topic:=brain",
         "sn_side": "S"},
        {"sn_package": "robotics_test", "sn_type": "talker.py", "sn_name": "body", "sn_params": "_topic:=body",
         "sn_side": "R"}])
    platform.provision_robot("robot1", "head_on_robot")
    elsewhere = f"http://{ELSEWHERE}:{trap.port}/"
    answer = {"ros_master_uri": elsewhere, "items": [], "reason": None, "inbound_port": None}
    with FakeAgent(platform.master.ic_port, "robot1", ROBOT, answers={"start_items": lambda body: answer}) as robot:
        assert robot.hello()["kind"] == "res"
        wait_until(lambda: "start_items" in robot.ops(), timeout=20, message="the master to ask for the R side")
        start = dict(robot.requests)["start_items"]
        assert start["start_ros_master_port"] and start["ros_master_uri"] is None    # ss_side R: the robot's

        def refused():
            status, space = platform.space("robot1")
            return space if status == 200 and "not on its own address" in (space.get("reason") or "") else None
        space = wait_until(refused, timeout=20, message="the space to be refused with its reason")
        assert space["paired"] is False
        assert space["ros_master_uri"] is None
        assert repr(elsewhere) in space["reason"] and f"http://{ROBOT}:PORT/" in space["reason"]
        assert "nothing of the space was started against it" in space["reason"]
        brain = next(node for node in space["r_nodes"] if node["sn_name"] == "brain")
        assert brain["state"] != "running"
        assert platform.state("robot1") == (True, False)
        # nothing of the master went to the host the robot named, and no S-side item was started at all
        assert not trap.reached()
        assert not [cmd for _, cmd in platform.leftovers() if "talker" in cmd or "rosmaster" in cmd]
        assert f"service space robot1: not paired: robot robot1 answered that the space's ROS master is at " \
               f"{elsewhere!r}" in platform.master.log_text()
