"""Tests of firos/scripts/include/ros_conversion.py: table-driven round trips (fill, serialize, deserialize, extract,
JSON dumps/loads, compare) over real message classes, the asymmetric cases, and errors with their field paths."""

import io
import json
import sys

import genpy
import genpy.dynamic
import pytest

from include import ros_conversion as rc

# A message with the field kinds no installed package has (char[], fixed uint8/char arrays, time[], byte[],
# fixed arrays of messages), generated from its text as rosbag does; its element classes come from a loader.
_ALL_KINDS_TEXT = """char[] chars
uint8[4] quad
char[2] pair_chars
byte[] signed_bytes
time[] times
duration span
duration[2] spans
test_msgs/Inner[2] pair
test_msgs/Inner[] many
test_msgs/Inner one
float32[3] fixed_floats
string[] words
bool[] flags
char c
byte b
int64[] big
uint64 u
================================================================================
MSG: test_msgs/Inner
int32 n
string s
"""
_DYNAMIC = genpy.dynamic.generate_dynamic("test_msgs/AllKinds", _ALL_KINDS_TEXT)
ALL_KINDS = _DYNAMIC["test_msgs/AllKinds"]


def _dynamic_loader(type_name):
    return _DYNAMIC[type_name]


def round_trip(msg_type, data, class_loader=rc.load_message_class):
    """Fill, serialize, deserialize, extract, JSON dumps/loads; also checks the bytes survive a second pass."""
    msg = rc.dict_to_message(data, msg_type, class_loader=class_loader)
    first = io.BytesIO()
    msg.serialize(first)
    back = type(msg)()
    back.deserialize(first.getvalue())
    extracted = json.loads(json.dumps(rc.message_to_dict(back), allow_nan=False))
    again = rc.dict_to_message(extracted, type(msg), class_loader=class_loader)
    second = io.BytesIO()
    again.serialize(second)
    assert second.getvalue() == first.getvalue()
    return extracted


def assert_contains(expected, actual, path="value"):
    """Every key of ``expected`` is in ``actual`` with an equal value (recursively); lists compared item by item."""
    if isinstance(expected, dict):
        assert isinstance(actual, dict), path
        for key, item in expected.items():
            assert key in actual, "%s.%s missing" % (path, key)
            assert_contains(item, actual[key], "%s.%s" % (path, key))
    elif isinstance(expected, list):
        assert isinstance(actual, list) and len(actual) == len(expected), path
        for index, (want, got) in enumerate(zip(expected, actual)):
            assert_contains(want, got, "%s[%d]" % (path, index))
    else:
        assert type(actual) is type(expected) and actual == expected, "%s: %r != %r" % (path, actual, expected)


STAMP = {"secs": 1443020619, "nsecs": 589710000}
HEADER = {"seq": 7, "stamp": STAMP, "frame_id": "map"}
POSE = {"position": {"x": 1.5, "y": -2.25, "z": 0.0}, "orientation": {"x": 0.0, "y": 0.0, "z": 0.5, "w": 1.0}}

