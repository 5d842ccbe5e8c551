"""FIROS's `include/whitelist.py`, its defences: the regex shape check, the length caps, and the types a whitelist
declares (the only way a topic outside the ROS graph is commanded; never with a caller's type)."""

import re

import pytest

from include.whitelist import Whitelist, WhitelistError, costly_shape, sre_parse, validate
from tests.support.firos import write_config


@pytest.mark.parametrize("pattern, refused", [
    ("(a|a)*b", "alternation inside a repetition"),
    ("(?:a|ab)*c", "alternation inside a repetition"),
    ("(a+)+b", "repetition inside a repetition"),
    ("(a*)*", "repetition inside a repetition"),
    ("(ab{2,3})*", "repetition inside a repetition"),
    ("(x)\\1", "backreference"),
    (".*a.*b.*c", "too many repetitions"),
    (".{0,40}.{0,40}.{0,40}.{0,40}x", "too many repetitions"),
    ("turtle\\w+", None), (".*move_base/goal", None), ("cmd_vel.*teleop", None), (".*foo.*", None),
    ("(cmd|odom)/.*", None), ("(a|b)*", None), ("[ab]*c", None), ("a{1,5}b{1,5}.*", None), ("p1", None),
])
def test_costly_shapes(pattern, refused):
    problem = costly_shape(sre_parse.parse(pattern))
    if refused is None:
        assert problem is None
        validate({"r": {"publisher": [pattern]}})
    else:
        assert refused in problem
        with pytest.raises(WhitelistError):
            validate({"r": {"publisher": [pattern]}})


def test_long_patterns_and_names():
    with pytest.raises(WhitelistError, match="longer than 256"):
        validate({"a" * 257: {}})
    whitelist = Whitelist("unused", {"r\\w*": {"publisher": ["p\\w*"]}})
    assert whitelist.robot_allowed("r" * 256) and not whitelist.robot_allowed("r" * 257)
    assert whitelist.topic_kinds("r1", "p" * 256) == {"publisher"}
    assert whitelist.topic_kinds("r1", "p" * 257) == set()


def test_a_type_is_declared_only_for_a_plain_publisher_topic_and_is_the_one_commands_take(tmp_path):
    config = write_config(str(tmp_path), 1026, whitelist={"end_end_test": {"publisher": [
        {"topic": "p1", "type": "std_msgs.msg.String"}, "p2", "q.*"]}})
    whitelist = Whitelist.load(config)
    assert whitelist.declared_type("end_end_test", "p1") == "std_msgs/String"   # either spelling, kept as pkg/Type
    assert whitelist.snapshot()["end_end_test"]["publisher"][0] == {"topic": "p1", "type": "std_msgs/String"}
    assert whitelist.declared_type("end_end_test", "p2") is None                 # a plain name declares nothing
    assert whitelist.declared_type("end_end_test", "q1") is None and whitelist.declared_type("other", "p1") is None
    whitelist.write({"end_end_test": {"publisher": [{"topic": "p3", "type": "geometry_msgs/Twist"}]}})
    assert whitelist.declared_types("end_end_test") == {"p1": "std_msgs/String", "p3": "geometry_msgs/Twist"}
    whitelist.write({"end_.*": {"publisher": [{"topic": "p1", "type": "std_msgs/Int32"}]}})
    assert whitelist.declared_type("end_end_test", "p1") is None                 # two types: which is meant?
    whitelist.restore()
    assert whitelist.declared_types("end_end_test") == {"p1": "std_msgs/String"}
    for bad, problem in (({"topic": "p.*", "type": "std_msgs/String"}, "not a regular expression"),
                         ({"topic": "p1", "type": "String"}, "is not a message type"),
                         ({"topic": "p1"}, "needs \"topic\""),
                         ({"topic": "p1", "type": "std_msgs/String", "max_rate": 1}, "nothing else")):
        with pytest.raises(WhitelistError, match=re.escape(problem)):
            whitelist.write({"end_end_test": {"publisher": [bad]}})