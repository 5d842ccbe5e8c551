"""FIROS's `include/whitelist.py`: the seed's examples, full-regex matching, and the in-memory edits (write,
remove, restore)."""

import json

import pytest

from include import config as cfg
from include.whitelist import Whitelist, WhitelistError
from tests.support.firos import SEED_WHITELIST


def test_seed_whitelist_examples(tmp_path):
    wl = Whitelist(str(tmp_path / "whitelist.json"), SEED_WHITELIST)
    assert wl.robot_allowed("turtle1") and wl.robot_allowed("turtle_two") and wl.robot_allowed("robot7")
    assert not wl.robot_allowed("turtle") and not wl.robot_allowed("myturtle1") and not wl.robot_allowed("robot")
    assert wl.topic_kinds("turtle1", "cmd_vel") == {"publisher"}
    assert wl.topic_kinds("turtle1", "pose") == {"subscriber"}
    assert wl.topic_kinds("turtle1", "pose2") == set()
    assert wl.topic_kinds("robot1", "cmd_vel_teleop") == {"publisher"}
    assert wl.topic_kinds("robot1", "cmd_vel/teleop") == {"publisher"}
    assert wl.topic_kinds("robot1", "cmd_vel") == set()
    assert wl.topic_kinds("robot1", "move_base/goal") == {"publisher"}
    assert wl.topic_kinds("robot1", "arm/move_base/cancel") == {"publisher"}
    assert wl.topic_kinds("robot1", "move_base/result") == {"subscriber"}
    assert wl.topic_kinds("robot1", "move_base/result_x") == set()


def test_whitelist_write_remove_restore(tmp_path):
    path = tmp_path / "whitelist.json"
    path.write_text(json.dumps(SEED_WHITELIST))
    wl = Whitelist(str(path))
    wl.write({"turtle\\w+": {"subscriber": ["odom"]}, "drone\\d": {"publisher": ["goto"]}})
    assert wl.topic_kinds("turtle1", "odom") == {"subscriber"} and wl.topic_kinds("drone1", "goto") == {"publisher"}
    wl.remove({"turtle\\w+": {"subscriber": ["pose"]}, "drone\\d": {}})
    assert wl.topic_kinds("turtle1", "pose") == set() and not wl.robot_allowed("drone1")
    before = wl.snapshot()
    for bad in ([], {"x(": {}}, {"x": {"publisher": "p"}}, {"x": {"other": []}}, {"x": {"publisher": ["("]}}):
        with pytest.raises(WhitelistError):
            wl.write(bad)
    assert wl.snapshot() == before
    wl.restore()
    assert wl.snapshot() == SEED_WHITELIST
    path.write_text("{bad json")
    with pytest.raises(cfg.ConfigError):
        wl.restore()
    assert wl.snapshot() == SEED_WHITELIST