ROUND_TRIPS = [
    # std_msgs: every primitive type
    ("std_msgs/Bool", {"data": True}),
    ("std_msgs/Bool", {"data": False}),
    ("std_msgs/Byte", {"data": -128}),
    ("std_msgs/Char", {"data": 255}),
    ("std_msgs/Int8", {"data": -5}),
    ("std_msgs/UInt8", {"data": 200}),
    ("std_msgs/Int16", {"data": -30000}),
    ("std_msgs/UInt16", {"data": 65535}),
    ("std_msgs/Int32", {"data": -2 ** 31}),
    ("std_msgs/UInt32", {"data": 2 ** 32 - 1}),
    ("std_msgs/Int64", {"data": -2 ** 63}),
    ("std_msgs/UInt64", {"data": 2 ** 64 - 1}),
    ("std_msgs/Float32", {"data": -1.25}),
    ("std_msgs/Float32", {"data": 3.4028234663852886e38}),
    ("std_msgs/Float64", {"data": 1e308}),
    ("std_msgs/Float64", {"data": 5e-324}),
    ("std_msgs/Float64", {"data": "NaN"}),
    ("std_msgs/Float64", {"data": "Infinity"}),
    ("std_msgs/Float32", {"data": "-Infinity"}),
    ("std_msgs/String", {"data": "test"}),
    ("std_msgs/String", {"data": ""}),
    ("std_msgs/String", {"data": "h\u00e9llo w\u00f6rld \u2014 \u6f22\u5b57 \U0001f916 \"q\" 'a' <b> \\ %27 \n\t"}),
    ("std_msgs/Time", {"data": STAMP}),
    ("std_msgs/Duration", {"data": {"secs": -3, "nsecs": 500000000}}),
    ("std_msgs/Header", HEADER),
    ("std_msgs/Float64MultiArray", {"layout": {"dim": [{"label": "rows", "size": 2, "stride": 4},
                                                       {"label": "cols", "size": 2, "stride": 2}],
                                               "data_offset": 1},
                                    "data": [0.5, "NaN", -1.0, "Infinity"]}),
    ("std_msgs/ByteMultiArray", {"layout": {"dim": [], "data_offset": 0}, "data": [-128, 0, 127]}),
    ("std_msgs/UInt8MultiArray", {"layout": {"dim": [], "data_offset": 0}, "data": "AAEC/w=="}),
    ("std_msgs/Empty", {}),
    # geometry_msgs: nested messages, header stamps, fixed arrays, arrays of messages
    ("geometry_msgs/Twist", {"linear": {"x": 0.5, "y": 0.0, "z": -1.0}, "angular": {"x": 0.0, "y": 0.0, "z": 2.0}}),
    ("geometry_msgs/PoseStamped", {"header": HEADER, "pose": POSE}),
    ("geometry_msgs/PoseWithCovariance", {"pose": POSE, "covariance": [float(i) / 4 for i in range(36)]}),
    ("geometry_msgs/PoseArray", {"header": HEADER, "poses": [POSE, POSE]}),
    # sensor_msgs: uint8[] as base64, arrays of strings and floats, fixed arrays, nested message in the middle
    ("sensor_msgs/Image", {"header": HEADER, "height": 1, "width": 3, "encoding": "mono8", "is_bigendian": 0,
                           "step": 3, "data": "AH//"}),
    ("sensor_msgs/JointState", {"header": HEADER, "name": ["elbow", "wrist \u00e9"],
                                "position": [0.25, "NaN"], "velocity": ["-Infinity", 1.0], "effort": []}),
    ("sensor_msgs/CameraInfo", {"header": HEADER, "height": 480, "width": 640, "distortion_model": "plumb_bob",
                                "D": [0.125, -0.25, 0.0, 0.0, 0.0], "K": [1.0] * 9, "R": [0.0] * 9,
                                "P": [2.0] * 12, "binning_x": 1, "binning_y": 2,
                                "roi": {"x_offset": 1, "y_offset": 2, "height": 3, "width": 4,
                                        "do_rectify": True}}),
    # robotics_msgs: the project's own package, loaded from the catkin workspace
    ("robotics_msgs/CB_Event", {"entity_name": "robot1", "entity_status": 1}),
    ("robotics_msgs/Robot_Event", {"instance_name": "robot1", "instance_status": 0}),
]


@pytest.mark.parametrize("msg_type,data", ROUND_TRIPS, ids=[case[0] for case in ROUND_TRIPS])
def test_round_trip_is_exact(msg_type, data):
    assert_contains(data, round_trip(msg_type, data))


def test_round_trip_full_dict_of_every_kind():
    data = {
        "chars": "aGk=", "quad": "AQIDBA==", "pair_chars": "AP8=", "signed_bytes": [-1, 0, 1],
        "times": [{"secs": 1, "nsecs": 2}, {"secs": 4294967295, "nsecs": 999999999}],
        "span": {"secs": -2147483648, "nsecs": 0},
        "spans": [{"secs": 1, "nsecs": 0}, {"secs": -1, "nsecs": 999999999}],
        "pair": [{"n": 1, "s": "a"}, {"n": -2, "s": "\u00fc"}], "many": [{"n": 3, "s": "x"}],
        "one": {"n": 2147483647, "s": "one"}, "fixed_floats": [0.5, "NaN", "-Infinity"],
        "words": ["a", "", "\U0001f916"], "flags": [True, False, True], "c": 65, "b": -1,
        "big": [-2 ** 63, 2 ** 63 - 1], "u": 2 ** 64 - 1,
    }
    out = round_trip(ALL_KINDS, data, class_loader=_dynamic_loader)
    assert out == data


