"""FIROS with NGSI-LD, repeated commands and live whitelist edits, end to end: a real ROS master, the stand-in
broker (speaking NGSI-LD as Orion-LD does) and FIROS (`rosrun firos core.py`) as real children, `rostopic` and
`tests/support/firos_talker.py` as ROS peers, HTTP on loopback.
"""

import json
import urllib.parse

import pytest

from tests.ngsi_broker.testing import start_broker
from tests.support.firos import (Firos, echoed_messages, received, request, rostopic_echo, rostopic_pub, talker,
                                 v2_value, wait_subscription, write_config)
from tests.support.polling import wait_until

pytestmark = pytest.mark.slow   # real ROS master, broker and FIROS children

CORE = "https://uri.etsi.org/ngsi-ld/v1/ngsi-ld-core-context.jsonld"
LINK = {"Link": f'<{CORE}>; rel="http://www.w3.org/ns/json-ld#context"; type="application/ld+json"'}
SEED_ID = "urn:ngsi-ld:ROBOT:end_end_test"


def ld_entity(broker, eid=SEED_ID):
    status, body = request(broker.port, "GET", f"/ngsi-ld/v1/entities/{urllib.parse.quote(eid, safe='')}",
                           headers=LINK)
    return body if status == 200 else None


def ld_subscriptions(broker):
    status, body = request(broker.port, "GET", "/ngsi-ld/v1/subscriptions", headers=LINK)
    assert status == 200, body
    return body


def ld_command(broker, attr, value, msg_type="std_msgs.msg.String", eid=SEED_ID):
    """An NGSI-LD update of attribute ``attr`` and COMMAND, as a user would send it (Append Entity Attributes,
    POST .../attrs, which also overwrites attributes that exist)."""
    body = {attr: {"type": "Property", "value": value, "messageType": {"type": "Property", "value": msg_type}},
            "COMMAND": {"type": "Property", "value": [attr]}}
    status, answer = request(broker.port, "POST", f"/ngsi-ld/v1/entities/{urllib.parse.quote(eid, safe='')}/attrs",
                             body, headers=LINK)
    assert status == 204, (status, answer)


def test_seed_end_to_end_in_ngsi_ld(procs, ros_master, tmp_path):
    broker = start_broker(procs)
    config = write_config(str(tmp_path / "config"), broker.port, version="ld",
                          descriptions={"end_end_test": {"descriptions": ["http://a.example/x", "http://b.example/y"]}})
    firos = Firos(procs, ros_master, config).start()
    # ~$ rostopic pub -1 s1 std_msgs/String "data: 'test'"  __ns:=end_end_test
    rostopic_pub(procs, ros_master, tmp_path, "s1", "std_msgs/String", "data: 'test'", "__ns:=end_end_test")

    # the entity: urn:ngsi-ld:ROBOT:<name>, type ROBOT, s1 a Property with observedAt, COMMAND, descriptions
    wait_until(lambda: (ld_entity(broker) or {}).get("s1"), timeout=15, message="s1 in the broker")
    entity = ld_entity(broker)
    assert entity["id"] == SEED_ID and entity["type"] == "ROBOT"
    s1 = entity["s1"]
    assert s1["type"] == "Property" and s1["value"]["data"] == "test"
    assert isinstance(s1["value"]["firosstamp"], float) and s1["observedAt"].endswith("Z")
    assert s1["messageType"] == {"type": "Property", "value": "std_msgs.msg.String"}
    assert entity["COMMAND"] == {"type": "Property", "value": ["s1"]}
    assert entity["descriptions"] == {"type": "Property", "value": "http://a.example/x||http://b.example/y"}
    # readable through FIROS too
    status, body = firos.get("/robot/end_end_test")
    assert status == 200 and body["attributes"]["s1"]["value"]["data"] == "test", body
    assert body["attributes"]["s1"]["type"] == "std_msgs.msg.String"

    # a command reaches ROS; the same command twice reaches it twice
    wait_subscription(firos, "end_end_test")
    (sub,) = ld_subscriptions(broker)
    assert sub["entities"] == [{"id": SEED_ID, "type": "ROBOT"}] and sub["watchedAttributes"] == ["p1"]
    assert sub["notification"]["endpoint"]["uri"] == f"http://127.0.0.1:{firos.port}/firos"
    echo = rostopic_echo(procs, ros_master, tmp_path, "/end_end_test/p1", count=2)
    ld_command(broker, "p1", {"data": "move 1 m"})
    wait_until(lambda: len(echoed_messages(procs, echo)) == 1, timeout=15, message="the first command on ROS")
    # FIROS took it: COMMAND back to [] in the broker
    wait_until(lambda: ld_entity(broker)["COMMAND"]["value"] == [], timeout=10, message="COMMAND written back")
    ld_command(broker, "p1", {"data": "move 1 m"})
    wait_until(lambda: len(echoed_messages(procs, echo)) == 2, timeout=15, message="the repeated command on ROS")
    assert [m["data"] for m in echoed_messages(procs, echo)] == ["move 1 m", "move 1 m"]

    # at exit the subscription and the entity are removed
    procs.stop(firos.process)
    assert firos.process.returncode == 0, firos.output()
    assert ld_subscriptions(broker) == [] and ld_entity(broker) is None


