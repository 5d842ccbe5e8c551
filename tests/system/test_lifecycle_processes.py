"""Robot lifecycle with real agents, real SQLite, real ROS on loopback (issue 4, "Tests that must exist").

A master runs on 127.0.0.1, robots on 127.0.0.2, .3, ...; every agent is ``python3 -m rcm_platform --home DIR``
started as a child; provisioning goes through the RDAPI over HTTP. Each test ends by stopping its agents and
checking that no process of the platform is left (no rosmaster, rosout, rosrun, roslaunch or talker).
"""

import os
import signal
import time

import pytest

from rcm_platform.rcmp_process import AGENT_PRIORITY_BOOST
from tests.support.lifecycle import Platform
from tests.support.polling import wait_until

TALKER = "talker.py"


def node(name, side, topic, package="robotics_test", node_type=TALKER):
    return {"sn_package": package, "sn_type": node_type, "sn_name": name, "sn_params": f"_topic:={topic}",
            "sn_side": side}


def launcher(name, side, prefix):
    return {"sl_package": "robotics_test", "sl_file_launcher": "two_talkers.launch", "sl_name": name,
            "sl_params": f"prefix:={prefix}", "sl_side": side}


@pytest.fixture
def platform(procs, tmp_path):
    plat = Platform(procs, tmp_path)
    try:
        yield plat
    finally:
        plat.stop_all_and_check_nothing_left()


def published_topics(plat, ss_name):
    return {name for name, _ in plat.ros_master(ss_name).getPublishedTopics("")}


def pair_two_sided_robot(plat):
    """Provision "two_sides" (talker "brain" on the S side, "body" on the R side) and robot1 with it, start robot1's
    agent on 127.0.0.2 and wait until it is paired; returns the robot agent. The master must be running."""
    plat.provision_logic("two_sides", sn_list=[node("brain", "S", "brain_chatter"),
                                                node("body", "R", "body_chatter")])
    plat.provision_robot("robot1", "two_sides")
    robot = plat.robot("robot1", "127.0.0.2").start()
    plat.wait_state("robot1", True, True)
    return robot


def finish(plat):
    """Stop every agent (robots first) with SIGTERM, check each exited 0 and nothing of the platform is left."""
    for robot in plat.robots.values():
        if robot.process is not None and robot.process in plat.procs.children:
            assert robot.stop() == 0
    if plat.master.process in plat.procs.children:
        assert plat.master.stop() == 0
    plat.wait_no_leftovers()


def test_s_and_r_nodes_pair_and_share_the_service_space(platform):
    platform.master.start()
    platform.provision_logic("two_sides", sn_list=[node("brain", "S", "brain_chatter"),
                                                    node("body", "R", "body_chatter")])
    platform.provision_robot("robot1", "two_sides")
    assert platform.state("robot1") == (False, False)
    robot = platform.robot("robot1", "127.0.0.2").start()
    platform.wait_state("robot1", True, True)

    wait_until(lambda: {"/brain_chatter", "/body_chatter"} <= published_topics(platform, "robot1"),
               message="both topics in the service space's ROS master")
    status, space = platform.space("robot1")
    assert status == 200
    where = {n["sn_name"]: n["i_name"] for n in space["r_nodes"]}
    assert where == {"brain": "master", "body": "robot1"}
    assert space["ros_master_uri"].startswith("http://127.0.0.1:")
    port = int(space["ros_master_uri"].rstrip("/").rsplit(":", 1)[1])
    assert port >= int(platform.master.keys["ros_port_base"])
    # the R-side node registered from the robot's address, the S-side one from the master's
    master_api = platform.ros_master("robot1")
    assert master_api.lookupNode("/body").startswith("http://127.0.0.2:")
    assert master_api.lookupNode("/brain").startswith("http://127.0.0.1:")
    assert "connected to master" in robot.log_text()
    finish(platform)


def _nice(pid):
    with open(f"/proc/{pid}/stat") as f:
        return int(f.read().rsplit(")", 1)[1].split()[16])   # field 19 of stat: nice


def _logged_start(log_text, key):
    """(timestamp text, argv text) of the agent's log line saying process ``key`` started."""
    for line in log_text.splitlines():
        if f"process {key} started:" in line:
            return line[:23], line.split(", argv ", 1)[1]
    raise AssertionError(f"no start of {key} in the log")


