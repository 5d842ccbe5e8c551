"""The RDAPI with a real robot agent connected: read shows it connected, ``service_space/read`` answers,
and ``platform_instance/r_provisioning`` disconnects it and tears its service space down before removing it."""

from tests.support.polling import wait_until
from tests.support.ports import port_accepts
from tests.support.rcmp_agent import RcmpAgent


def robot_row(master, name):
    rows = master.get("/platform_instance/read")[1]["reason"]
    return next((r for r in rows if r["pi_name"] == name), None)


def test_r_provisioning_of_a_connected_robot(procs, tmp_path):
    master = RcmpAgent(procs, tmp_path / "master", heartbeat_interval=0.5).start()
    assert master.post("/platform_instance/provisioning", {"pi_name": "robot1", "pi_service_logic": "empty"})[0] == 200
    robot = RcmpAgent(procs, tmp_path / "robot", role="robot", name="robot1", ip_master="127.0.0.1",
                      ic_port=master.ic_port, heartbeat_interval=0.5).start()

    # connected is this issue's; paired (every item up) belongs to the robot-lifecycle issue
    wait_until(lambda: (robot_row(master, "robot1") or {}).get("connected"), timeout=30,
               message="robot1 connected")
    assert robot_row(master, "robot1")["service_logic"] == "empty"
    wait_until(lambda: master.get("/service_space/read?ss_name=robot1")[0] == 200, timeout=15,
               message="robot1's service space to be described")
    space = master.get("/service_space/read?ss_name=robot1")[1]
    assert space["result"] == "OK", space
    for key in ("r_nodes", "r_launchers", "public_ip", "inbound_port"):
        assert key in space["reason"], key
    assert space["reason"]["public_ip"] == "127.0.0.1"
    ros_port = int(space["reason"]["ros_master_uri"].rstrip("/").rsplit(":", 1)[1])
    wait_until(lambda: port_accepts(ros_port), timeout=15, message="the space's ROS master")

    # a service logic in use by a connected robot cannot go
    assert master.post("/service_logic/r_provisioning", {"slg_name": "empty"})[0] == 409

    status, answer = master.post("/platform_instance/r_provisioning", {"pi_name": "robot1"})
    assert status == 200 and answer["result"] == "OK", answer
    assert "disconnecting" in answer["reason"]
    assert master.get("/platform_instance/read")[1]["reason"] == []
    assert master.get("/service_space/read?ss_name=robot1")[0] == 404
    wait_until(lambda: not port_accepts(ros_port), timeout=20, message="the space's ROS master to be gone")
    # the robot keeps running (and retrying); the master refuses it now
    assert robot.process.poll() is None
    assert master.post("/service_logic/r_provisioning", {"slg_name": "empty"})[0] == 200
    assert robot.stop() == 0
    assert master.stop() == 0
