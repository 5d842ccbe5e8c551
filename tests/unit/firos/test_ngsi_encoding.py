"""Tests of firos/scripts/include/ngsi_encoding.py: the seed's v1 text, exact v1/v2 round trips of awkward strings,
lenient decoding, attribute and type naming, firosstamp, and the whole path from a ROS message to the broker value."""

import io
import json

import pytest

from include import ngsi_encoding as ne
from include import ros_conversion as rc

SEED_V1_VALUE = "{%27firosstamp%27: 1443020619.58971, %27data%27: %27test%27}"
SEED_UPDATE_VALUE = "{%27data%27: %2712345%27}"


def test_v1_encoding_reproduces_the_seed_output():
    value = ne.with_firosstamp({"data": "test"}, 1443020619.58971)
    assert ne.encode_v1(value) == SEED_V1_VALUE


def test_v1_decodes_the_seed_texts():
    assert ne.decode_v1(SEED_V1_VALUE) == {"firosstamp": 1443020619.58971, "data": "test"}
    assert ne.split_firosstamp(ne.decode_v1(SEED_V1_VALUE)) == ({"data": "test"}, 1443020619.58971)
    assert ne.decode_v1(SEED_UPDATE_VALUE) == {"data": "12345"}


@pytest.mark.parametrize("text,expected", [
    ("{'data': 'test'}", {"data": "test"}),
    ("{%27data%27: u%27test%27}", {"data": "test"}),
    ("{'firosstamp': 1443020619.58971, 'data': 'test'}", {"firosstamp": 1443020619.58971, "data": "test"}),
    ("{'a': True, 'b': None, 'c': (1, 2), 'd': [False]}", {"a": True, "b": None, "c": [1, 2], "d": [False]}),
    ("{'it': \"it's\"}", {"it": "it's"}),
    ('{"data": "raw json"}', {"data": "raw json"}),
    ("{%27linear%27: {%27x%27: 1.5, %27y%27: 0, %27z%27: -2}}", {"linear": {"x": 1.5, "y": 0, "z": -2}}),
    ("  {%27data%27: %27spaced%27}  ", {"data": "spaced"}),
])
def test_v1_accepts_single_quote_and_raw_variants(text, expected):
    assert ne.decode_v1(text) == expected


def test_v1_decode_copies_compound_values():
    compound = {"data": "x", "list": (1, 2)}
    decoded = ne.decode_v1(compound)
    assert decoded == {"data": "x", "list": [1, 2]} and decoded is not compound


# Strings chosen to break naive encodings: every forbidden character, '%' and things that look like escapes.
AWKWARD = [
    "", "test", "%", "%27", "%2527", "%25", "%3C", "%3c", "100%", "%zz", "a%", "\\", "\\%27", "\\\"", "'\"'",
    "<>\"'=;()", "x=1; y=(2)", "<script>alert('x')</script>", "\n\t\r\x00\x7f", "\u00e9\u6f22\U0001f916",
    "\u2028\u2029", "\\u0025", "{%27a%27: 1}", "%%%%", "%2", "%'",
]


@pytest.mark.parametrize("text", AWKWARD)
def test_v1_round_trip_is_exact(text):
    value = {"data": text, text: [text, {"k": text}], "n": 1.5, "b": False, "z": None}
    encoded = ne.encode_v1(value)
    assert ne.decode_v1(encoded) == value
    assert not set(encoded) & set(ne.FORBIDDEN_CHARACTERS)
    assert encoded.replace("%27", "").count("%") == 0


@pytest.mark.parametrize("text", AWKWARD)
def test_v2_round_trip_is_exact(text):
    value = {"data": text, text: [text, {"k": text}], "n": 1.5, "i": -3, "b": True, "z": None}
    encoded = ne.encode_v2(value)
    wire = json.loads(json.dumps(encoded, allow_nan=False))
    assert ne.decode_v2(wire) == value
    for string in _strings(encoded):
        assert not set(string) & set(ne.FORBIDDEN_CHARACTERS), string


def _strings(obj):
    if isinstance(obj, str):
        yield obj
    elif isinstance(obj, dict):
        for key, item in obj.items():
            yield key
            yield from _strings(item)
    elif isinstance(obj, list):
        for item in obj:
            yield from _strings(item)


@pytest.mark.parametrize("plain,encoded", [
    ("a<b>c", "a%3Cb%3Ec"), ("\"q\"", "%22q%22"), ("'s'", "%27s%27"), ("x=1;", "x%3D1%3B"), ("(p)", "%28p%29"),
    ("50%", "50%25"), ("%27", "%2527"), ("plain text", "plain text"),
])
def test_v2_escapes_are_the_documented_ones(plain, encoded):
    assert ne.encode_v2(plain) == encoded
    assert ne.decode_v2(encoded) == plain