MALFORMED_LD = [
    b"not json",
    b"[]",
    b'{"data": [{"id": "urn:ngsi-ld:ROBOT:end_end_test"}]}',                       # no "type": "Notification"
    b'{"type": "Notification", "data": {}}',
    b'{"type": "Notification", "data": [{"type": "ROBOT"}]}',
    b'{"type": "Notification", "data": [{"id": "urn:ngsi-ld:ROBOT:end_end_test", "p1": 5}]}',
    b'{"type": "Notification", "data": [{"id": "urn:ngsi-ld:ROBOT:end_end_test", "p1": {"value": 5}}]}',
    b'{"type": "Notification", "data": [{"id": "urn:ngsi-ld:ROBOT:end_end_test", "p1": {"type": "Property"}}]}',
    b'{"type": "Notification", "data": [{"id": "urn:ngsi-ld:ROBOT:end_end_test", '
    b'"p1": {"type": "Property", "value": {"data": 5}, "messageType": {"type": "Property", '
    b'"value": "std_msgs.msg.String"}}, "COMMAND": {"type": "Property", "value": ["p1"]}}]}',
    b'{"type": "Notification", "data": [{"id": "urn:ngsi-ld:ROBOT:end_end_test", '
    b'"COMMAND": {"type": "Property", "value": 7}}]}',
]


def test_malformed_ld_notifications_get_400_and_firos_keeps_forwarding(procs, ros_master, tmp_path):
    broker = start_broker(procs)
    config = write_config(str(tmp_path / "config"), broker.port, version="ld")
    firos = Firos(procs, ros_master, config).start()
    peer = talker(procs, ros_master, tmp_path, "--rate", "5", "--pub", "/end_end_test/s1", "std_msgs/String",
                  json.dumps({"data": "one"}), "--sub", "/end_end_test/p1", "std_msgs/String")
    wait_until(lambda: (ld_entity(broker) or {}).get("s1"), timeout=15, message="s1 in the broker")
    for raw in MALFORMED_LD:
        status, body = firos.post("/firos", raw=raw)
        assert status == 400, (raw, status, body)
        assert body["result"] == "ERROR" and body["reason"], body
    assert firos.alive() and received(procs, peer, "/end_end_test/p1") == []

    wait_subscription(firos, "end_end_test")
    ld_command(broker, "p1", {"data": "go"})
    wait_until(lambda: {"data": "go"} in received(procs, peer, "/end_end_test/p1"), timeout=15,
               message="the command after the bad notifications")
    before = ld_entity(broker)["s1"]["value"]["firosstamp"]
    wait_until(lambda: ld_entity(broker)["s1"]["value"]["firosstamp"] > before, timeout=15,
               message="s1 still forwarded after the bad notifications")


