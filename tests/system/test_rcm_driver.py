"""rcm_driver (rcm/scripts/rcm_driver.py), the real node against a real ROS master.

The node is started as ``rosrun rcm rcm_driver.py port=N``; ROS-side peers are ``tests.support.ros_probe`` child
processes (one rospy node per pytest process would tie the whole suite to one master), and the RCM agent is a
plain TCP client in the test (``tests/unit/rcm/test_rcm_driver.py`` has the driver's helpers).
"""

import json
import os
import signal
import socket

import pytest

from tests.support.polling import wait_until
from tests.support.ports import stable_free_ports
from tests.support.processes import ros_env

PROBE = ["/usr/bin/python3", "-m", "tests.support.ros_probe"]
CONNECTED, DISCONNECTED = 1, 0
CREATED, REMOVED = 1, 0


# ---------------------------------------------------------------------------------------------------------
# The real node


@pytest.fixture
def env(ros_master, tmp_path):
    log_dir = tmp_path / "roslog"
    log_dir.mkdir()
    return ros_master.env({"ROS_LOG_DIR": str(log_dir)})


def start_driver(procs, env, port_arg=None):
    (port,) = stable_free_ports(1)
    arg = port_arg or "port="
    proc = procs.start(["/usr/bin/rosrun", "rcm", "rcm_driver.py", f"{arg}{port}"], env=env, name="rcm_driver")
    wait_until(lambda: "listening for RCM agents" in procs.output(proc) or proc.poll() is not None,
               timeout=20, message="rcm_driver to start")
    assert proc.poll() is None, procs.output(proc)
    proc.port = port
    return proc


def probe_output(procs, proc):
    """The JSON objects a probe printed so far (rospy's own log lines are skipped)."""
    objects = []
    for line in procs.output(proc).splitlines():
        if line.startswith("{"):
            objects.append(json.loads(line))
    return objects


def start_probe(procs, env, *args, ready_key):
    proc = procs.start(PROBE + list(args), env=env, name="probe")
    wait_until(lambda: any(o.get(ready_key) for o in probe_output(procs, proc)) or proc.poll() is not None,
               timeout=20, message=f"probe {args[:2]} to be ready")
    assert proc.poll() is None, procs.output(proc)
    return proc


def echo(procs, env, topic, msg_type, *ros_args):
    return start_probe(procs, env, "echo", topic, msg_type, *ros_args, ready_key="ready")


def publish(procs, env, topic, msg_type, fields, *ros_args):
    return start_probe(procs, env, "pub", topic, msg_type, json.dumps(fields), *ros_args, ready_key="published")


def robot_events(procs, proc):
    return [o for o in probe_output(procs, proc) if "instance_name" in o]


def test_agent_commands_become_robot_events_and_entity_events_come_back(procs, env, agents):
    node = start_driver(procs, env)
    listener = echo(procs, env, "/rcm/robot_event", "robotics_msgs/Robot_Event")
    agent = agents(node.port)

    agent.announce("r_connection", "robot1")
    wait_until(lambda: robot_events(procs, listener) == [{"instance_name": "robot1", "instance_status": CONNECTED}],
               message="Robot_Event robot1 CONNECTED")

    publish(procs, env, "/firos/cb_event", "robotics_msgs/CB_Event",
            {"entity_name": "robot1", "entity_status": CREATED})
    assert agent.read_line() == {"rcm_d_cmd": "e_created", "r_name": "robot1"}

    agent.announce("r_disconnection", "robot1")
    wait_until(lambda: robot_events(procs, listener)[1:] == [{"instance_name": "robot1",
                                                              "instance_status": DISCONNECTED}],
               message="Robot_Event robot1 DISCONNECTED")
    publish(procs, env, "/firos/cb_event", "robotics_msgs/CB_Event",
            {"entity_name": "robot1", "entity_status": REMOVED})
    assert agent.read_line() == {"rcm_d_cmd": "e_removed", "r_name": "robot1"}
    output = procs.output(node)
    assert "r_connection robot1" in output and "e_created robot1 sent to" in output


def test_late_subscriber_gets_the_latest_event(procs, env, agents):
    node = start_driver(procs, env)
    agent = agents(node.port)
    agent.announce("r_connection", "early")
    wait_until(lambda: "published Robot_Event early CONNECTED" in procs.output(node), message="the publish")
    listener = echo(procs, env, "/rcm/robot_event", "robotics_msgs/Robot_Event")
    wait_until(lambda: robot_events(procs, listener) == [{"instance_name": "early", "instance_status": CONNECTED}],
               message="the latched Robot_Event")


def test_firos_info_lists_the_graph_topics_but_not_the_platforms(procs, env, ros_master):
    start_driver(procs, env)
    publish(procs, env, "/robot1/chatter", "std_msgs/String", {"data": "hi"})
    echo(procs, env, "/robot1/chatter", "std_msgs/String")
    echo(procs, env, "/robot1/cmd", "geometry_msgs/Twist")
    echo(procs, env, "/rcm/robot_event", "robotics_msgs/Robot_Event")            # FIROS-like listener
    publish(procs, env, "/firos/status", "std_msgs/String", {"data": "x"}, "__name:=firos")   # FIROS itself
    assert "/firos" in ros_master.nodes() and "/rcmdriver" in ros_master.nodes()

    call = procs.start(PROBE + ["call", "/rcm/firos_info", "robotics_msgs/FIROS_Info",
                                json.dumps({"instance_name": "robot1"})], env=env, name="call")
    wait_until(lambda: call.poll() is not None, timeout=20, message="the firos_info call")
    assert call.returncode == 0, procs.output(call)
    answer = json.loads(probe_output(procs, call)[-1]["json_format"])
    assert answer == {"robot1": {"topics": [
        {"name": "/robot1/chatter", "msg": "std_msgs/String", "type": "publisher"},
        {"name": "/robot1/chatter", "msg": "std_msgs/String", "type": "subscriber"},
        {"name": "/robot1/cmd", "msg": "geometry_msgs/Twist", "type": "subscriber"},
    ]}}