def test_nodes_run_as_one_exec_once_the_master_answers_below_their_agents_priority(platform):
    """Issue 10: a node is exec'd directly (rosrun's bash, catkin_find and rospack cost 0.2 CPU-s per node), only
    once the space's ROS master answers (a rospy node given private params sets them on its master at once and
    dies if none answers), and runs at the niceness its agent started with while a root agent runs
    AGENT_PRIORITY_BOOST levels above it (hellos and heartbeats go first when many nodes start at once)."""
    platform.master.start()
    robot = pair_two_sided_robot(platform)
    master_log, robot_log = platform.master.log_text(), robot.log_text()
    answered = next(line[:23] for line in master_log.splitlines() if "service space robot1: ROS master answers" in line)
    for log_text, key in ((master_log, "ss/robot1/node/brain"), (robot_log, "robot/robot1/node/body"),
                          (master_log, "ss/robot1/rosout")):
        when, argv = _logged_start(log_text, key)
        assert "rosrun" not in argv and argv.startswith("['/"), argv
        assert when >= answered, (key, when, answered)
    base = os.nice(0)
    boost = AGENT_PRIORITY_BOOST if os.geteuid() == 0 and base - AGENT_PRIORITY_BOOST >= -20 else 0
    for agent, topic in ((platform.master, "brain_chatter"), (robot, "body_chatter")):
        assert _nice(agent.process.pid) == base - boost
        node_pids = [pid for pid, cmd in platform.leftovers() if f"_topic:={topic}" in cmd]
        assert len(node_pids) == 1 and _nice(node_pids[0]) == base
    if boost:
        assert "nice levels above the processes it starts" in master_log
    finish(platform)


def test_launcher_nodes_appear_in_associated_r_nodes(platform):
    platform.master.start()
    platform.provision_logic("with_launcher", sl_list=[launcher("pair_of_talkers", "R", "lt")])
    platform.provision_robot("robot1", "with_launcher")
    platform.robot("robot1", "127.0.0.2").start()
    platform.wait_state("robot1", True, True)
    status, space = platform.space("robot1")
    assert status == 200
    (entry,) = space["r_launchers"]
    assert entry["sl_name"] == "pair_of_talkers" and entry["i_name"] == "robot1"
    assert sorted(entry["associated_r_nodes"]) == ["lt_talker_a", "lt_talker_b"]
    assert {"lt_talker_a", "lt_talker_b"} <= {n["sn_name"] for n in space["r_nodes"]}
    wait_until(lambda: {"/launch_chatter_a", "/launch_chatter_b"} <= published_topics(platform, "robot1"))
    finish(platform)


def test_items_that_cannot_start_leave_the_robot_connected_not_paired_with_the_error(platform):
    platform.master.start()
    platform.provision_logic("broken", sn_list=[
        node("ghost", "S", "x", package="no_such_package_here", node_type="nothing.py"),
        {"sn_package": "robotics_test", "sn_type": "crasher.py", "sn_name": "crash", "sn_params": "",
         "sn_side": "R"},
        node("fine", "R", "fine_chatter")])
    platform.provision_robot("robot1", "broken")
    platform.robot("robot1", "127.0.0.2").start()

    def settled_space():
        status, space = platform.space("robot1")
        states = {n["sn_name"]: n.get("state") for n in space["r_nodes"]} if status == 200 else {}
        return space if states.get("ghost") == "failed" and states.get("crash") == "failed" else None

    space = wait_until(settled_space, timeout=30, message="both broken items to be reported failed")
    assert platform.state("robot1") == (True, False)
    errors = {n["sn_name"]: n.get("error") or "" for n in space["r_nodes"]}
    assert "no_such_package_here" in errors["ghost"]
    assert "imaginary_lidar" in errors["crash"]
    assert {n["sn_name"]: n.get("state") for n in space["r_nodes"]}["fine"] == "running"
    finish(platform)