def test_extracted_dict_has_every_field_in_slot_order():
    twist = rc.dict_to_message({}, "geometry_msgs/Twist")
    assert list(rc.message_to_dict(twist)) == ["linear", "angular"]
    assert rc.message_to_dict(twist)["linear"] == {"x": 0.0, "y": 0.0, "z": 0.0}


def test_missing_fields_keep_defaults():
    cls = rc.load_message_class("sensor_msgs/CameraInfo")
    msg = rc.dict_to_message({"width": 640, "header": {"frame_id": "cam"}}, cls)
    default = cls()
    assert msg.width == 640 and msg.header.frame_id == "cam"
    assert msg.height == default.height and list(msg.K) == list(default.K) and msg.header.stamp == genpy.Time()
    assert isinstance(msg, cls)


def test_class_and_type_name_give_the_same_message():
    cls = rc.load_message_class("geometry_msgs/Twist")
    data = {"linear": {"x": 1.0}}
    assert rc.dict_to_message(data, cls) == rc.dict_to_message(data, "geometry_msgs/Twist")


def test_header_stamp_is_never_replaced_by_the_clock():
    msg = rc.dict_to_message({"header": {"frame_id": "map"}}, "geometry_msgs/PoseStamped")
    assert msg.header.stamp.secs == 0 and msg.header.stamp.nsecs == 0
    partial = rc.dict_to_message({"header": {"stamp": {"secs": 5}}}, "geometry_msgs/PoseStamped")
    assert (partial.header.stamp.secs, partial.header.stamp.nsecs) == (5, 0)


def test_message_to_dict_reads_hand_made_messages():
    from sensor_msgs.msg import Image
    from std_msgs.msg import Float64, String
    assert rc.message_to_dict(Image(data=[1, 2, 255]))["data"] == "AQL/"
    assert rc.message_to_dict(Float64(data=float("-inf"))) == {"data": "-Infinity"}
    assert rc.message_to_dict(String(data=b"caf\xc3\xa9 \xff")) == {"data": "caf\u00e9 \ufffd"}


# Accepted on the way in, written differently on the way out.
ASYMMETRIC = [
    ("std_msgs/Float64", {"data": None}, {"data": "NaN"}),
    ("std_msgs/Float64", {"data": "nan"}, {"data": "NaN"}),
    ("std_msgs/Float64", {"data": "inf"}, {"data": "Infinity"}),
    ("std_msgs/Float64", {"data": "+Infinity"}, {"data": "Infinity"}),
    ("std_msgs/Float32", {"data": "-INF"}, {"data": "-Infinity"}),
    ("std_msgs/Float64", {"data": 2}, {"data": 2.0}),
    ("std_msgs/Float32", {"data": 0.1}, {"data": 0.10000000149011612}),
    ("std_msgs/Int32", {"data": 3.0}, {"data": 3}),
    ("std_msgs/Time", {"data": {"secs": 5.0}}, {"data": {"secs": 5, "nsecs": 0}}),
    ("sensor_msgs/Image", {"data": [1, 2, 255]}, {"data": "AQL/"}),
    ("sensor_msgs/Image", {"data": []}, {"data": ""}),
    ("sensor_msgs/JointState", {"position": [1, None]}, {"position": [1.0, "NaN"]}),
]


@pytest.mark.parametrize("msg_type,data,expected", ASYMMETRIC, ids=[c[0] for c in ASYMMETRIC])
def test_asymmetric_inputs(msg_type, data, expected):
    assert_contains(expected, round_trip(msg_type, data))


def test_asymmetric_binary_list_into_fixed_arrays():
    out = round_trip(ALL_KINDS, {"quad": [9, 8, 7, 6], "pair_chars": [65, 66]}, class_loader=_dynamic_loader)
    assert out["quad"] == "CQgHBg==" and out["pair_chars"] == "QUI="


