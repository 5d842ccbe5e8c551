"""FIROS's `include/sender.py` near the broker's limits, against the stand-in broker in-process (which answers 413
above 1 MB, as Orion does): a map over the limit beside a small topic (the small one keeps flowing, the map is
counted and said once, judged from its serialized size without being converted), a 413 for a request FIROS
thought small enough (the others still go), values packed into requests under the limit, an entity made again
with values that need several requests, and each topic's max_rate and max_size."""

import io
import logging
import time

import pytest

from geometry_msgs.msg import Pose2D
from include import ros_conversion
from include.ngsi_versions import client_for
from include.ros_conversion import SerializedMessage
from include.sender import Sender
from nav_msgs.msg import OccupancyGrid
from sensor_msgs.msg import Image
from tests.support.firos import settings_for
from tests.support.polling import wait_until

POSE, MAP, IMAGE = "geometry_msgs.msg.Pose2D", "nav_msgs.msg.OccupancyGrid", "sensor_msgs.msg.Image"


def serialized(msg):
    buffer = io.BytesIO()
    msg.serialize(buffer)
    return SerializedMessage(type(msg), buffer.getvalue())


@pytest.fixture(scope="module")
def big_map():
    """A 1,500 x 1,500 occupancy grid as rospy hands it over: 2.25 MB serialized, at least 2.25 MB of JSON."""
    grid = OccupancyGrid()
    grid.info.width = grid.info.height = 1500
    grid.data = b"\x00" * (1500 * 1500)
    return serialized(grid)


def image(size):
    return serialized(Image(height=1, width=size, encoding="mono8", step=size, data=b"\x7f" * size))


def start(tmp_path, broker, version="v2", **extra):
    settings = settings_for(tmp_path, broker.port, version=version, **extra)
    sender = Sender(client_for(settings), settings)
    sender.start()
    sender.create("bot", {})
    client = client_for(settings)
    wait_until(lambda: client.get_entity("bot") is not None, message="the entity")
    return sender, client


def value(client, attr):
    return ((client.get_entity("bot") or {}).get(attr) or {}).get("value")


@pytest.mark.parametrize("version", ["v1", "v2", "ld"])
def test_a_map_over_the_limit_never_blocks_a_small_topic_and_is_said_once(tmp_path, broker, big_map, caplog,
                                                                         monkeypatch, version):
    converted = []
    original = SerializedMessage.message
    monkeypatch.setattr(SerializedMessage, "message", lambda self: converted.append(self.size) or original(self))
    caplog.set_level(logging.WARNING, logger="firos.sender")
    sender, client = start(tmp_path, broker, version)
    try:
        for i in range(3):
            with sender._cond:                   # the map and a pose arrive together: one batch
                sender.offer("bot", "map", MAP, big_map)
                sender.offer("bot", "pose", POSE, serialized(Pose2D(x=float(i))))
            wait_until(lambda: (value(client, "pose") or {}).get("x") == float(i), timeout=10,
                       message=f"pose {i} in the broker beside the map")
        # the pose can be in the broker a moment before the sender has counted its batch
        stats = wait_until(lambda: sender.snapshot_stats()["forwarded"] == 3 and sender.snapshot_stats(),
                           message="the batch counted")
        assert stats["too_large"] == 3 and stats["forwarded"] == 3 and stats["errors"] == 0
        assert list(stats["too_large_values"]) == ["bot"] and list(stats["too_large_values"]["bot"]) == ["map"]
        assert stats["too_large_values"]["bot"]["map"]["count"] == 3
        size = stats["too_large_values"]["bot"]["map"]["size"]
        assert size >= 2 * 1500 * 1500
        assert value(client, "map") is None
        assert big_map.size not in converted     # judged by its serialized size, never deserialized
        said = [r.getMessage() for r in caplog.records if "bot.map not sent" in r.getMessage()]
        assert len(said) == 1 and f"at least {size} bytes" in said[0] and "1048576" in said[0], said
    finally:
        sender.stop()