def v2_forced_command(broker, value):
    status, body = request(broker.port, "POST", "/v2/op/update?options=forcedUpdate", {
        "actionType": "append", "entities": [{"id": "end_end_test", "type": "ROBOT",
                                              "p1": {"type": "std_msgs.msg.String", "value": value},
                                              "COMMAND": {"type": "COMMAND", "value": ["p1"]}}]})
    assert status == 204, body


def test_v2_repeated_command_renewal_and_live_whitelist(procs, ros_master, tmp_path):
    broker = start_broker(procs)
    config = write_config(str(tmp_path / "config"), broker.port, version="v2")
    peer = talker(procs, ros_master, tmp_path, "--rate", "10",
                  "--pub", "/end_end_test/s1", "std_msgs/String", json.dumps({"data": "s1"}),
                  "--pub", "/end_end_test/s2", "std_msgs/String", json.dumps({"data": "s2"}),
                  "--sub", "/end_end_test/p1", "std_msgs/String")
    firos = Firos(procs, ros_master, config).start()
    wait_until(lambda: v2_value(broker, "end_end_test", "s1"), timeout=15, message="s1 in the broker")
    wait_subscription(firos, "end_end_test")

    # the same command twice (forcedUpdate, as Orion needs for an unchanged value) reaches ROS twice
    v2_forced_command(broker, {"data": "forward"})
    wait_until(lambda: len(received(procs, peer, "/end_end_test/p1")) == 1, timeout=15, message="first command")
    v2_forced_command(broker, {"data": "forward"})
    wait_until(lambda: len(received(procs, peer, "/end_end_test/p1")) == 2, timeout=15, message="repeated command")

    # what a broker re-sends without an update (an initial or renewal notification: the current state) does not
    # publish again: FIROS wrote COMMAND back once it took the command
    wait_until(lambda: v2_value(broker, "end_end_test", "COMMAND")["value"] != ["p1"], timeout=10,
               message="COMMAND written back")
    status, entity = request(broker.port, "GET", "/v2/entities/end_end_test?type=ROBOT")
    assert status == 200 and entity["p1"]["value"] == {"data": "forward"}
    status, body = firos.post("/firos", {"subscriptionId": "renewal", "data": [entity]})
    assert status == 200 and body["reason"] == {}, body
    # ... and a third real command still goes through, after the renewal
    v2_forced_command(broker, {"data": "forward"})
    wait_until(lambda: len(received(procs, peer, "/end_end_test/p1")) == 3, timeout=15, message="third command")
    assert received(procs, peer, "/end_end_test/p1") == [{"data": "forward"}] * 3

    # whitelist addition and removal take effect on the mapped robot without a restart
    assert "/firos" not in subscribers(ros_master, "/end_end_test/s2")
    status, _ = firos.admin("/whitelist/write", {"end_end_test": {"subscriber": ["s2"]}})
    assert status == 200
    wait_until(lambda: v2_value(broker, "end_end_test", "s2"), timeout=15, message="s2 mapped after write")
    assert "/firos" in subscribers(ros_master, "/end_end_test/s2")
    status, _ = firos.admin("/whitelist/remove", {"end_end_test": {"subscriber": ["s2"]}})
    assert status == 200
    wait_until(lambda: "/firos" not in subscribers(ros_master, "/end_end_test/s2"), timeout=10,
               message="FIROS's subscriber of s2 dropped")
    s2_stamp = v2_value(broker, "end_end_test", "s2")["value"]["firosstamp"]
    s1_stamp = v2_value(broker, "end_end_test", "s1")["value"]["firosstamp"]
    # s1 keeps flowing (a clock for the check): after a second of s1 updates, s2 has not moved
    wait_until(lambda: v2_value(broker, "end_end_test", "s1")["value"]["firosstamp"] > s1_stamp + 1.0,
               timeout=15, message="s1 updates for a second")
    assert v2_value(broker, "end_end_test", "s2")["value"]["firosstamp"] == s2_stamp
    assert "s2" not in {t["name"] for t in firos.robots()["end_end_test"]["topics"]}

    # and added again: mapped at once
    status, _ = firos.admin("/whitelist/write", {"end_end_test": {"subscriber": ["s2"]}})
    assert status == 200
    wait_until(lambda: v2_value(broker, "end_end_test", "s2")["value"]["firosstamp"] > s2_stamp, timeout=15,
               message="s2 forwarded again after write")
    assert firos.alive()


