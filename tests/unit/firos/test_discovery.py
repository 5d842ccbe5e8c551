"""FIROS's `include/discovery.py`: robots from a ROS graph snapshot and from rcm_driver's answer, with the naming
rules of `ngsi_encoding` (and none of its own)."""

import pytest

from include.discovery import robot_from_rcm, robots_from_graph
from include.whitelist import Whitelist
from tests.support.firos import SEED_WHITELIST


def test_robots_from_graph(tmp_path):
    wl = Whitelist(str(tmp_path / "w.json"), SEED_WHITELIST)
    graph = {"/turtle1/pose": ("turtlesim/Pose", True, False),
             "/turtle1/cmd_vel": ("geometry_msgs/Twist", False, True),
             "/turtle1/secret": ("std_msgs/String", True, True),
             "/turtle2/pose": ("turtlesim/Pose", False, True),          # nobody publishes: nothing to forward
             "/robot1/move_base/goal": ("move_base_msgs/MoveBaseActionGoal", False, True),
             "/robot1/move_base/result": ("move_base_msgs/MoveBaseActionResult", True, False),
             "/rosout": ("rosgraph_msgs/Log", True, True),
             "/firos/connect": ("std_msgs/String", True, True),
             "/myturtle/pose": ("turtlesim/Pose", True, False)}
    robots = robots_from_graph(graph, wl)
    assert set(robots) == {"turtle1", "robot1"}
    assert {k: v.kinds for k, v in robots["turtle1"].items()} == {"pose": {"subscriber"},
                                                                   "cmd_vel": {"publisher"}}
    assert robots["robot1"]["move_base/goal"].attribute == "move_base.goal"
    assert set(robots_from_graph(graph, wl, only="robot1")) == {"robot1"}


def test_robot_from_rcm_flips_rcm_driver_point_of_view(tmp_path):
    wl = Whitelist(str(tmp_path / "w.json"), SEED_WHITELIST)
    info = {"topics": [{"name": "/odom", "msg": "nav_msgs/Odometry", "type": "publisher"},
                       {"name": "/odom", "msg": "nav_msgs/Odometry", "type": "subscriber"},
                       {"name": "/bot/arm/cmd", "msg": "std_msgs/String", "type": "subscriber"},
                       {"name": "/rosout", "msg": "rosgraph_msgs/Log", "type": "publisher"},
                       {"name": 5}]}
    topics = robot_from_rcm("bot", info, wl)
    assert topics["odom"].kinds == {"publisher", "subscriber"} and topics["odom"].name == "/odom"
    assert topics["arm/cmd"].kinds == {"publisher"} and topics["arm/cmd"].name == "/bot/arm/cmd"
    assert set(topics) == {"odom", "arm/cmd"}
    # a whitelisted robot name filters rcm_driver's topics as usual
    topics = robot_from_rcm("turtle1", {"topics": [
        {"name": "/turtle1/pose", "msg": "turtlesim/Pose", "type": "publisher"},
        {"name": "/turtle1/other", "msg": "std_msgs/String", "type": "publisher"}]}, wl)
    assert set(topics) == {"pose"}


def test_names_and_types_come_from_ngsi_encoding_only():
    import include.discovery as discovery
    from include import ngsi_encoding as enc
    for loose in ("attribute_name", "python_type", "ros_type", "topic_from_attribute"):
        assert not hasattr(discovery, loose)
    assert enc.relative_topic_to_attribute("move_base/goal") == "move_base.goal"
    assert enc.attribute_to_relative_topic("move_base.goal") == "move_base/goal"
    with pytest.raises(enc.NgsiEncodingError):
        enc.attribute_to_relative_topic("a..b")
    assert enc.ld_entity_id("ROBOT", "robot1") == "urn:ngsi-ld:ROBOT:robot1"
    assert enc.robot_from_ld_entity_id("urn:ngsi-ld:ROBOT:robot1", "ROBOT") == "robot1"
    for bad in ("robot1", "urn:ngsi-ld:Car:robot1", "urn:ngsi-ld:ROBOT:a/b", "urn:ngsi-ld:ROBOT:"):
        with pytest.raises(enc.NgsiEncodingError):
            enc.robot_from_ld_entity_id(bad, "ROBOT")
    # discovery leaves out what the rules refuse
    wl = Whitelist("w.json", {"bot": {"subscriber": [".*"]}})
    graph = {"/bot/ok": ("std_msgs/String", True, False), "/bot/weird": ("notatype", True, False)}
    assert set(robots_from_graph(graph, wl)["bot"]) == {"ok"}


def test_images_and_point_clouds_are_mapped_only_where_an_entry_names_them_plainly():
    wl = Whitelist("w.json", {"bot": {"subscriber": [".*", "front/image_raw",
                                                     {"topic": "lidar/points", "max_rate": 1, "max_size": 900000}],
                                      "publisher": ["display/image"]}})
    graph = {"/bot/front/image_raw": ("sensor_msgs/Image", True, False),
             "/bot/rear/image_raw": ("sensor_msgs/Image", True, False),
             "/bot/rear/image_raw/compressed": ("sensor_msgs/CompressedImage", True, False),
             "/bot/lidar/points": ("sensor_msgs/PointCloud2", True, False),
             "/bot/sonar/points": ("sensor_msgs/PointCloud", True, False),
             "/bot/display/image": ("sensor_msgs/Image", False, True),
             "/bot/map": ("nav_msgs/OccupancyGrid", True, False)}
    topics = robots_from_graph(graph, wl)["bot"]
    assert {k: v.kinds for k, v in topics.items()} == {
        "front/image_raw": {"subscriber"}, "lidar/points": {"subscriber"}, "display/image": {"publisher"},
        "map": {"subscriber"}}
    assert topics["lidar/points"].limits == (1, 900000) and topics["map"].limits == (None, None)


def test_an_rcm_robot_without_whitelist_entry_gets_no_images():
    wl = Whitelist("w.json", {"other": {"subscriber": [".*"]}})
    info = {"topics": [{"name": "/camera/image_raw", "msg": "sensor_msgs/Image", "type": "publisher"},
                       {"name": "/cloud", "msg": "sensor_msgs/PointCloud2", "type": "publisher"},
                       {"name": "/scan", "msg": "sensor_msgs/LaserScan", "type": "publisher"}]}
    assert set(robot_from_rcm("bot", info, wl)) == {"scan"}
    wl = Whitelist("w.json", {"bot": {"subscriber": ["scan", {"topic": "camera/image_raw", "max_rate": 1}]}})
    topics = robot_from_rcm("bot", info, wl)
    assert set(topics) == {"scan", "camera/image_raw"} and topics["camera/image_raw"].max_rate == 1