def test_a_413_for_a_request_under_firos_own_limit_does_not_stop_the_others(tmp_path, broker, caplog):
    caplog.set_level(logging.WARNING, logger="firos.sender")
    sender, client = start(tmp_path, broker, contextbroker={"address": "127.0.0.1", "port": broker.port,
                                                           "max_request_size": 4 * 1024 * 1024})
    try:
        big = image(900_000)                   # 1.2 MB of base64: under FIROS's 4 MB, over the broker's 1 MB
        with sender._cond:
            sender.offer("bot", "camera", IMAGE, big)
            for name in ("a", "b", "c"):
                sender.offer("bot", name, POSE, serialized(Pose2D(x=1.0)))
        wait_until(lambda: all(value(client, name) for name in "abc"), timeout=10, message="a, b and c")
        stats = wait_until(lambda: sender.snapshot_stats()["too_large"] == 1 and sender.snapshot_stats(),
                           message="the image counted")
        assert stats["too_large_values"]["bot"]["camera"]["count"] == 1 and value(client, "camera") is None
        assert any("bot.camera not sent" in r.getMessage() and "413" in r.getMessage() for r in caplog.records)
        sender.offer("bot", "a", POSE, serialized(Pose2D(x=2.0)))       # and later updates still go
        wait_until(lambda: value(client, "a")["x"] == 2.0, message="a later update")
        assert sender.broker_up() and sender.snapshot_stats()["errors"] == 0
    finally:
        sender.stop()


def test_values_are_packed_into_requests_under_the_limit_and_made_again_the_same_way(tmp_path, broker):
    sender, client = start(tmp_path, broker)
    try:
        texts = {name: {"data": name * 400_000} for name in "xyz"}      # three values of 400 kB: 1.2 MB
        with sender._cond:
            for name, data in texts.items():
                sender.offer("bot", name, "std_msgs.msg.String", data)
        wait_until(lambda: sender.snapshot_stats()["forwarded"] == 3, timeout=10, message="the three values")
        stats = sender.snapshot_stats()
        assert stats["requests"] == 2 and stats["too_large"] == 0 and stats["errors"] == 0
        assert client.get_entity("bot")["COMMAND"]["value"] in (["x", "y"], ["z"])
        client.delete_entity("bot")                        # the broker lost the entity: FIROS makes it again
        sender.recreate("bot")
        wait_until(lambda: all((value(client, name) or {}).get("data") == name * 400_000 for name in "xyz"),
                   timeout=10, message="the entity made again with its three values")
    finally:
        sender.stop()


def test_max_size_and_max_rate_of_a_topic(tmp_path, broker):
    sender, client = start(tmp_path, broker)
    try:
        sender.set_limits("bot", "small", max_size=200)
        sender.offer("bot", "small", "std_msgs.msg.String", {"data": "x" * 300})
        wait_until(lambda: sender.snapshot_stats()["too_large"] == 1, message="the value over max_size refused")
        sender.offer("bot", "small", "std_msgs.msg.String", {"data": "x" * 20})
        wait_until(lambda: value(client, "small") == {"firosstamp": value(client, "small")["firosstamp"],
                                                      "data": "x" * 20}, message="a value under max_size")
        sender.set_limits("bot", "slow", max_rate=2.0)       # at most two a second: 0.5 s apart
        sender.offer("bot", "slow", POSE, {"x": 1.0})
        wait_until(lambda: value(client, "slow"), message="the first value")
        first = time.monotonic()
        for i in range(2, 12):
            sender.offer("bot", "slow", POSE, {"x": float(i)})
        wait_until(lambda: value(client, "slow")["x"] == 11.0, message="the newest value")
        assert time.monotonic() - first >= 0.4
        assert sender.snapshot_stats()["skipped"] >= 8     # the ones in between were never sent
    finally:
        sender.stop()


def test_the_size_bound_of_the_map_and_of_a_camera_frame_needs_no_conversion(big_map):
    assert ros_conversion.json_size_lower_bound(OccupancyGrid, big_map.data) >= 2 * 1500 * 1500 - 1
    frame = image(900_000)
    assert ros_conversion.json_size_lower_bound(Image, frame.data) >= 1_200_000      # its base64
    pose = serialized(Pose2D()).data
    assert ros_conversion.json_size_lower_bound(Pose2D, pose) == len('{"x":0.0,"y":0.0,"theta":0.0}')
