"""bridge.Firos alone, its collaborators faked (no ROS master, no broker): connecting from a graph snapshot, what a
notification publishes (every command, repeats included; FIROS's own values and unmapped names never; topics absent
from the graph only with the type the whitelist declares), the commands counted by outcome, COMMAND written back
once a command is taken, whitelist edits on robots already mapped, a topic changing type, and the NGSI-LD entity ids.
"""

import pytest

from include.bridge import ApiError, Firos
from include.config import Settings
from include.ngsi_versions import client_for
from include.whitelist import Whitelist


class FakeSender:
    def __init__(self):
        self.calls = []
        self.own = set()

    def create(self, robot, static):
        self.calls.append(("create", robot))

    def delete(self, robot):
        self.calls.append(("delete", robot))

    def forget(self, robot, attr):
        self.calls.append(("forget", robot, attr))

    def set_limits(self, robot, attr, max_rate, max_size):
        self.calls.append(("limits", robot, attr, max_rate, max_size))

    def command_taken(self, robot):
        self.calls.append(("taken", robot))

    def recreate(self, robot):
        self.calls.append(("recreate", robot))

    def is_own(self, robot, attr, value):
        return isinstance(value, dict) and (robot, attr, value.get("firosstamp")) in self.own


class FakeSubscriptions:
    def __init__(self):
        self.wanted = {}

    def set(self, robot, attrs):
        self.wanted[robot] = list(attrs)

    def remove(self, robot):
        self.wanted.pop(robot, None)

    def ids(self):
        return {robot: f"sub-{robot}" for robot in self.wanted}


class FakeTopics:
    def __init__(self):
        self.subscribed = {}          # topic -> type
        self.published = []           # (topic, type, msg)
        self.publishers_dropped = []

    def subscribe(self, robot, info):
        if self.subscribed.get(info.name) == info.msg_type:
            return False
        self.subscribed[info.name] = info.msg_type
        return True

    def unsubscribe(self, robot, topic):
        self.subscribed.pop(topic, None)

    def drop_publisher(self, topic):
        self.publishers_dropped.append(topic)

    def publish(self, robot, topic, msg_type, msg, known):
        self.published.append((topic, msg_type, msg))

    def drop_robot(self, robot):
        for topic in [t for t in self.subscribed if t.startswith(f"/{robot}/")]:
            del self.subscribed[topic]


class FakeGraph:
    def __init__(self, topics):
        self.graph = topics

    def topics(self):
        return dict(self.graph)


def make(version="v2", whitelist=None, graph=None):
    settings = Settings(config_dir="/nowhere", environment="test", broker_address="127.0.0.1",
                        ngsi_version=version)
    wl = Whitelist("/nowhere/whitelist.json", whitelist or {
        "bot": {"publisher": ["cmd", {"topic": "go", "type": "std_msgs/Int32"}, "stop"],
                "subscriber": ["pose", "odom"]}})
    graph = FakeGraph(graph if graph is not None else {
        "/bot/pose": ("geometry_msgs/Pose2D", True, False),
        "/bot/odom": ("geometry_msgs/Pose2D", True, False),
        "/bot/cmd": ("std_msgs/String", False, True)})
    firos = Firos(settings, wl, {}, FakeSender(), FakeSubscriptions(), FakeTopics(), graph, client_for(settings))
    firos.scan()
    return firos


def v2_note(robot, command, **attrs):
    entity = {"id": robot, "type": "ROBOT", "COMMAND": {"type": "COMMAND", "value": command, "metadata": {}}}
    for name, (atype, value) in attrs.items():
        entity[name] = {"type": atype, "value": value, "metadata": {}}
    return {"subscriptionId": "s", "data": [entity]}


def ld_note(robot, command, **attrs):
    entity = {"id": f"urn:ngsi-ld:ROBOT:{robot}", "type": "ROBOT",
              "COMMAND": {"type": "Property", "value": command}}
    for name, (atype, value) in attrs.items():
        entity[name] = {"type": "Property", "value": value, "messageType": {"type": "Property", "value": atype}}
    return {"id": "urn:ngsi-ld:Notification:1", "type": "Notification", "subscriptionId": "urn:ngsi-ld:Subscription:1",
            "notifiedAt": "2026-01-01T00:00:00.000Z", "data": [entity]}