def test_unprovisioned_robot_is_refused_then_connects_once_provisioned(platform):
    platform.master.start()
    platform.provision_logic("one_node", sn_list=[node("brain", "S", "brain_chatter")])
    robot = platform.robot("latecomer", "127.0.0.3").start()
    wait_until(lambda: "not provisioned" in robot.log_text(), message="the refusal reason in the robot's log")
    assert "latecomer" not in platform.instances()
    pid = robot.process.pid
    platform.provision_robot("latecomer", "one_node")
    platform.wait_state("latecomer", True, True, timeout=15)
    assert robot.process.pid == pid and robot.process.poll() is None     # no restart needed
    finish(platform)


def test_robot_with_an_empty_service_logic_pairs(platform):
    platform.master.start()
    platform.provision_logic("empty_logic")
    platform.provision_robot("robot1", "empty_logic")
    platform.robot("robot1", "127.0.0.2").start()
    platform.wait_state("robot1", True, True, timeout=15)
    status, space = platform.space("robot1")
    assert status == 200 and space["r_nodes"] == [] and space["r_launchers"] == []
    finish(platform)


def test_sigkill_robot_disconnects_it_and_leaves_nothing(platform):
    platform.master.start()
    robot = pair_two_sided_robot(platform)
    robot_home = robot.home
    assert any("body_chatter" in cmd for _, cmd in platform.leftovers())

    killed = time.monotonic()
    robot.kill()
    platform.wait_state("robot1", False, False, timeout=3 * platform.heartbeat)
    assert time.monotonic() - killed <= 3 * platform.heartbeat
    wait_until(lambda: platform.space("robot1")[0] == 404, timeout=10, message="the service space to be gone")
    # nothing of the robot's service space is left: not its R-side talker, not the master's side
    wait_until(lambda: not [p for p in platform.leftovers() if p[0] != platform.master.process.pid],
               timeout=10, message="every process of the service space to be gone")
    assert os.path.isdir(robot_home)
    finish(platform)


def test_sigkill_master_stops_robot_items_and_a_new_master_repairs(platform):
    platform.master.start()
    robot = pair_two_sided_robot(platform)

    platform.master.kill()
    wait_until(lambda: not [p for p in platform.leftovers() if p[0] != robot.process.pid],
               timeout=10, message="the robot's R items and the old master's service space to be gone")
    wait_until(lambda: "lost the master" in robot.log_text(), timeout=5)
    platform.master.start()
    platform.wait_state("robot1", True, True, timeout=30)
    wait_until(lambda: {"/brain_chatter", "/body_chatter"} <= published_topics(platform, "robot1"))
    finish(platform)


def test_r_provisioning_a_paired_robot_tears_its_space_down(platform):
    platform.master.start()
    robot = pair_two_sided_robot(platform)

    status, answer = platform.remove_robot("robot1")
    assert (status, answer["result"]) == (200, "OK")
    assert "robot1" not in platform.instances()
    assert platform.space("robot1")[0] == 404
    agents = {platform.master.process.pid, robot.process.pid}
    wait_until(lambda: not [p for p in platform.leftovers() if p[0] not in agents], timeout=10,
               message="the service space's processes to be gone")
    wait_until(lambda: robot.log_text().count("not provisioned") >= 1, timeout=10,
               message="the robot to be refused after its removal")
    finish(platform)


def test_two_robots_with_one_logic_get_separate_spaces(platform):
    platform.master.start()
    platform.provision_logic("two_sides", sn_list=[node("brain", "S", "brain_chatter"),
                                                    node("body", "R", "body_chatter")])
    for index, name in enumerate(("robot1", "robot2")):
        platform.provision_robot(name, "two_sides")
        platform.robot(name, f"127.0.0.{index + 2}").start(wait=False)
    for name in ("robot1", "robot2"):
        platform.robots[name].wait_ready()
        platform.wait_state(name, True, True)
    uris = {name: platform.space(name)[1]["ros_master_uri"] for name in ("robot1", "robot2")}
    assert uris["robot1"] != uris["robot2"]
    for name in ("robot1", "robot2"):
        wait_until(lambda: {"/brain_chatter", "/body_chatter"} <= published_topics(platform, name),
                   message=f"both topics in {name}'s ROS master")
        assert platform.ros_master(name).lookupNode("/body").startswith(
            f"http://{platform.robots[name].keys['vpn_address']}:")
    finish(platform)


