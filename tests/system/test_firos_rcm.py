"""FIROS with RCM: rcm_driver (`rosrun rcm rcm_driver.py port=N`) and FIROS as real children on one ROS master.

An agent's `r_connection` line on rcm_driver's TCP port makes FIROS ask `/rcm/firos_info` for the service space's
topics, create the robot's entity and announce CB_Event CREATED, which comes back to the agent as `e_created`;
commands from the broker reach the service space's topics; `r_disconnection` removes the entity (`e_removed`).
"""

import json
import socket

import pytest

from tests.ngsi_broker.testing import start_broker
from tests.support.firos import Firos, received, request, talker, v2_entity, wait_subscription, write_config
from tests.support.polling import wait_until
from tests.support.ports import port_accepts, stable_free_ports

pytestmark = pytest.mark.slow   # real ROS master, broker and FIROS children


class AgentLine:
    """The agent's side of rcm_driver's TCP protocol: JSON lines both ways."""

    def __init__(self, port):
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=10)
        self.buffer = b""

    def send(self, obj):
        self.sock.sendall(json.dumps(obj).encode() + b"\n")

    def read(self, timeout=15.0):
        self.sock.settimeout(timeout)
        while b"\n" not in self.buffer:
            chunk = self.sock.recv(4096)
            assert chunk, "rcm_driver closed the connection"
            self.buffer += chunk
        line, self.buffer = self.buffer.split(b"\n", 1)
        return json.loads(line)

    def close(self):
        self.sock.close()


def test_rcm_connection_creates_entity_and_e_created_comes_back(procs, ros_master, tmp_path):
    broker = start_broker(procs)
    config = write_config(str(tmp_path / "config"), broker.port)
    (driver_port,) = stable_free_ports(1)
    procs.start(["/usr/bin/rosrun", "rcm", "rcm_driver.py", f"port={driver_port}"],
                env=ros_master.env({"ROS_LOG_DIR": str(tmp_path / "roslog")}), name="rcm_driver")
    wait_until(lambda: port_accepts(driver_port), timeout=20, message="rcm_driver's TCP port")
    # the robot's service space: no namespace, the whole graph is the robot
    peer = talker(procs, ros_master, tmp_path, "--rate", "5",
                  "--pub", "/odom", "geometry_msgs/Pose2D", json.dumps({"x": 3.0, "y": 4.0, "theta": 1.0}),
                  "--sub", "/cmd_vel", "geometry_msgs/Twist")
    firos = Firos(procs, ros_master, config).start()

    agent = AgentLine(driver_port)
    try:
        agent.send({"rcm_d_cmd": "r_connection", "r_name": "rcmbot"})
        assert agent.read() == {"rcm_d_cmd": "e_created", "r_name": "rcmbot"}
        entity = v2_entity(broker, "rcmbot")
        assert entity is not None and entity["type"] == "ROBOT"
        wait_until(lambda: (v2_entity(broker, "rcmbot") or {}).get("odom"), timeout=15,
                   message="the service space's /odom as rcmbot.odom")
        value = v2_entity(broker, "rcmbot")["odom"]
        assert value["type"] == "geometry_msgs.msg.Pose2D" and value["value"]["theta"] == 1.0
        robots = firos.robots()
        assert {(t["name"], t["pubsub"]) for t in robots["rcmbot"]["topics"]} == {
            ("odom", "subscriber"), ("cmd_vel", "publisher")}

        # a broker command reaches the service space
        wait_subscription(firos, "rcmbot")
        status, _ = request(broker.port, "POST", "/v2/op/update", {"actionType": "append", "entities": [
            {"id": "rcmbot", "type": "ROBOT",
             "cmd_vel": {"type": "geometry_msgs.msg.Twist", "value": {"linear": {"x": 0.5}}},
             "COMMAND": {"type": "COMMAND", "value": ["cmd_vel"]}}]})
        assert status == 204
        wait_until(lambda: received(procs, peer, "/cmd_vel"), timeout=15, message="the command on /cmd_vel")
        assert received(procs, peer, "/cmd_vel")[0]["linear"]["x"] == 0.5

        agent.send({"rcm_d_cmd": "r_disconnection", "r_name": "rcmbot"})
        assert agent.read() == {"rcm_d_cmd": "e_removed", "r_name": "rcmbot"}
        assert v2_entity(broker, "rcmbot") is None
        assert "rcmbot" not in firos.robots()
        wait_until(lambda: request(broker.port, "GET", "/v2/subscriptions")[1] == [], timeout=10,
                   message="rcmbot's subscription removed")
    finally:
        agent.close()
    assert firos.alive()