def test_connect_maps_whitelisted_topics_and_subscribes_to_publisher_attributes():
    firos = make()
    assert set(firos.robots) == {"bot"}
    assert firos.topics.subscribed == {"/bot/pose": "geometry_msgs/Pose2D", "/bot/odom": "geometry_msgs/Pose2D"}
    # the graph's publisher topics and the declared ones; "stop" when a node uses it
    assert firos.subscriptions.wanted == {"bot": ["cmd", "go"]}
    assert ("create", "bot") in firos.sender.calls


@pytest.mark.parametrize("version,note", [("v2", v2_note), ("ld", ld_note)])
def test_the_same_command_twice_is_published_twice_and_taken_each_time(version, note):
    firos = make(version)
    body = note("bot", ["cmd"], cmd=("std_msgs.msg.String", {"data": "forward 1 m"}))
    assert firos.handle_notification(body) == {"bot": ["cmd"]}
    assert firos.handle_notification(body) == {"bot": ["cmd"]}
    assert [(t, m.data) for t, _, m in firos.topics.published] == [("/bot/cmd", "forward 1 m")] * 2
    assert firos.sender.calls.count(("taken", "bot")) == 2


def test_what_comes_back_without_a_command_is_not_published():
    firos = make()
    # after FIROS took the command, the broker holds COMMAND [] (or FIROS's own list): a renewal re-sends that
    assert firos.handle_notification(v2_note("bot", [], cmd=("std_msgs.msg.String", {"data": "x"}))) == {}
    assert firos.handle_notification(v2_note("bot", ["pose"], pose=("geometry_msgs.msg.Pose2D", {"x": 1.0}))) == {}
    # FIROS's own value coming back
    firos.sender.own.add(("bot", "cmd", 12.5))
    own = v2_note("bot", ["cmd"], cmd=("std_msgs.msg.String", {"firosstamp": 12.5, "data": "mine"}))
    assert firos.handle_notification(own) == {}
    # names that are not topics, unknown robots
    assert firos.handle_notification(v2_note("bot", ["a..b"], **{"a..b": ("std_msgs.msg.String", {})})) == {}
    assert firos.handle_notification(v2_note("nobody", ["cmd"], cmd=("std_msgs.msg.String", {}))) == {}
    assert firos.topics.published == [] and ("taken", "bot") not in firos.sender.calls


def test_a_topic_absent_from_the_graph_is_commanded_only_with_the_type_the_whitelist_declares():
    firos = make()
    published = firos.handle_notification(v2_note("bot", ["go"], go=("std_msgs.msg.Int32", {"data": 3})))
    assert published == {"bot": ["go"]} and firos.topics.published[0][:2] == ("/bot/go", "std_msgs/Int32")
    # an attribute type that names no message type: the declared type is used
    assert firos.handle_notification(v2_note("bot", ["go"], go=("Text", {"data": 4}))) == {"bot": ["go"]}
    assert firos.topics.published[1][:2] == ("/bot/go", "std_msgs/Int32")
    # another type than the declared one is refused
    with pytest.raises(ApiError) as info:
        firos.handle_notification(v2_note("bot", ["go"], go=("std_msgs.msg.String", {"data": "x"})))
    assert info.value.status == 400 and "carries std_msgs.msg.Int32" in info.value.reason
    assert len(firos.topics.published) == 2


