"""FIROS end to end: a real ROS master, the stand-in broker and FIROS (`rosrun firos core.py -P PORT --config
DIR`) as real children, driven with real `rostopic` commands and HTTP on loopback.

Covers the seed guide's end-to-end procedure in NGSI v1 and v2, the whitelist (the seed's examples), robot
descriptions, nested messages both ways, `/robots` and `/robot/<name>`, the whitelist API, a broker outage, and
malformed notifications and API bodies.
"""

import http.client
import json
import os
import random
import re

import pytest

from tests.ngsi_broker.testing import start_broker
from tests.support.firos import (Firos, SEED_WHITELIST, echoed_messages, received, request, rostopic_echo,
                                 rostopic_pub, talker, v2_entity, v2_value, wait_subscription, write_config)
from tests.support.polling import wait_until

SEED_QUERY = {"entities": [{"type": "ROBOT", "isPattern": "true", "id": "end_end_test"}], "attributes": ["s1"]}

pytestmark = pytest.mark.slow   # real ROS master, broker and FIROS children


def seed_update(number):
    return {"contextElements": [{"type": "ROBOT", "isPattern": "false", "id": "end_end_test", "attributes": [
        {"name": "p1", "type": "std_msgs.msg.String", "value": "{%27data%27: %27" + str(number) + "%27}"},
        {"name": "COMMAND", "type": "COMMAND", "value": ["p1"]}]}], "updateAction": "APPEND"}


def request_to(host, port, path):
    conn = http.client.HTTPConnection(host, port, timeout=10)
    try:
        conn.request("GET", path)
        resp = conn.getresponse()
        return resp.status, resp.read()
    finally:
        conn.close()


def without_seq(value):
    """A PoseStamped-like dict without firosstamp and header.seq (rospy numbers headers as it publishes)."""
    out = {k: v for k, v in value.items() if k != "firosstamp"}
    out["header"] = {k: v for k, v in out["header"].items() if k != "seq"}
    return out


@pytest.mark.parametrize("version", ["v1", "v2"])
def test_seed_end_to_end(version, procs, ros_master, tmp_path):
    broker = start_broker(procs)
    config = write_config(str(tmp_path / "config"), broker.port, version=version)
    firos = Firos(procs, ros_master, config).start()

    # ~$ rostopic pub -1 s1 std_msgs/String "data: 'test'"  __ns:=end_end_test
    rostopic_pub(procs, ros_master, tmp_path, "s1", "std_msgs/String", "data: 'test'", "__ns:=end_end_test")

    def seed_query_value():
        status, body = request(broker.port, "POST", "/v1/queryContext", SEED_QUERY)
        assert status == 200, body
        element = body["contextResponses"][0]["contextElement"]
        assert (element["id"], element["type"], element["isPattern"]) == ("end_end_test", "ROBOT", "false")
        (attr,) = element["attributes"]
        return attr if attr["name"] == "s1" else None

    attr = wait_until(seed_query_value, timeout=15, message="s1 in the broker")
    assert attr["type"] == "std_msgs.msg.String"
    if version == "v1":
        # the seed's format: {%27firosstamp%27: 1443020619.58971, %27data%27: %27test%27}
        assert re.fullmatch(r"\{%27firosstamp%27: \d+\.\d+, %27data%27: %27test%27\}", attr["value"]), attr
    else:
        value = v2_value(broker, "end_end_test", "s1")
        assert value["type"] == "std_msgs.msg.String"
        assert value["value"]["data"] == "test" and isinstance(value["value"]["firosstamp"], float)
        assert list(value["value"]) == ["firosstamp", "data"]
        assert v2_value(broker, "end_end_test", "COMMAND")["value"] == ["s1"]

    # rostopic echo /end_end_test/p1 in one terminal, the seed's updateContext in the other
    wait_subscription(firos, "end_end_test")
    echo = rostopic_echo(procs, ros_master, tmp_path, "/end_end_test/p1")
    number = random.randint(0, 32767)
    if version == "v1":
        status, body = request(broker.port, "POST", "/v1/updateContext", seed_update(number))
    else:
        status, body = request(broker.port, "POST", "/v2/op/update", {"actionType": "append", "entities": [
            {"id": "end_end_test", "type": "ROBOT",
             "p1": {"type": "std_msgs.msg.String", "value": {"data": str(number)}},
             "COMMAND": {"type": "COMMAND", "value": ["p1"]}}]})
    assert status in (200, 204), body
    wait_until(lambda: any(str(m.get("data")) == str(number) for m in echoed_messages(procs, echo)),
               timeout=15, message="the command on /end_end_test/p1")
    assert firos.alive()