def test_malformed_lines_are_logged_and_the_next_good_line_works(procs, env, agents):
    node = start_driver(procs, env)
    listener = echo(procs, env, "/rcm/robot_event", "robotics_msgs/Robot_Event")
    agent = agents(node.port)
    bad_lines = [
        (b"not json at all\n", "line is not JSON"),
        (b"[1, 2]\n", "expected an object"),
        (b'{"rcm_d_cmd": "r_connection"}\n', '"r_name" is missing'),
        (b'{"rcm_d_cmd": "explode", "r_name": "robot2"}\n', "unknown command 'explode'"),
        (b'{"rcm_d_cmd": "r_connection", "r_name": "bad name!"}\n', "is not a robot name"),
        (b"\xff\xfe\n", "not UTF-8"),
        (b"y" * 10000 + b"\n", "line longer than 4096 bytes discarded"),
        (b'{"rcm_d_cmd": "r_connection", "r_name": "' + b"z" * 5000 + b'"}\n', "line longer than 4096 bytes"),
    ]
    for data, _ in bad_lines:
        agent.send(data)
    agent.announce("r_connection", "robot2")

    wait_until(lambda: robot_events(procs, listener), message="a Robot_Event")
    assert robot_events(procs, listener) == [{"instance_name": "robot2", "instance_status": CONNECTED}]
    output = procs.output(node)
    for _, reason in bad_lines:
        assert reason in output
    assert output.count("bad line ignored") == 6
    assert output.count("line longer than 4096 bytes discarded") == 2
    assert "Traceback" not in output
    assert node.poll() is None


def test_two_agents_each_get_their_robots_events(procs, env, agents):
    node = start_driver(procs, env)
    first, second = agents(node.port), agents(node.port)
    first.announce("r_connection", "robotA")
    second.announce("r_connection", "robotB")
    wait_until(lambda: "r_connection robotA" in procs.output(node) and "r_connection robotB" in procs.output(node),
               message="both announcements")

    publish(procs, env, "/firos/cb_event", "robotics_msgs/CB_Event",
            {"entity_name": "robotB", "entity_status": CREATED})
    assert second.read_line() == {"rcm_d_cmd": "e_created", "r_name": "robotB"}
    # nobody announced robotX: everyone hears it, and it is the first line the first agent gets
    publish(procs, env, "/firos/cb_event", "robotics_msgs/CB_Event",
            {"entity_name": "robotX", "entity_status": REMOVED})
    assert first.read_line() == {"rcm_d_cmd": "e_removed", "r_name": "robotX"}
    assert second.read_line() == {"rcm_d_cmd": "e_removed", "r_name": "robotX"}

    # the first agent leaves: its robot's events now go to whoever is still connected
    first.close()
    wait_until(lambda: "disconnected (closed by the agent); 1 connection(s) left" in procs.output(node),
               message="the driver to notice the closed connection")
    publish(procs, env, "/firos/cb_event", "robotics_msgs/CB_Event",
            {"entity_name": "robotA", "entity_status": CREATED})
    assert second.read_line() == {"rcm_d_cmd": "e_created", "r_name": "robotA"}
    assert node.poll() is None


def test_port_in_use_is_one_clear_line_and_exit_status_1(procs, tmp_path):
    env = ros_env({"ROS_LOG_DIR": str(tmp_path)})
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        proc = procs.start(["/usr/bin/rosrun", "rcm", "rcm_driver.py", f"port={port}"], env=env, name="rcm_driver")
        wait_until(lambda: proc.poll() is not None, timeout=20, message="rcm_driver to give up")
    output = procs.output(proc)
    assert proc.returncode == 1
    assert output.strip() == f"rcm_driver: cannot listen on 127.0.0.1:{port}: Address already in use"


def test_bad_port_argument_is_a_usage_error(procs, tmp_path):
    env = ros_env({"ROS_LOG_DIR": str(tmp_path)})
    proc = procs.start(["/usr/bin/rosrun", "rcm", "rcm_driver.py", "port=ninety"], env=env, name="rcm_driver")
    wait_until(lambda: proc.poll() is not None, timeout=20, message="rcm_driver to refuse")
    assert proc.returncode == 2
    output = procs.output(proc)
    assert "port must be a number from 1 to 65535, got 'ninety'" in output and "Traceback" not in output


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_remap_style_port_and_clean_stop_on_signal(procs, env, agents, ros_master, sig):
    node = start_driver(procs, env, port_arg="port:=")
    agent = agents(node.port)
    agent.announce("r_connection", "robot3")
    wait_until(lambda: "r_connection robot3" in procs.output(node), message="the announcement")
    assert "/rcmdriver" in ros_master.nodes()

    os.killpg(node.pid, sig)
    wait_until(lambda: node.poll() is not None, timeout=15, message="rcm_driver to stop")
    assert node.returncode == 0, procs.output(node)
    assert agent.at_eof()
    assert "rcm_driver: stopped" in procs.output(node)
    assert "/rcmdriver" not in ros_master.nodes()