def test_a_whitelisted_topic_absent_from_the_graph_is_never_commanded_with_the_callers_type(firos_log):
    firos = make()                      # "stop": a plain publisher entry, no node uses /bot/stop
    note = v2_note("bot", ["stop"], stop=("geometry_msgs.msg.Twist", {"linear": {"x": 9.0}}))
    for _ in range(30):
        assert firos.handle_notification(note) == {}
    assert firos.topics.published == [] and ("taken", "bot") not in firos.sender.calls
    said = [r.getMessage() for r in firos_log.records if "'/bot/stop' is not in the ROS graph" in r.getMessage()]
    assert 1 <= len(said) <= 10, said              # through the budget: at most 10 lines in a window
    assert firos.commands["not_in_graph"] == 30
    # once a node uses the topic, its own type is the one commands take
    firos.graph.graph["/bot/stop"] = ("std_msgs/Empty", False, True)
    firos.scan()
    with pytest.raises(ApiError):
        firos.handle_notification(note)
    assert firos.handle_notification(v2_note("bot", ["stop"], stop=("std_msgs.msg.Empty", {}))) == {"bot": ["stop"]}
    assert firos.topics.published[0][:2] == ("/bot/stop", "std_msgs/Empty")


def test_commands_are_counted_by_outcome():
    firos = make()
    firos.handle_notification(v2_note("bot", ["cmd"], cmd=("std_msgs.msg.String", {"data": "x"})))
    firos.handle_notification(v2_note("bot", ["pose", "nothing"], pose=("geometry_msgs.msg.Pose2D", {"x": 1.0}),
                                      nothing=("std_msgs.msg.String", {})))
    firos.handle_notification(v2_note("nobody", ["cmd"], cmd=("std_msgs.msg.String", {})))
    firos.sender.own.add(("bot", "cmd", 12.5))
    firos.handle_notification(v2_note("bot", ["cmd"], cmd=("std_msgs.msg.String", {"firosstamp": 12.5})))
    with pytest.raises(ApiError):
        firos.handle_notification(v2_note("bot", ["cmd"], cmd=("std_msgs.msg.String", {"data": 5})))
    with pytest.raises(ApiError):
        firos.handle_notification({"not": "a notification"})
    assert firos.commands == {"published": 1, "not_whitelisted": 2, "not_in_graph": 0, "own_update": 1,
                              "unknown_robot": 1, "refused": 2}


def test_a_bad_value_publishes_nothing_of_the_notification():
    firos = make()
    body = v2_note("bot", ["go", "cmd"], go=("std_msgs.msg.Int32", {"data": 3}),
                   cmd=("std_msgs.msg.String", {"data": 5}))
    with pytest.raises(ApiError) as info:
        firos.handle_notification(body)
    assert info.value.status == 400 and "cmd" in info.value.reason and firos.topics.published == []


@pytest.mark.parametrize("body", [
    {"data": []}, {"type": "Notification"}, {"type": "Notification", "data": {}},
    {"type": "Notification", "data": [{"type": "ROBOT"}]},
    {"type": "Notification", "data": [{"id": "urn:ngsi-ld:ROBOT:bot", "cmd": 5}]},
    {"type": "Notification", "data": [{"id": "urn:ngsi-ld:ROBOT:bot", "cmd": {"value": 5}}]},
    {"type": "Notification", "data": [{"id": "urn:ngsi-ld:ROBOT:bot", "cmd": {"type": "Property"}}]},
    {"type": "Notification", "data": [{"id": "urn:ngsi-ld:ROBOT:bot", "r": {"type": "Relationship"}}]},
])
def test_malformed_ld_notifications_are_400(body):
    firos = make("ld")
    with pytest.raises(ApiError) as info:
        firos.handle_notification(body)
    assert info.value.status == 400 and info.value.reason