@pytest.mark.parametrize("received,decoded", [
    ("50%", "50%"), ("%41", "%41"), ("%3c", "<"), ("%3C%3e", "<>"), ("%", "%"), ("%2", "%2"), ("%%3C", "%<"),
])
def test_v2_decode_leaves_foreign_percent_text_alone(received, decoded):
    assert ne.decode_v2(received) == decoded


def test_v2_keeps_numbers_booleans_null_and_structure():
    value = {"a": [1, 2.5, True, None, {"b": []}], "c": {}}
    assert ne.encode_v2(value) == value and ne.decode_v2(value) == value
    assert ne.encode_v2((1, "(")) == [1, "%28"]


@pytest.mark.parametrize("function,value,message", [
    (ne.encode_v1, ["not", "an", "object"], "a v1 value must be a JSON object, got list"),
    (ne.encode_v1, {"x": float("nan")}, "value is not JSON-safe: Out of range float values are not JSON compliant"),
    (ne.encode_v1, {"x": {1, 2}}, "value is not JSON-safe: Object of type set is not JSON serializable"),
    (ne.encode_v2, {"x": float("inf")}, "value.x: inf is not a JSON number"),
    (ne.encode_v2, {"x": [b"bytes"]}, "value.x[0]: bytes is not a JSON value"),
    (ne.encode_v2, {1: "x"}, "value: object keys must be strings, got int"),
    (ne.decode_v2, {"x": object()}, "value.x: object is not a JSON value"),
    (ne.decode_v1, 5, "a v1 value must be text, got int"),
    (ne.decode_v1, "[1, 2]", "a v1 value must hold a JSON object, got an array"),
    (ne.decode_v1, "%27text%27", "a v1 value must hold a JSON object, got a string"),
    (ne.decode_v1, "", "value is neither JSON nor a Python literal (quotes written %27): ''"),
    (ne.decode_v1, "{%27a%27: NaN}",
     "value is neither JSON nor a Python literal (quotes written %27): '{%27a%27: NaN}'"),
    (ne.decode_v1, "{'a': {1, 2}}", "value.a: set is not a JSON value"),
    (ne.decode_v1, "{1: 'a'}", "value: object keys must be strings, got int"),
    (ne.decode_v1, "{'a': __import__('os')}",
     "value is neither JSON nor a Python literal (quotes written %27): \"{'a': __import__('os')}\""),
])
def test_bad_values_get_a_clear_error(function, value, message):
    with pytest.raises(ne.NgsiEncodingError) as caught:
        function(value)
    # Python 3.12+ adds the offending value to json's own messages ("...not JSON compliant: nan")
    assert str(caught.value) == message or str(caught.value).startswith(message + ": "), str(caught.value)


def test_v1_decode_survives_absurd_nesting():
    with pytest.raises(ne.NgsiEncodingError) as caught:
        ne.decode_v1("[" * 100000)
    assert str(caught.value).endswith("'" + "[" * 80 + "'...")
    with pytest.raises(ne.NgsiEncodingError):
        ne.decode_v1("{%27a%27: " * 50000)


NAMES = [
    ("robot1", "/robot1/move_base/goal", "move_base.goal"),
    ("end_end_test", "/end_end_test/s1", "s1"),
    ("turtle1", "/turtle1/pose", "pose"),
    ("r", "/r/a/b/c/d", "a.b.c.d"),
    ("Robot_2", "/Robot_2/cmd_vel", "cmd_vel"),
]


@pytest.mark.parametrize("robot,topic,attribute", NAMES)
def test_topic_and_attribute_names_map_both_ways(robot, topic, attribute):
    assert ne.topic_to_attribute(robot, topic) == attribute
    assert ne.attribute_to_topic(robot, attribute) == topic
    assert ne.topic_to_attribute(robot, topic.lstrip("/")) == attribute


@pytest.mark.parametrize("robot,topic", [
    ("robot1", "/robot2/pose"), ("robot1", "/robot10/pose"), ("robot1", "/robot1"), ("robot1", "/robot1/"),
    ("robot1", "/robot1/a//b"), ("robot1", "/robot1/a.b"), ("robot1", "/robot1/a b"), ("robot1", 5),
    ("rob/ot", "/rob/ot/x"), ("", "//x"), (None, "/x/y"),
])
def test_topic_to_attribute_refuses_topics_outside_the_robot(robot, topic):
    with pytest.raises(ne.NgsiEncodingError):
        ne.topic_to_attribute(robot, topic)


@pytest.mark.parametrize("attribute", ["", "a..b", ".a", "a.", "a/b", "a b", "a<b", "move_base.goal;", None])
def test_attribute_to_topic_refuses_bad_names(attribute):
    with pytest.raises(ne.NgsiEncodingError):
        ne.attribute_to_topic("robot1", attribute)


