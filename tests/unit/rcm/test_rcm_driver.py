"""rcm_driver (rcm/scripts/rcm_driver.py) in this process: its pure helpers, and its agent server on its own (no ROS
needed: its rospy log calls go to Python logging); the RCM agent is a plain TCP client in the test."""

import importlib.util
import json
import os

import pytest

from tests.support.paths import REPO
from tests.support.polling import wait_until
from tests.support.ports import port_accepts

ROOT = REPO
DRIVER_SCRIPT = os.path.join(ROOT, "rcm", "scripts", "rcm_driver.py")


def load_driver_module():
    spec = importlib.util.spec_from_file_location("rcm_driver", DRIVER_SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


driver = load_driver_module()


# ---------------------------------------------------------------------------------------------------------
# Pure helpers

@pytest.mark.parametrize("argv, port", [
    ([], 9998),
    (["port=12345"], 12345),
    (["port:=12346"], 12346),
    (["__name:=rcmdriver", "__log:=/tmp/x.log", "port=1"], 1),
])
def test_parse_port_accepts_both_styles_and_ros_arguments(argv, port):
    assert driver.parse_port(argv) == port


@pytest.mark.parametrize("argv, problem", [
    (["port=abc"], "port must be a number"),
    (["port=0"], "port must be a number"),
    (["port=70000"], "port must be a number"),
    (["--port", "5"], "unknown argument '--port'"),
])
def test_parse_port_rejects_bad_arguments(argv, problem):
    with pytest.raises(driver.UsageError, match=problem):
        driver.parse_port(argv)


def test_rospy_argv_drops_only_our_port_remap():
    assert driver.rospy_argv(["x", "port:=5", "__name:=a", "port=6"]) == ["x", "__name:=a", "port=6"]


@pytest.mark.parametrize("raw, problem", [
    (b"hello", "not JSON"),
    (b"[1, 2]", "JSON list, expected an object"),
    (b'{"r_name": "r1"}', '"rcm_d_cmd" is missing'),
    (b'{"rcm_d_cmd": "explode", "r_name": "r1"}', "unknown command 'explode'"),
    (b'{"rcm_d_cmd": "r_connection"}', '"r_name" is missing'),
    (b'{"rcm_d_cmd": "r_connection", "r_name": 7}', "not a robot name"),
    (b'{"rcm_d_cmd": "r_connection", "r_name": "two words"}', "not a robot name"),
    (b'{"rcm_d_cmd": "r_connection", "r_name": ""}', "not a robot name"),
    (b"\xff\xfe", "not UTF-8"),
])
def test_parse_agent_line_rejects_with_a_reason(raw, problem):
    with pytest.raises(driver.BadLine, match=problem):
        driver.parse_agent_line(raw)


def test_parse_agent_line_and_entity_line_round_trip():
    assert driver.parse_agent_line(b'{"rcm_d_cmd": "r_disconnection", "r_name": "robot_1"}') == \
        ("r_disconnection", "robot_1")
    line = driver.entity_line("robot_1", "e_created")
    assert line.endswith(b"\n") and line.count(b"\n") == 1
    assert json.loads(line) == {"rcm_d_cmd": "e_created", "r_name": "robot_1"}


def test_graph_topics_lists_publishers_and_subscribers_minus_the_platform():
    state = (
        [["/r1/odom", ["/robot"]], ["/rosout", ["/robot"]], ["/rcm/robot_event", ["/rcmdriver"]],
         ["/firos/only", ["/firos"]], ["/both", ["/firos", "/robot"]]],
        [["/r1/cmd", ["/robot"]], ["/r1/odom", ["/viewer"]], ["/firos/cb_event", ["/rcmdriver"]],
         ["/any", ["/rostopic_1"]]],
        [["/rcm/firos_info", ["/rcmdriver"]]],
    )
    types = [["/r1/odom", "nav_msgs/Odometry"], ["/rosout", "rosgraph_msgs/Log"],
             ["/rcm/robot_event", "robotics_msgs/Robot_Event"], ["/firos/only", "std_msgs/String"],
             ["/both", "std_msgs/Int32"], ["/r1/cmd", "geometry_msgs/Twist"],
             ["/firos/cb_event", "robotics_msgs/CB_Event"], ["/any", "*"]]
    assert driver.graph_topics(state, types) == [
        {"name": "/both", "msg": "std_msgs/Int32", "type": "publisher"},
        {"name": "/r1/cmd", "msg": "geometry_msgs/Twist", "type": "subscriber"},
        {"name": "/r1/odom", "msg": "nav_msgs/Odometry", "type": "publisher"},
        {"name": "/r1/odom", "msg": "nav_msgs/Odometry", "type": "subscriber"},
    ]
    assert json.loads(driver.firos_info_json("r1", [])) == {"r1": {"topics": []}}


# ---------------------------------------------------------------------------------------------------------
# The agent server on its own, in this process (no ROS needed: its rospy log calls go to Python logging)

@pytest.fixture
def agent_server():
    commands, servers = [], []

    def start(**kwargs):
        sock = driver.AgentServer.bind(0)
        server = driver.AgentServer(sock, lambda command, name: commands.append((command, name)), **kwargs)
        server.port = sock.getsockname()[1]
        server.start()
        servers.append(server)
        return server

    start.commands = commands
    yield start
    for server in servers:
        server.stop()
        assert not server.thread.is_alive()


def test_an_agent_that_stops_reading_is_dropped_and_others_keep_working(agent_server, agents, caplog):
    server = agent_server(max_pending_out=64 * 1024)
    slow, other = agents(server.port), agents(server.port)
    slow_robot = "slow_" + "x" * 4000        # long (still valid) name: its 4 kB lines fill the kernel's buffers fast
    slow.announce("r_connection", slow_robot)
    other.announce("r_connection", "other_robot")
    wait_until(lambda: len(agent_server.commands) == 2, message="both announcements")

    def flood():
        for _ in range(50):
            server.send_entity_event(slow_robot, "e_created")
        return len(server.clients) == 1
    wait_until(flood, timeout=30, message="the agent that never reads to be dropped")
    assert "does not read its answers" in caplog.text

    server.send_entity_event("other_robot", "e_removed")
    line = other.read_line()
    while line["r_name"] == slow_robot:      # sent to everyone once its announcer was gone
        line = other.read_line()
    assert line == {"rcm_d_cmd": "e_removed", "r_name": "other_robot"}


def test_stop_closes_every_connection_and_the_port(agent_server, agents):
    server = agent_server()
    first, second = agents(server.port), agents(server.port)
    wait_until(lambda: len(server.clients) == 2, message="two connections")
    server.stop()
    assert not server.thread.is_alive()
    assert first.at_eof() and second.at_eof()
    assert not port_accepts(server.port)


# ---------------------------------------------------------------------------------------------------------
# The key the agent starts rcm_driver with: only connections that show it are obeyed (issue 18 item 4)

KEY = "k3y" * 10


def keyed(command, name, key=KEY):
    return {"rcm_d_cmd": command, "r_name": name, "key": key}


def test_with_a_key_only_a_connection_whose_first_line_shows_it_is_obeyed(agent_server, agents):
    server = agent_server(key=KEY)
    stranger, wrong, agent = agents(server.port), agents(server.port), agents(server.port)
    stranger.announce("r_disconnection", "robot1")             # what any local user could send before
    wrong.send(keyed("r_disconnection", "robot1", key="guess"))
    assert stranger.at_eof() and wrong.at_eof()
    agent.send(keyed("r_connection", "robot1"))
    agent.announce("r_disconnection", "robot1")                # later lines of a proven connection need no key
    wait_until(lambda: len(agent_server.commands) == 2, message="the agent's two commands")
    assert agent_server.commands == [("r_connection", "robot1"), ("r_disconnection", "robot1")]
    server.send_entity_event("robot1", "e_removed")
    assert agent.read_line() == {"rcm_d_cmd": "e_removed", "r_name": "robot1"}


def test_connections_that_never_show_the_key_cannot_keep_the_agent_out(agent_server, agents):
    server = agent_server(key=KEY, proof_deadline=0.5)
    squatters = [agents(server.port) for _ in range(driver.MAX_UNPROVEN * 3)]   # connected, silent
    agent = agents(server.port)
    agent.send(keyed("r_connection", "robot7"))
    wait_until(lambda: agent_server.commands == [("r_connection", "robot7")], message="the agent to be obeyed")
    assert all(s.at_eof(timeout=5) for s in squatters)     # evicted by newer ones, or past the deadline
    wait_until(lambda: len(server.clients) == 1, message="only the agent's connection to stay")
    assert server.warnings.written <= driver.WARNING_BURST


def test_without_a_key_any_local_connection_is_obeyed_as_before_but_there_are_at_most_max_agents(agent_server,
                                                                                                   agents):
    server = agent_server()
    clients = [agents(server.port) for _ in range(driver.MAX_AGENTS)]
    wait_until(lambda: len(server.clients) == driver.MAX_AGENTS, message="every agent connection")
    extra = agents(server.port)
    assert extra.at_eof()
    clients[0].announce("r_connection", "robot2")
    wait_until(lambda: agent_server.commands == [("r_connection", "robot2")], message="the hand-started way")