ERRORS = [
    ("geometry_msgs/Twist", {"linear": {"x": "fast"}},
     "geometry_msgs/Twist.linear.x: expected float, got str"),
    ("geometry_msgs/Twist", {"linear": {"w": 1, "q": 2}},
     "geometry_msgs/Twist.linear: unknown field(s) 'w', 'q' for geometry_msgs/Vector3 (fields: x, y, z)"),
    ("geometry_msgs/Twist", {"linear": {}, "spin": 1},
     "geometry_msgs/Twist: unknown field(s) 'spin' for geometry_msgs/Twist (fields: linear, angular)"),
    ("geometry_msgs/Twist", [1, 2], "geometry_msgs/Twist: expected object, got list"),
    ("geometry_msgs/Twist", {"linear": 5}, "geometry_msgs/Twist.linear: expected object, got int"),
    ("geometry_msgs/PoseArray", {"poses": [POSE, {"position": {"x": "a"}}]},
     "geometry_msgs/PoseArray.poses[1].position.x: expected float, got str"),
    ("sensor_msgs/JointState", {"position": [1.0, "x"]},
     "sensor_msgs/JointState.position[1]: expected float, got str"),
    ("sensor_msgs/JointState", {"name": "elbow"}, "sensor_msgs/JointState.name: expected list, got str"),
    ("sensor_msgs/JointState", {"name": ["a", 3]}, "sensor_msgs/JointState.name[1]: expected str, got int"),
    ("geometry_msgs/PoseWithCovariance", {"covariance": [0.0] * 35},
     "geometry_msgs/PoseWithCovariance.covariance: expected 36 items, got 35"),
    ("sensor_msgs/CameraInfo", {"K": [0.0] * 10}, "sensor_msgs/CameraInfo.K: expected 9 items, got 10"),
    ("sensor_msgs/Image", {"data": "not base64!"},
     "sensor_msgs/Image.data: expected base64 text, got str that is not base64"),
    ("sensor_msgs/Image", {"data": "\u00e9"},
     "sensor_msgs/Image.data: expected base64 text, got str that is not base64"),
    ("sensor_msgs/Image", {"data": [1, 256]}, "sensor_msgs/Image.data[1]: expected int 0..255, got 256"),
    ("sensor_msgs/Image", {"data": [True]}, "sensor_msgs/Image.data[0]: expected int 0..255, got True"),
    ("sensor_msgs/Image", {"data": 5}, "sensor_msgs/Image.data: expected base64 str or list of int, got int"),
    ("std_msgs/Int32", {"data": True}, "std_msgs/Int32.data: expected int, got bool"),
    ("std_msgs/Int32", {"data": 2.5}, "std_msgs/Int32.data: expected int, got float"),
    ("std_msgs/Int32", {"data": "3"}, "std_msgs/Int32.data: expected int, got str"),
    ("std_msgs/Bool", {"data": 1}, "std_msgs/Bool.data: expected bool, got int"),
    ("std_msgs/Bool", {"data": "true"}, "std_msgs/Bool.data: expected bool, got str"),
    ("std_msgs/Float64", {"data": True}, "std_msgs/Float64.data: expected float, got bool"),
    ("std_msgs/Float64", {"data": [1.0]}, "std_msgs/Float64.data: expected float, got list"),
    ("std_msgs/Float64", {"data": 10 ** 400}, "std_msgs/Float64.data: %d is out of range for float64" % 10 ** 400),
    ("std_msgs/Float32", {"data": 1e39}, "std_msgs/Float32.data: 1e+39 is out of range for float32"),
    ("std_msgs/String", {"data": 5}, "std_msgs/String.data: expected str, got int"),
    ("std_msgs/String", {"data": None}, "std_msgs/String.data: expected str, got None"),
    ("std_msgs/String", {"data": "\ud800"}, "std_msgs/String.data: str is not valid unicode text (lone surrogate)"),
    ("geometry_msgs/PoseStamped", {"header": {"stamp": "now"}},
     "geometry_msgs/PoseStamped.header.stamp: expected object with secs and nsecs for time, got str"),
    ("geometry_msgs/PoseStamped", {"header": {"stamp": {"secs": -1}}},
     "geometry_msgs/PoseStamped.header.stamp.secs: -1 is out of range (0..4294967295)"),
    ("geometry_msgs/PoseStamped", {"header": {"stamp": {"nsecs": 1000000000}}},
     "geometry_msgs/PoseStamped.header.stamp.nsecs: 1000000000 is out of range (0..999999999)"),
    ("geometry_msgs/PoseStamped", {"header": {"stamp": {"secs": "1"}}},
     "geometry_msgs/PoseStamped.header.stamp.secs: expected int, got str"),
    ("geometry_msgs/PoseStamped", {"header": {"stamp": {"sec": 1, "nanosec": 2}}},
     "geometry_msgs/PoseStamped.header.stamp: unknown field(s) 'sec', 'nanosec' for time (fields: secs, nsecs)"),
    ("std_msgs/Duration", {"data": {"secs": 2 ** 31}},
     "std_msgs/Duration.data.secs: 2147483648 is out of range (-2147483648..2147483647)"),
    ("std_msgs/Header", {"seq": -1}, "std_msgs/Header.seq: -1 is out of range for uint32 (0..4294967295)"),
]