def test_four_firos_robots_get_the_four_inbound_ports_and_a_fifth_waits(procs, tmp_path):
    from tests.ngsi_broker.testing import start_broker
    from tests.support.firos import write_config
    from tests.support.firos import v2_entity

    plat = Platform(procs, tmp_path / "platform", inbound_ports=4)
    try:
        broker = start_broker(procs)
        config_dir = write_config(str(tmp_path / "firos-config"), broker.port)
        plat.master.start()
        plat.provision_logic("fiware_robot", sn_list=[
            {"sn_package": "rcm", "sn_type": "rcm_driver.py", "sn_name": "rcm_driver", "sn_params": "",
             "sn_side": "S"},
            {"sn_package": "firos", "sn_type": "core.py", "sn_name": "firos", "sn_params": f"--config {config_dir}",
             "sn_side": "S"},
            node("body", "R", "body_chatter")])
        names = [f"robot{n}" for n in range(1, 6)]
        for index, name in enumerate(names[:4]):
            plat.provision_robot(name, "fiware_robot")
            plat.robot(name, f"127.0.0.{index + 2}").start(wait=False)
        for name in names[:4]:
            plat.robots[name].wait_ready()
            plat.wait_state(name, True, True, timeout=60)
        ports = {name: plat.space(name)[1]["inbound_port"] for name in names[:4]}
        assert sorted(ports.values()) == sorted(plat.inbound_ports)
        for name in names[:4]:
            wait_until(lambda: v2_entity(broker, name) is not None, timeout=30,
                       message=f"the broker entity of {name}")

        plat.provision_robot(names[4], "fiware_robot")
        plat.robot(names[4], "127.0.0.6").start()

        def fifth_refused_a_port():
            status, space = plat.space(names[4])
            return status == 200 and "no inbound open port" in (space.get("reason") or "")

        wait_until(fifth_refused_a_port, timeout=30, message="the fifth robot's reason")
        assert plat.state(names[4]) == (True, False)
        assert plat.space(names[4])[1]["inbound_port"] is None
        # a FIROS robot leaving frees its port for the fifth one
        assert plat.robots["robot1"].stop() == 0
        plat.wait_state("robot1", False, False)
        wait_until(lambda: v2_entity(broker, "robot1") is None, timeout=15,
                   message="FIROS to remove robot1's entity")
        finish(plat)
    finally:
        plat.stop_all_and_check_nothing_left()


def test_ss_side_r_puts_the_ros_master_on_the_robot(platform):
    platform.master.start()
    platform.provision_logic("head_on_robot", ss_side="R", sn_list=[node("brain", "S", "brain_chatter"),
                                                                     node("body", "R", "body_chatter")])
    platform.provision_robot("robot1", "head_on_robot")
    robot = platform.robot("robot1", "127.0.0.2").start()
    platform.wait_state("robot1", True, True)
    status, space = platform.space("robot1")
    assert status == 200 and space["ros_master_uri"].startswith("http://127.0.0.2:")
    wait_until(lambda: {"/brain_chatter", "/body_chatter"} <= published_topics(platform, "robot1"))
    robot_side = [cmd for pid, cmd in platform.leftovers() if "rosmaster" in cmd and robot.home in
                  open(f"/proc/{pid}/environ", "rb").read().decode("utf-8", "replace")]
    assert robot_side, "the space's ROS master runs on the robot's side"
    # the master goes: the robot stops its items and its ROS master
    platform.master.kill()
    wait_until(lambda: not [p for p in platform.leftovers() if p[0] != robot.process.pid], timeout=15,
               message="the robot's ROS master and items to stop")
    finish(platform)


def test_a_server_vm_joins_by_itself_and_a_robots_name_is_refused(platform):
    """CONTRACTS §8: a robot=no agent needs no provisioning; a name provisioned as a robot cannot be a server."""
    platform.master.start()
    platform.provision_logic("vm_logic", sn_list=[node("vm_worker", "R", "vm_chatter")])
    platform.provision_robot("robot1", "vm_logic")
    impostor = platform.robot("robot1", "127.0.0.5", role="server").start()
    wait_until(lambda: "provisioned as a robot" in impostor.log_text(), message="the server's hello refused")
    impostor.stop()
    vm = platform.robot("vm1", "127.0.0.4", role="server").start()
    wait_until(lambda: "as vm1 (127.0.0.4)" in vm.log_text(), message="the server VM to join")
    status, answer = platform.master.get("/platform_instance/read?pi_type=S")
    assert status == 200, answer
    assert [(row["pi_name"], row["connected"], row["address"]) for row in answer["reason"]] == [
        ("master", True, "127.0.0.1"), ("vm1", True, "127.0.0.4")]
    assert "vm1" not in platform.instances()            # a server is no provisioned robot
    finish(platform)