def subscribers(ros_master, topic):
    _, subs, _ = ros_master.system_state()
    return next((members for name, members in subs if name == topic), [])


def v1_command(broker, text):
    """The seed's updateContext of p1 (v1 text value, quotes as %27) with COMMAND."""
    status, body = request(broker.port, "POST", "/v1/updateContext", {"contextElements": [{
        "type": "ROBOT", "isPattern": "false", "id": "end_end_test", "attributes": [
            {"name": "p1", "type": "std_msgs.msg.String", "value": "{%27data%27: %27" + text + "%27}"},
            {"name": "COMMAND", "type": "COMMAND", "value": ["p1"]}]}], "updateAction": "APPEND"})
    assert status == 200 and "errorCode" not in body, body


def test_v1_second_update_context_is_published_and_the_initial_notification_is_not(procs, ros_master, tmp_path):
    broker = start_broker(procs)      # answers subscribeContext with an initial notification, as Orion < 3.1
    config = write_config(str(tmp_path / "config"), broker.port, version="v1")
    peer = talker(procs, ros_master, tmp_path, "--rate", "5", "--sub", "/end_end_test/p1", "std_msgs/String",
                  "--pub", "/end_end_test/s1", "std_msgs/String", json.dumps({"data": "s1"}))
    firos = Firos(procs, ros_master, config).start()
    first = wait_subscription(firos, "end_end_test")

    v1_command(broker, "123")
    wait_until(lambda: len(received(procs, peer, "/end_end_test/p1")) == 1, timeout=15, message="first command")
    # FIROS takes the command by writing COMMAND back to []; a v1 broker notifies only changes, so the same
    # command sent again before that write would change nothing (a person repeating it is slower than FIROS)
    wait_until(lambda: (v2_value(broker, "end_end_test", "COMMAND") or {}).get("value") == [], timeout=15,
               message="the first command taken (COMMAND back to [])")
    v1_command(broker, "123")      # the seed's updateContext once more: the robot moves again
    wait_until(lambda: len(received(procs, peer, "/end_end_test/p1")) == 2, timeout=15, message="second command")

    # a new subscription (here: the whitelist declares one more publisher topic) gets Orion's initial notification
    # with the entity as it is, p1 included: it is not a command
    status, _ = firos.admin("/whitelist/write", {"end_end_test": {"publisher": [{"topic": "p2",
                                                                                 "type": "std_msgs/String"}]}})
    assert status == 200
    second = wait_until(lambda: firos.stats()["subscriptions"].get("end_end_test") not in (None, first)
                        and firos.stats()["subscriptions"]["end_end_test"], timeout=15, message="the new subscription")
    status, sub = request(broker.port, "GET", f"/v2/subscriptions/{second}")
    assert status == 200 and sub["notification"]["timesSent"] >= 1, sub      # the initial notification
    v1_command(broker, "456")      # a clock: once this arrived, the initial notification was handled before it
    wait_until(lambda: {"data": "456"} in received(procs, peer, "/end_end_test/p1"), timeout=15,
               message="the third command")
    assert received(procs, peer, "/end_end_test/p1") == [{"data": "123"}, {"data": "123"}, {"data": "456"}]