@pytest.mark.parametrize("message_type,attribute_type", [
    ("std_msgs/String", "std_msgs.msg.String"), ("geometry_msgs/Twist", "geometry_msgs.msg.Twist"),
    ("robotics_msgs/CB_Event", "robotics_msgs.msg.CB_Event"),
])
def test_message_and_attribute_types_map_both_ways(message_type, attribute_type):
    assert ne.message_type_to_attribute_type(message_type) == attribute_type
    assert ne.attribute_type_to_message_type(attribute_type) == message_type
    assert ne.attribute_type_to_message_type(message_type) == message_type


@pytest.mark.parametrize("bad", ["std_msgs", "std_msgs.String", "std_msgs.msg.String.x", "a/b/c", "COMMAND", 5, ""])
def test_bad_types_are_refused(bad):
    with pytest.raises(ne.NgsiEncodingError):
        ne.attribute_type_to_message_type(bad)
    with pytest.raises(ne.NgsiEncodingError):
        ne.message_type_to_attribute_type(bad)


def test_with_firosstamp_puts_the_stamp_first_and_copies():
    message = {"data": "x", "firosstamp": "stale"}
    value = ne.with_firosstamp(message, 12)
    assert list(value) == ["firosstamp", "data"] and value["firosstamp"] == 12.0
    assert isinstance(value["firosstamp"], float)
    assert message == {"data": "x", "firosstamp": "stale"}


@pytest.mark.parametrize("stamp", [float("nan"), float("inf"), "12", True, None])
def test_with_firosstamp_refuses_bad_stamps(stamp):
    with pytest.raises(ne.NgsiEncodingError):
        ne.with_firosstamp({"data": "x"}, stamp)


@pytest.mark.parametrize("value,expected", [
    ({"data": "x"}, ({"data": "x"}, None)),
    ({"firosstamp": 5, "data": "x"}, ({"data": "x"}, 5.0)),
    ({"firosstamp": "1443020619.5", "data": "x"}, ({"data": "x"}, 1443020619.5)),
    ({"firosstamp": "soon", "data": "x"}, ({"data": "x"}, None)),
    ({"firosstamp": True}, ({}, None)),
    ({"firosstamp": "nan"}, ({}, None)),
])
def test_split_firosstamp(value, expected):
    assert ne.split_firosstamp(value) == expected


def test_split_firosstamp_refuses_non_objects():
    with pytest.raises(ne.NgsiEncodingError):
        ne.split_firosstamp(["data"])


# The whole path FIROS takes: ROS message -> dict -> value in the broker (JSON on the wire) -> dict -> ROS message.
PIPELINE = [
    ("std_msgs/String", {"data": "it's \"<quoted>\" (100%) = done; %27"}),
    ("geometry_msgs/Twist", {"linear": {"x": 0.5, "y": "NaN", "z": 0.0}, "angular": {"x": 0.0, "y": 0.0,
                                                                                         "z": "-Infinity"}}),
    ("geometry_msgs/PoseStamped", {"header": {"seq": 3, "stamp": {"secs": 10, "nsecs": 20}, "frame_id": "map"},
                                   "pose": {"position": {"x": 1.0, "y": 2.0, "z": 3.0},
                                            "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}}),
    ("sensor_msgs/Image", {"encoding": "rgb8", "height": 1, "width": 1, "step": 3, "data": "/wAA"}),
]


@pytest.mark.parametrize("version", ["v1", "v2"])
@pytest.mark.parametrize("msg_type,data", PIPELINE, ids=[case[0] for case in PIPELINE])
def test_message_to_broker_value_and_back(version, msg_type, data):
    original = rc.dict_to_message(data, msg_type)
    value = ne.with_firosstamp(rc.message_to_dict(original), 1443020619.58971)
    if version == "v1":
        wire = json.loads(json.dumps({"value": ne.encode_v1(value)}))["value"]
        received = ne.decode_v1(wire)
    else:
        wire = json.loads(json.dumps({"value": ne.encode_v2(value)}, allow_nan=False))["value"]
        received = ne.decode_v2(wire)
    message_dict, stamp = ne.split_firosstamp(received)
    assert stamp == 1443020619.58971
    back = rc.dict_to_message(message_dict, msg_type)
    first, second = io.BytesIO(), io.BytesIO()
    original.serialize(first)
    back.serialize(second)
    assert second.getvalue() == first.getvalue()


def test_seed_update_becomes_a_string_message():
    message_dict, stamp = ne.split_firosstamp(ne.decode_v1(SEED_UPDATE_VALUE))
    assert stamp is None
    assert rc.dict_to_message(message_dict, "std_msgs/String").data == "12345"
