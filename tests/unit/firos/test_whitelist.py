"""FIROS's `include/whitelist.py`: the seed's examples, full-regex matching, and the in-memory edits (write,
remove, restore)."""

import json
import re

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


LIMITED = {"bot": {"publisher": ["cmd"],
                   "subscriber": ["pose", {"topic": "camera/image_raw", "max_rate": 2, "max_size": 500000},
                                  {"topic": "scan.*", "max_rate": 10}, {"topic": "scan_front", "max_rate": 5},
                                  ".*"]}}


def test_subscriber_entries_may_set_limits_and_the_smallest_counts(tmp_path):
    wl = Whitelist(str(tmp_path / "whitelist.json"), LIMITED)
    assert wl.topic_limits("bot", "camera/image_raw") == (2, 500000)
    assert wl.topic_limits("bot", "scan_front") == (5, None)        # two entries match: the smaller rate
    assert wl.topic_limits("bot", "scan_back") == (10, None)
    assert wl.topic_limits("bot", "pose") == (None, None)
    assert wl.topic_kinds("bot", "camera/image_raw") == {"subscriber"}
    assert wl.snapshot() == LIMITED                                 # the format comes back as written


def test_names_plainly_means_the_topic_itself_written_without_regex(tmp_path):
    wl = Whitelist(str(tmp_path / "whitelist.json"), LIMITED)
    assert wl.names_plainly("bot", "camera/image_raw") == {"subscriber"}
    assert wl.names_plainly("bot", "pose") == {"subscriber"} and wl.names_plainly("bot", "cmd") == {"publisher"}
    assert wl.names_plainly("bot", "scan_back") == set()              # only "scan.*" and ".*" match it
    assert wl.names_plainly("bot", "camera/other") == set()
    assert wl.names_plainly("other", "pose") == set()


@pytest.mark.parametrize("entry,problem", [
    ({"topic": "x", "max_rate": 0}, "max_rate of 'x'"),
    ({"topic": "x", "max_rate": "fast"}, "max_rate of 'x'"),
    ({"topic": "x", "max_size": 1.5}, "max_size of 'x'"),
    ({"topic": "x", "max_size": True}, "max_size of 'x'"),
    ({"topic": "x", "speed": 3}, "may have \"max_rate\" and \"max_size\""),
    ({"max_rate": 3}, "needs \"topic\""),
    ({"topic": "(x"}, "not a valid regular expression"),
    (5, "must be a list of topic regexes"),
])
def test_bad_limit_entries_are_refused_with_a_sentence(entry, problem):
    with pytest.raises(WhitelistError, match=re.escape(problem)):
        Whitelist("unused", {"bot": {"subscriber": [entry]}})


def test_limits_are_for_subscriber_topics_only():
    with pytest.raises(WhitelistError, match="needs \"topic\" .a topic name. and \"type\""):
        Whitelist("unused", {"bot": {"publisher": [{"topic": "cmd", "max_rate": 1}]}})


def test_write_replaces_the_entry_of_the_same_pattern_and_remove_takes_it_by_pattern(tmp_path):
    wl = Whitelist(str(tmp_path / "whitelist.json"), {"bot": {"subscriber": ["map"]}})
    wl.write({"bot": {"subscriber": [{"topic": "map", "max_rate": 0.5}]}})
    assert wl.snapshot()["bot"]["subscriber"] == [{"topic": "map", "max_rate": 0.5}]
    assert wl.topic_limits("bot", "map") == (0.5, None)
    wl.write({"bot": {"subscriber": ["odom"]}})
    wl.remove({"bot": {"subscriber": ["map"]}})
    assert wl.snapshot()["bot"]["subscriber"] == ["odom"] and wl.topic_limits("bot", "map") == (None, None)