def test_robot_started_before_the_master_retries_until_it_is_up(platform):
    robot = platform.robot("early", "127.0.0.3").start()
    wait_until(lambda: "unreachable" in robot.log_text(), message="the robot to report the master unreachable")
    platform.master.start()
    platform.provision_logic("one_node", sn_list=[node("brain", "S", "brain_chatter")])
    platform.provision_robot("early", "one_node")
    platform.wait_state("early", True, True, timeout=20)     # backoff is capped at 5 s
    finish(platform)


def test_an_r_item_dying_later_unpairs_the_robot_with_the_reason(platform):
    platform.master.start()
    robot = pair_two_sided_robot(platform)
    (body_pid,) = [pid for pid, cmd in platform.leftovers()
                   if "talker.py" in cmd and "body_chatter" in cmd and not cmd.startswith("/bin/bash")
                   and "bash" not in cmd.split()[0]]
    os.kill(body_pid, signal.SIGKILL)
    platform.wait_state("robot1", True, False, timeout=10)
    status, space = platform.space("robot1")
    body = next(n for n in space["r_nodes"] if n["sn_name"] == "body")
    assert status == 200 and body["state"] == "failed" and body["i_name"] == "robot1"
    assert robot.process.poll() is None
    finish(platform)


def test_master_whose_agent_port_is_taken_stops_with_one_clear_line(platform):
    import socket
    blocker = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    blocker.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    blocker.bind(("127.0.0.1", platform.master.ic_port))
    blocker.listen(1)
    try:
        platform.master.start(wait=False)
        wait_until(lambda: platform.master.process.poll() is not None, timeout=20,
                   message="the master to give up")
        assert platform.master.process.returncode != 0
        assert str(platform.master.ic_port) in platform.master.output()
        assert "Traceback" not in platform.master.output()
    finally:
        blocker.close()


def test_a_frozen_robot_is_declared_gone_by_heartbeats_and_repairs_when_it_thaws(platform):
    platform.master.start()
    robot = pair_two_sided_robot(platform)
    brain = [pid for pid, cmd in platform.leftovers() if "brain_chatter" in cmd]
    assert brain

    os.kill(robot.process.pid, signal.SIGSTOP)      # the connection stays open; only heartbeats can tell
    try:
        frozen = time.monotonic()
        # silence is counted from the last frame heard (up to one interval before the freeze), checked each interval
        platform.wait_state("robot1", False, False, timeout=5 * platform.heartbeat + 1.0)
        elapsed = time.monotonic() - frozen
        assert 2 * platform.heartbeat <= elapsed <= 5 * platform.heartbeat + 1.0, elapsed
        wait_until(lambda: not [p for p in brain if os.path.exists(f"/proc/{p}")], timeout=10,
                   message="the master side of the space to stop")
        assert "silent for" in platform.master.log_text()
    finally:
        os.kill(robot.process.pid, signal.SIGCONT)
    platform.wait_state("robot1", True, True, timeout=20)
    finish(platform)


def test_a_frozen_master_makes_the_robot_stop_its_items_and_repair_after_thawing(platform):
    platform.master.start()
    robot = pair_two_sided_robot(platform)
    body = [pid for pid, cmd in platform.leftovers() if "body_chatter" in cmd]
    assert body

    os.kill(platform.master.process.pid, signal.SIGSTOP)
    try:
        wait_until(lambda: not [p for p in body if os.path.exists(f"/proc/{p}")], timeout=10,
                   message="the robot to stop its R items when the master falls silent")
        assert "no heartbeat from the master" in robot.log_text()
    finally:
        os.kill(platform.master.process.pid, signal.SIGCONT)
    platform.wait_state("robot1", True, True, timeout=20)
    wait_until(lambda: {"/brain_chatter", "/body_chatter"} <= published_topics(platform, "robot1"))
    finish(platform)