def test_whitelist_remove_and_write_take_effect_on_a_mapped_robot():
    firos = make()
    firos.whitelist_remove({"bot": {"subscriber": ["odom"], "publisher": ["cmd"]}})
    assert "/bot/odom" not in firos.topics.subscribed and "/bot/pose" in firos.topics.subscribed
    assert ("forget", "bot", "odom") in firos.sender.calls
    assert "/bot/cmd" in firos.topics.publishers_dropped
    assert set(firos.robots["bot"].topics) == {"pose"}
    assert firos.subscriptions.wanted == {"bot": ["go"]}
    # a command for the removed publisher topic is no longer published
    assert firos.handle_notification(v2_note("bot", ["cmd"], cmd=("std_msgs.msg.String", {"data": "x"}))) == {}

    firos.whitelist_write({"bot": {"subscriber": ["odom"], "publisher": ["cmd"]}})
    assert "/bot/odom" in firos.topics.subscribed
    assert set(firos.robots["bot"].topics) == {"pose", "odom", "cmd"}
    assert firos.subscriptions.wanted == {"bot": ["cmd", "go"]}

    # the robot's whole entry removed: it is disconnected, and comes back when allowed again
    whitelist = firos.whitelist.snapshot()
    firos.whitelist_remove({"bot": {}})
    assert "bot" not in firos.robots and ("delete", "bot") in firos.sender.calls and firos.topics.subscribed == {}
    firos.whitelist_write(whitelist)
    assert "bot" in firos.robots and "/bot/pose" in firos.topics.subscribed


def test_a_topic_that_changes_type_is_subscribed_again_with_the_new_type():
    firos = make()
    firos.graph.graph["/bot/pose"] = ("geometry_msgs/Pose", True, False)
    firos.scan()
    assert firos.topics.subscribed["/bot/pose"] == "geometry_msgs/Pose"
    assert firos.robots["bot"].topics["pose"].msg_type == "geometry_msgs/Pose"


def test_v1_subscriptions_also_watch_command_so_that_repeats_notify():
    assert make("v1").subscriptions.wanted == {"bot": ["COMMAND", "cmd", "go"]}
    assert make("ld").subscriptions.wanted == {"bot": ["cmd", "go"]}     # NGSI-LD notifies every update


def test_ld_ids_name_the_robot_and_other_ids_are_ignored():
    firos = make("ld")
    assert firos.read_client.entity_id("bot") == "urn:ngsi-ld:ROBOT:bot"
    body = ld_note("bot", ["cmd"], cmd=("std_msgs.msg.String", {"data": "x"}))
    body["data"][0]["id"] = "bot"
    assert firos.handle_notification(body) == {}


def test_an_ld_json_notification_with_context_members_is_read_like_any_other():
    firos = make("ld")
    body = ld_note("bot", ["cmd"], cmd=("std_msgs.msg.String", {"data": "x"}))
    body["@context"] = "https://uri.etsi.org/ngsi-ld/v1/ngsi-ld-core-context.jsonld"
    body["data"][0]["@context"] = ["https://uri.etsi.org/ngsi-ld/v1/ngsi-ld-core-context.jsonld"]
    body["data"][0]["cmd"] = [{"type": "Property", "value": {"data": "other"}, "datasetId": "urn:x:1"},
                              dict(body["data"][0]["cmd"])]          # several instances: the default one counts
    assert firos.handle_notification(body) == {"bot": ["cmd"]}
    assert firos.topics.published[0][2].data == "x"


def test_whitelist_limits_reach_the_sender_and_an_image_needs_its_plain_name():
    firos = make(whitelist={"bot": {"subscriber": [{"topic": "pose", "max_rate": 2}, ".*", "camera"]}},
                 graph={"/bot/pose": ("geometry_msgs/Pose2D", True, False),
                        "/bot/camera": ("sensor_msgs/Image", True, False),
                        "/bot/other_camera": ("sensor_msgs/Image", True, False)})
    assert ("limits", "bot", "pose", 2, None) in firos.sender.calls
    assert set(firos.topics.subscribed) == {"/bot/pose", "/bot/camera"}
    firos.whitelist_write({"bot": {"subscriber": [{"topic": "pose", "max_rate": 5, "max_size": 1000}]}})
    assert ("limits", "bot", "pose", 5, 1000) in firos.sender.calls
    firos.whitelist_remove({"bot": {"subscriber": ["camera"]}})        # ".*" alone does not map an image
    assert set(firos.topics.subscribed) == {"/bot/pose"} and ("forget", "bot", "camera") in firos.sender.calls
