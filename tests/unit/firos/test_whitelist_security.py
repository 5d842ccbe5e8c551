"""FIROS's `include/whitelist.py`, its defences: the regex shape check, the length caps, and the rule that only
plain names of the configured whitelist.json may be commanded outside the ROS graph."""

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


def test_only_plain_names_of_the_configured_whitelist_may_be_commanded_outside_the_graph(tmp_path):
    config = write_config(str(tmp_path), 1026, whitelist={"end_end_test": {"publisher": ["p1", "q.*"]}})
    whitelist = Whitelist.load(config)
    assert whitelist.configured_literal("end_end_test", "p1")
    assert not whitelist.configured_literal("end_end_test", "q1")        # a regex entry
    assert not whitelist.configured_literal("other", "p1")
    whitelist.write({"end_end_test": {"publisher": ["p2"]}})
    assert "publisher" in whitelist.topic_kinds("end_end_test", "p2")
    assert not whitelist.configured_literal("end_end_test", "p2")        # an HTTP edit
    whitelist.restore()
    assert whitelist.configured_literal("end_end_test", "p1")