def test_whitelist_descriptions_robots_and_nested_round_trip(procs, ros_master, tmp_path):
    broker = start_broker(procs)
    whitelist = dict(SEED_WHITELIST)
    whitelist["navbot"] = {"publisher": ["cmd_in", "goal"], "subscriber": ["twist", "pose_st", "event"]}
    descriptions = {"turtle1": {"descriptions": ["http://wiki.ros.org/ROS/Tutorials/UsingRxconsoleRoslaunch",
                                                 "http://wiki.ros.org/ROS/Tutorials/UnderstandingNodes"]}}
    config = write_config(str(tmp_path / "config"), broker.port, whitelist=whitelist, descriptions=descriptions)
    twist = {"linear": {"x": 1.5, "y": -2.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": -0.25}}
    pose = {"header": {"seq": 7, "stamp": {"secs": 1443020619, "nsecs": 589710000}, "frame_id": "map"},
            "pose": {"position": {"x": 1.0, "y": 2.0, "z": 3.0},
                     "orientation": {"x": 0.0, "y": 0.0, "z": 0.7071, "w": 0.7071}}}
    peer = talker(procs, ros_master, tmp_path,
                  "--pub", "/turtle1/pose", "geometry_msgs/Pose2D", json.dumps({"x": 1.0, "y": 2.0, "theta": 0.5}),
                  "--pub", "/turtle1/hidden", "std_msgs/String", json.dumps({"data": "secret"}),
                  "--pub", "/turtle/pose", "geometry_msgs/Pose2D", "{}",
                  "--pub", "/myturtle1/pose", "geometry_msgs/Pose2D", "{}",
                  "--pub", "/robot1/move_base/result", "std_msgs/String", json.dumps({"data": "done"}),
                  "--pub", "/robot1/move_base/status", "std_msgs/String", json.dumps({"data": "busy"}),
                  "--pub", "/navbot/twist", "geometry_msgs/Twist", json.dumps(twist),
                  "--pub", "/navbot/pose_st", "geometry_msgs/PoseStamped", json.dumps(pose),
                  "--pub", "/navbot/event", "robotics_msgs/CB_Event",          # a type from the catkin workspace
                  json.dumps({"entity_name": "navbot", "entity_status": 1}),
                  "--sub", "/turtle1/cmd_vel", "geometry_msgs/Twist",
                  "--sub", "/robot1/move_base/goal", "geometry_msgs/PoseStamped",
                  "--sub", "/navbot/cmd_in", "geometry_msgs/Twist",
                  "--sub", "/navbot/goal", "geometry_msgs/PoseStamped")
    firos = Firos(procs, ros_master, config).start()

    # whitelist: robots and topics by full regex match (seed examples)
    wait_until(lambda: {"turtle1", "robot1", "navbot"} <= set(firos.robots()), timeout=15,
               message="the whitelisted robots")
    robots = firos.robots()
    assert set(robots) == {"turtle1", "robot1", "navbot"}      # not "turtle", "myturtle1"
    topics = {(t["name"], t["pubsub"]): t for t in robots["turtle1"]["topics"]}
    assert set(topics) == {("pose", "subscriber"), ("cmd_vel", "publisher")}   # not "hidden"
    assert topics[("pose", "subscriber")]["type"] == "geometry_msgs.msg.Pose2D"
    assert topics[("pose", "subscriber")]["structure"] == {"x": "float64", "y": "float64", "theta": "float64"}
    assert topics[("cmd_vel", "publisher")]["structure"]["linear"] == {"x": "float64", "y": "float64",
                                                                       "z": "float64"}
    assert {(t["name"], t["pubsub"]) for t in robots["robot1"]["topics"]} == {
        ("move_base/result", "subscriber"), ("move_base/goal", "publisher")}
    nav = {(t["name"], t["pubsub"]): t for t in robots["navbot"]["topics"]}
    assert nav[("pose_st", "subscriber")]["structure"]["header"]["stamp"] == "time"

    # descriptions and the mapped attributes in the broker
    wait_until(lambda: (v2_value(broker, "turtle1", "pose") or {}).get("value"), timeout=15,
               message="turtle1.pose in the broker")
    entity = v2_entity(broker, "turtle1")
    assert entity["type"] == "ROBOT"
    assert entity["descriptions"] == {"type": "DescriptionData", "metadata": {}, "value":
                                      "http://wiki.ros.org/ROS/Tutorials/UsingRxconsoleRoslaunch||"
                                      "http://wiki.ros.org/ROS/Tutorials/UnderstandingNodes"}
    assert entity["pose"]["type"] == "geometry_msgs.msg.Pose2D"
    assert {k: v for k, v in entity["pose"]["value"].items() if k != "firosstamp"} == \
        {"x": 1.0, "y": 2.0, "theta": 0.5}
    assert "hidden" not in entity
    assert v2_entity(broker, "myturtle1") is None and v2_entity(broker, "turtle") is None
    wait_until(lambda: v2_value(broker, "robot1", "move_base.result"), timeout=15,
               message="robot1's move_base.result (topic / written as .)")
    assert "move_base.status" not in v2_entity(broker, "robot1")

    # /robot/<name> reads the entity back from the broker
    status, body = firos.get("/robot/turtle1")
    assert status == 200 and body["id"] == "turtle1" and body["connected"] is True
    assert body["attributes"]["pose"]["value"]["theta"] == 0.5
    assert firos.get("/robot/nobody")[0] == 404

    # nested messages ROS -> broker: Twist and PoseStamped with a header, exactly
    wait_until(lambda: v2_value(broker, "navbot", "pose_st"), timeout=15, message="navbot.pose_st")
    nav_entity = v2_entity(broker, "navbot")
    twist_value = nav_entity["twist"]["value"]
    pose_value = nav_entity["pose_st"]["value"]
    assert {k: v for k, v in twist_value.items() if k != "firosstamp"} == twist
    assert without_seq(pose_value) == without_seq(pose)
    wait_until(lambda: v2_value(broker, "navbot", "event"), timeout=15, message="navbot.event")
    event = v2_value(broker, "navbot", "event")
    assert event["type"] == "robotics_msgs.msg.CB_Event"
    assert {k: v for k, v in event["value"].items() if k != "firosstamp"} == {"entity_name": "navbot",
                                                                              "entity_status": 1}

    # ... and back: the broker's own values sent as commands come out on ROS unchanged
    wait_subscription(firos, "navbot")
    status, body = request(broker.port, "POST", "/v2/op/update", {"actionType": "append", "entities": [
        {"id": "navbot", "type": "ROBOT",
         "cmd_in": {"type": "geometry_msgs.msg.Twist", "value": twist_value},
         "goal": {"type": "geometry_msgs.msg.PoseStamped", "value": pose_value},
         "COMMAND": {"type": "COMMAND", "value": ["cmd_in", "goal"]}}]})
    assert status == 204, body
    wait_until(lambda: received(procs, peer, "/navbot/cmd_in") and received(procs, peer, "/navbot/goal"),
               timeout=15, message="the commands on /navbot/cmd_in and /navbot/goal")
    assert received(procs, peer, "/navbot/cmd_in")[0] == twist
    assert without_seq(received(procs, peer, "/navbot/goal")[0]) == without_seq(pose)

    # an update naming only subscriber topics in COMMAND is not published back (no echo)
    assert received(procs, peer, "/turtle1/cmd_vel") == []

    # the whitelist API, on the administration socket: write adds (in memory), remove takes away, restore reloads
    # the file
    status, body = firos.admin("/whitelist/write", {"turtle1": {"subscriber": ["hidden"]}})
    assert status == 200 and "hidden" in body["reason"]["turtle1"]["subscriber"]
    wait_until(lambda: v2_value(broker, "turtle1", "hidden"), timeout=15, message="turtle1.hidden after write")
    status, body = firos.admin("/whitelist/remove", {"robot\\w+": {}})
    assert status == 200 and "robot\\w+" not in body["reason"]
    status, body = firos.admin("/whitelist/restore")
    assert status == 200 and body["reason"] == whitelist

    # disconnect removes the entity; connect brings it back
    status, _ = firos.admin("/robot/disconnect/robot1")
    assert status == 200
    wait_until(lambda: v2_entity(broker, "robot1") is None, timeout=10, message="robot1's entity removed")
    assert "robot1" not in firos.robots()
    assert firos.admin("/robot/disconnect/robot1")[0] == 404
    status, body = firos.admin("/robot/connect", {"name": "robot1"})
    assert status == 200 and body["reason"] == ["robot1"]
    wait_until(lambda: v2_entity(broker, "robot1") is not None, timeout=10, message="robot1 back")
    assert firos.alive()


def test_broker_down_then_up(procs, ros_master, tmp_path):
    broker = start_broker(procs)
    port = broker.port
    config = write_config(str(tmp_path / "config"), port)
    firos = Firos(procs, ros_master, config).start()
    before = talker(procs, ros_master, tmp_path, "--rate", "10", "--pub", "/end_end_test/s1", "std_msgs/String",
                    json.dumps({"data": "before"}), name="talker_before")
    wait_until(lambda: (v2_value(broker, "end_end_test", "s1") or {}).get("value", {}).get("data") == "before",
               timeout=15, message="the first value in the broker")
    wait_subscription(firos, "end_end_test")

    procs.stop(broker.process)
    procs.stop(before)
    talker(procs, ros_master, tmp_path, "--rate", "10", "--pub", "/end_end_test/s1", "std_msgs/String",
           json.dumps({"data": "after"}), name="talker_after")
    wait_until(lambda: firos.stats()["broker_up"] is False, timeout=15, message="FIROS to notice the outage")
    assert firos.alive()
    assert firos.get("/robot/end_end_test")[0] == 503

    broker2 = start_broker(procs, extra_args=["--port", str(port)])
    assert broker2.port == port
    wait_until(lambda: (v2_value(broker2, "end_end_test", "s1") or {}).get("value", {}).get("data") == "after",
               timeout=20, message="the entity to reappear with the newest value")
    wait_until(lambda: request(port, "GET", "/v2/subscriptions")[1], timeout=15,
               message="the subscription re-created")
    status, subs = request(port, "GET", "/v2/subscriptions")
    assert subs[0]["subject"]["entities"] == [{"id": "end_end_test", "type": "ROBOT"}]
    assert subs[0]["notification"]["http"]["url"] == f"http://127.0.0.1:{firos.port}/firos"
    assert firos.alive() and firos.stats()["broker_up"] is True


MALFORMED = [
    ("/firos", b"not json"),
    ("/firos", b"[1, 2, 3]"),
    ("/firos", b"\"text\""),
    ("/firos", b"{}"),
    ("/firos", b'{"data": "x"}'),
    ("/firos", b'{"data": [17]}'),
    ("/firos", b'{"data": [{"type": "ROBOT"}]}'),
    ("/firos", b'{"data": [{"id": "end_end_test", "p1": 5}]}'),
    ("/firos", b'{"contextResponses": {}}'),
    ("/firos", b'{"contextResponses": [{"contextElement": {"attributes": []}}]}'),
    ("/firos", b'{"contextResponses": [{"contextElement": {"id": "end_end_test", "attributes": [{"value": 1}]}}]}'),
    ("/firos", b'{"data": [{"id": "end_end_test", "COMMAND": {"value": 7}}]}'),
    ("/firos", b'{"data": [{"id": "end_end_test", "p1": {"type": "std_msgs.msg.String", "value": {"data": 5}},'
               b' "COMMAND": {"type": "COMMAND", "value": ["p1"]}}]}'),
    ("/firos", b'{"data": [{"id": "end_end_test", "p1": {"type": "std_msgs.msg.String", "value": {"nope": "x"}},'
               b' "COMMAND": {"type": "COMMAND", "value": ["p1"]}}]}'),
    ("/firos", b'{"data": [{"id": "end_end_test", "p1": {"type": "no_such_pkg.msg.Thing", "value": {}},'
               b' "COMMAND": {"type": "COMMAND", "value": ["p1"]}}]}'),
    ("/firos", b'\xff\xfe'),
    ("/whitelist/write", b'{"robot(": {"publisher": []}}'),
    ("/whitelist/write", b'{"end_end_test": {"publisher": "p1"}}'),
    ("/whitelist/remove", b'[]'),
    ("/robot/connect", b'{"name": 17}'),
]


def test_malformed_bodies_get_400_and_firos_keeps_forwarding(procs, ros_master, tmp_path):
    assert len(MALFORMED) == 20
    broker = start_broker(procs)
    config = write_config(str(tmp_path / "config"), broker.port)
    firos = Firos(procs, ros_master, config).start()
    peer = talker(procs, ros_master, tmp_path, "--rate", "5", "--pub", "/end_end_test/s1", "std_msgs/String",
                  json.dumps({"data": "one"}), "--sub", "/end_end_test/p1", "std_msgs/String")
    wait_until(lambda: v2_value(broker, "end_end_test", "s1"), timeout=15, message="s1 in the broker")
    whitelist_before = firos.admin("/whitelist/write", {})[1]["reason"]
    for path, raw in MALFORMED:
        status, body = (firos.post if path == "/firos" else firos.admin)(path, raw=raw)
        assert status == 400, (path, raw, status, body)
        assert body["result"] == "ERROR" and body["reason"], body
    assert firos.admin("/whitelist/write", {})[1]["reason"] == whitelist_before
    assert firos.alive()

    # still forwarding both ways
    procs.stop(peer)
    peer = talker(procs, ros_master, tmp_path, "--rate", "5", "--pub", "/end_end_test/s1", "std_msgs/String",
                  json.dumps({"data": "two"}), "--sub", "/end_end_test/p1", "std_msgs/String", name="talker2")
    wait_until(lambda: v2_value(broker, "end_end_test", "s1")["value"]["data"] == "two", timeout=15,
               message="the new value forwarded after the bad requests")
    wait_subscription(firos, "end_end_test")
    status, _ = request(broker.port, "POST", "/v2/op/update", {"actionType": "append", "entities": [
        {"id": "end_end_test", "type": "ROBOT", "p1": {"type": "std_msgs.msg.String", "value": {"data": "go"}},
         "COMMAND": {"type": "COMMAND", "value": ["p1"]}}]})
    assert status == 204
    wait_until(lambda: {"data": "go"} in received(procs, peer, "/end_end_test/p1"), timeout=15,
               message="the command after the bad requests")


def test_ros_connect_disconnect_service_headers_and_cleanup_at_shutdown(procs, ros_master, tmp_path):
    """NGSI v1 with a Fiware-Service: firos/disconnect and firos/connect from ROS, and at shutdown FIROS removes
    its subscriptions and entities."""
    broker = start_broker(procs)
    config = write_config(str(tmp_path / "config"), broker.port, version="v1", fiware_service="robots",
                          fiware_servicepath="/lab")
    tenant = {"Fiware-Service": "robots", "Fiware-ServicePath": "/lab"}

    def entity(eid, headers=tenant):
        status, body = request(broker.port, "GET", f"/v2/entities/{eid}?type=ROBOT", headers=headers)
        return body if status == 200 else None

    def subscriptions():
        return request(broker.port, "GET", "/v2/subscriptions", headers=tenant)[1]

    talker(procs, ros_master, tmp_path, "--rate", "5", "--pub", "/end_end_test/s1", "std_msgs/String",
           json.dumps({"data": "x"}))
    firos = Firos(procs, ros_master, config).start()
    wait_until(lambda: (entity("end_end_test") or {}).get("s1"), timeout=15, message="s1 in tenant robots")
    assert entity("end_end_test", headers={}) is None             # not in the default tenant
    status, body = firos.get("/robot/end_end_test")                # read back through NGSI v1 queryContext
    assert status == 200 and body["attributes"]["s1"]["value"]["data"] == "x", body
    assert body["attributes"]["s1"]["type"] == "std_msgs.msg.String"
    wait_subscription(firos, "end_end_test")
    assert len(subscriptions()) == 1

    # seed "List of Running Processes" / "Network interfaces Up & Open": a firos core.py process. It listens on
    # its platform address (ROS_IP, 127.0.0.1 here) only, not on the seed's any-address (issue 12, row 4), so
    # another loopback address does not reach it
    cmdlines = []
    for entry in os.listdir("/proc"):
        try:
            if entry.isdigit() and os.getpgid(int(entry)) == firos.process.pid:
                with open(f"/proc/{entry}/cmdline", "rb") as f:
                    cmdlines.append(f.read().replace(b"\0", b" ").decode())
        except OSError:
            continue
    assert any("firos" in c and "core.py" in c and "python" in c for c in cmdlines), cmdlines
    with pytest.raises(ConnectionRefusedError):
        request_to("127.0.0.2", firos.port, "/robots")

    rostopic_pub(procs, ros_master, tmp_path, "/firos/disconnect", "std_msgs/String", "data: end_end_test",
                 name="disconnect")
    wait_until(lambda: entity("end_end_test") is None and subscriptions() == [], timeout=15,
               message="entity and subscription removed after firos/disconnect")
    assert "end_end_test" not in firos.robots()                   # and discovery leaves it alone

    rostopic_pub(procs, ros_master, tmp_path, "/firos/connect", "std_msgs/String", "data: end_end_test",
                 name="connect")
    wait_until(lambda: (entity("end_end_test") or {}).get("s1") and len(subscriptions()) == 1, timeout=15,
               message="entity and subscription back after firos/connect")

    procs.stop(firos.process)
    assert firos.process.returncode == 0, firos.output()
    assert subscriptions() == [] and entity("end_end_test") is None