@pytest.mark.parametrize("msg_type,data,message", ERRORS, ids=[c[2].split(":")[0] for c in ERRORS])
def test_errors_name_root_type_and_path(msg_type, data, message):
    with pytest.raises(rc.ConversionError) as caught:
        rc.dict_to_message(data, msg_type)
    assert str(caught.value) == message
    assert caught.value.root_type == msg_type
    assert isinstance(caught.value, ValueError)


def test_error_attributes_split_the_message():
    with pytest.raises(rc.ConversionError) as caught:
        rc.dict_to_message({"linear": {"x": "fast"}}, "geometry_msgs/Twist")
    assert (caught.value.path, caught.value.problem) == (".linear.x", "expected float, got str")


DYNAMIC_ERRORS = [
    ({"quad": "AQID"}, "test_msgs/AllKinds.quad: expected 4 bytes, got 3"),
    ({"pair_chars": [1, 2, 3]}, "test_msgs/AllKinds.pair_chars: expected 2 bytes, got 3"),
    ({"pair": [{"n": 1}]}, "test_msgs/AllKinds.pair: expected 2 items, got 1"),
    ({"many": [{"n": 1}, {"n": 2 ** 31}]},
     "test_msgs/AllKinds.many[1].n: 2147483648 is out of range for int32 (-2147483648..2147483647)"),
    ({"signed_bytes": [128]}, "test_msgs/AllKinds.signed_bytes[0]: 128 is out of range for byte (-128..127)"),
    ({"times": [{"secs": 1}, 7]}, "test_msgs/AllKinds.times[1]: expected object with secs and nsecs for time, "
                                  "got int"),
    ({"flags": [True, 0]}, "test_msgs/AllKinds.flags[1]: expected bool, got int"),
    ({"c": 256}, "test_msgs/AllKinds.c: 256 is out of range for char (0..255)"),
    ({"u": -1}, "test_msgs/AllKinds.u: -1 is out of range for uint64 (0..18446744073709551615)"),
    ({"u": 2 ** 64}, "test_msgs/AllKinds.u: 18446744073709551616 is out of range for uint64 "
                     "(0..18446744073709551615)"),
]


@pytest.mark.parametrize("data,message", DYNAMIC_ERRORS, ids=[c[1].split(":")[0] for c in DYNAMIC_ERRORS])
def test_errors_in_every_field_kind(data, message):
    with pytest.raises(rc.ConversionError) as caught:
        rc.dict_to_message(data, ALL_KINDS, class_loader=_dynamic_loader)
    assert str(caught.value) == message


INT_TYPES = [("std_msgs/Int8", "int8", -128, 127), ("std_msgs/UInt8", "uint8", 0, 255),
             ("std_msgs/Byte", "byte", -128, 127), ("std_msgs/Char", "char", 0, 255),
             ("std_msgs/Int16", "int16", -32768, 32767), ("std_msgs/UInt16", "uint16", 0, 65535),
             ("std_msgs/Int32", "int32", -2 ** 31, 2 ** 31 - 1), ("std_msgs/UInt32", "uint32", 0, 2 ** 32 - 1),
             ("std_msgs/Int64", "int64", -2 ** 63, 2 ** 63 - 1), ("std_msgs/UInt64", "uint64", 0, 2 ** 64 - 1)]


@pytest.mark.parametrize("msg_type,base,low,high", INT_TYPES, ids=[c[1] for c in INT_TYPES])
def test_integer_ranges_are_checked(msg_type, base, low, high):
    assert round_trip(msg_type, {"data": low}) == {"data": low}
    assert round_trip(msg_type, {"data": high}) == {"data": high}
    for bad in (low - 1, high + 1):
        with pytest.raises(rc.ConversionError) as caught:
            rc.dict_to_message({"data": bad}, msg_type)
        assert str(caught.value) == "%s.data: %d is out of range for %s (%d..%d)" % (msg_type, bad, base, low, high)


