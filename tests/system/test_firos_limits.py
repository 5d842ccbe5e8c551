"""FIROS near the broker's size limit, as real children: a ROS master, the stand-in broker (413 above 1 MB, as
Orion), FIROS by rosrun, and a ROS peer publishing a small Pose2D (a new value each time) beside a big
OccupancyGrid. The pose keeps reaching the broker; the map is counted in /stats and said once in FIROS's log:
once because FIROS itself will not send a request over 1 MB, once because the broker answers 413 to a request
FIROS thought small enough (its own limit set higher)."""

import json

import pytest

from tests.ngsi_broker.testing import start_broker
from tests.support.firos import Firos, talker, v2_entity, write_config
from tests.support.polling import wait_until

pytestmark = pytest.mark.slow   # real ROS master, broker and FIROS children

WHITELIST = {"bot": {"subscriber": ["pose", "map"]}}


def grid_file(tmp_path, width, height):
    """A JSON file with an all-free OccupancyGrid of width x height cells (about two JSON bytes a cell)."""
    path = tmp_path / f"grid-{width}x{height}.json"
    path.write_text(json.dumps({"info": {"width": width, "height": height}, "data": [0] * (width * height)}))
    return str(path)


def run(procs, ros_master, tmp_path, grid, max_request_size=None):
    broker = start_broker(procs)
    extra = {}
    if max_request_size:
        extra["contextbroker"] = {"address": "127.0.0.1", "port": broker.port, "max_request_size": max_request_size}
    config = write_config(str(tmp_path / "config"), broker.port, whitelist=WHITELIST, **extra)
    firos = Firos(procs, ros_master, config).start()
    talker(procs, ros_master, tmp_path, "--rate", "2", "--pub", "/bot/pose", "geometry_msgs/Pose2D", '{"x": 0}',
           "--stamp", "/bot/pose", "x", "--pub-file", "/bot/map", "nav_msgs/OccupancyGrid", grid)
    seen = set()

    def poses():
        entity = v2_entity(broker, "bot") or {}
        if "pose" in entity:
            seen.add(entity["pose"]["value"]["x"])
        return len(seen) >= 5
    wait_until(poses, timeout=30, message="five different poses in the broker beside the map")
    stats = wait_until(lambda: firos.stats()["too_large"] >= 3 and firos.stats(), timeout=20,
                       message="three maps counted as too large")
    assert "map" not in v2_entity(broker, "bot")
    said = [line for line in firos.output().splitlines() if "bot.map not sent" in line]
    assert len(said) == 1, said
    return stats, said[0]


def test_a_map_over_the_limit_beside_a_small_topic(procs, ros_master, tmp_path):
    stats, said = run(procs, ros_master, tmp_path, grid_file(tmp_path, 1100, 1000))
    assert stats["too_large_values"]["bot"]["map"]["size"] >= 1100 * 1000 and stats["errors"] == 0
    assert "at least" in said and "1048576" in said       # judged from its serialized size, not converted


def test_a_413_from_the_broker_does_not_stop_the_other_updates(procs, ros_master, tmp_path):
    # FIROS's own limit 4 MB: it sends the 1.2 MB map, the broker answers 413
    stats, said = run(procs, ros_master, tmp_path, grid_file(tmp_path, 800, 750), max_request_size=4 * 1024 * 1024)
    assert "413" in said and stats["too_large_values"]["bot"]["map"]["size"] > 1024 * 1024
    assert stats["errors"] == 0 and stats["broker_up"]