def test_load_message_class_finds_installed_and_workspace_types():
    from geometry_msgs.msg import Twist
    assert rc.load_message_class("geometry_msgs/Twist") is Twist
    assert rc.load_message_class("robotics_msgs/CB_Event")._type == "robotics_msgs/CB_Event"
    assert rc.load_message_class("Header")._type == "std_msgs/Header"
    assert rc.load_message_class("geometry_msgs.msg.Twist") is Twist
    assert rc.load_message_class("robotics_msgs.msg.Robot_Event")._type == "robotics_msgs/Robot_Event"


@pytest.mark.parametrize("name,problem", [
    ("geometry_msgs", "not a message type name (expected 'pkg/Type')"),
    ("geometry_msgs/Twist/x", "not a message type name (expected 'pkg/Type')"),
    ("../etc/passwd", "not a message type name (expected 'pkg/Type')"),
    ("geometry_msgs.Twist", "not a message type name (expected 'pkg/Type')"),
    ("os.path.join", "not a message type name (expected 'pkg/Type')"),
    ("this.msg.Zen", "unknown message type: no ROS package 'this' with messages is installed"),
    ("no_such_pkg_xyz/Thing", "unknown message type: no ROS package 'no_such_pkg_xyz' with messages is installed"),
    ("geometry_msgs/NoSuchType", "unknown message type: package 'geometry_msgs' has no message 'NoSuchType'"),
])
def test_load_message_class_refuses_bad_names(name, problem):
    with pytest.raises(rc.ConversionError) as caught:
        rc.load_message_class(name)
    assert caught.value.problem == problem
    with pytest.raises(rc.ConversionError):
        rc.dict_to_message({}, name)


def test_class_loader_failures_name_the_field():
    def loader(type_name):
        return None if type_name == "geometry_msgs/Pose" else rc.load_message_class(type_name)

    assert list(rc.dict_to_message({"poses": []}, "geometry_msgs/PoseArray", class_loader=loader).poses) == []
    with pytest.raises(rc.ConversionError) as caught:
        rc.dict_to_message({"poses": [POSE]}, "geometry_msgs/PoseArray", class_loader=loader)
    assert str(caught.value) == "geometry_msgs/PoseArray.poses: unknown message type geometry_msgs/Pose"
    with pytest.raises(rc.ConversionError) as caught:
        rc.dict_to_message({"many": [{}]}, ALL_KINDS, class_loader=rc.load_message_class)
    assert str(caught.value) == ("test_msgs/AllKinds.many: unknown message type: no ROS package 'test_msgs' "
                                 "with messages is installed")


def test_load_message_class_never_imports_plain_python_modules():
    assert "this" not in sys.modules
    with pytest.raises(rc.ConversionError):
        rc.load_message_class("this/Zen")
    assert "this" not in sys.modules


def test_dict_to_message_refuses_non_message_classes():
    with pytest.raises(rc.ConversionError) as caught:
        rc.dict_to_message({}, dict)
    assert str(caught.value) == "type: not a ROS message class"


def test_message_to_dict_refuses_non_messages_and_broken_fields():
    with pytest.raises(rc.ConversionError) as caught:
        rc.message_to_dict({"data": 1})
    assert str(caught.value) == "dict: not a ROS message instance"
    from geometry_msgs.msg import Twist
    broken = Twist()
    broken.linear.y = "abc"
    with pytest.raises(rc.ConversionError) as caught:
        rc.message_to_dict(broken)
    assert str(caught.value).startswith("geometry_msgs/Twist.linear.y: cannot convert str value for float64")


def test_a_failed_fill_leaves_nothing_behind():
    """A bad dict raises before any message escapes; the default class is not mutated."""
    from geometry_msgs.msg import Twist
    with pytest.raises(rc.ConversionError):
        rc.dict_to_message({"linear": {"x": 1.0, "y": "bad"}}, Twist)
    assert Twist().linear.x == 0.0


def test_the_size_walk_stops_within_its_budget_and_stays_a_lower_bound():
    from visualization_msgs.msg import Marker, MarkerArray
    markers = MarkerArray(markers=[Marker(ns="n%d" % i, text="é" * 3) for i in range(3000)])
    buffer = io.BytesIO()
    markers.serialize(buffer)
    walk = rc._Walk(buffer.getvalue())
    with pytest.raises(rc._WalkEnd):
        walk.message(MarkerArray)                  # 3000 markers of 14 fields: more than the walk visits
    real = len(json.dumps(rc.message_to_dict(markers), separators=(",", ":"), ensure_ascii=False).encode())
    assert 0 < walk.bound <= rc.json_size_lower_bound(MarkerArray, buffer.getvalue()) <= real
