"""Every message type of Debian's common message packages, random but valid, through the whole path FIROS gives
it in NGSI v1, v2 and NGSI-LD: ROS serialization (as rospy delivers it) → message_to_dict → firosstamp → the
version's attribute text → the update body (strict JSON) → what the broker stores, notified back as JSON → the
version's notification parsing → dict_to_message → ROS serialization, byte for byte the same. Also the size
FIROS reckons without converting (`json_size_lower_bound`) is never above the real JSON size.

Property-based (hypothesis, derandomized: the same examples on every run). Message classes are found by walking
the packages; fixed arrays, empty arrays, extreme integers, binary arrays, unicode strings with Orion's forbidden
characters, NaN and infinities, times and durations all come up. A type of our own (generated with
genpy.dynamic) adds the field kinds none of those packages has (uint8[16], char[4], bool[3], time[2], ...).
"""

import importlib
import io
import json
import math
import os
import tempfile

import genpy
import genpy.dynamic
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.configuration import set_hypothesis_home_dir

from include.config import Settings
from include.ngsi_encoding import message_type_to_attribute_type, split_firosstamp, with_firosstamp
from include.ngsi_versions import CLIENTS
from include.ros_conversion import dict_to_message, json_size_lower_bound, load_message_class, message_to_dict

# hypothesis keeps a cache (unicode tables) in a folder of the current one by default: not in the work tree
set_hypothesis_home_dir(os.path.join(tempfile.gettempdir(), "firos-tests-hypothesis"))

PACKAGES = ("std_msgs", "geometry_msgs", "sensor_msgs", "nav_msgs", "trajectory_msgs", "diagnostic_msgs",
            "actionlib_msgs", "visualization_msgs")
EXAMPLES = 10            # per type; each example goes through all three versions
ROBOT, ATTR, STAMP = "bot", "topic.sub", 1443020619.58971

ALL_KINDS = genpy.dynamic.generate_dynamic("firos_test/AllKinds", """
bool flag
bool[3] flags
bool[] more_flags
uint8[16] uuid
char[4] tag
uint8[] blob
int8[] signed_bytes
byte[] old_bytes
char letter
byte old_byte
int64 big
uint64 bigger
int64[2] bigs
float32 f
float32[] fs
float64[3] ds
time t
time[2] ts
duration d
duration[] ds_
string text
string[2] texts
string[] more_texts
geometry_msgs/Point[2] points
std_msgs/Header header
================================================================================
MSG: geometry_msgs/Point
float64 x
float64 y
float64 z
================================================================================
MSG: std_msgs/Header
uint32 seq
time stamp
string frame_id
""")["firos_test/AllKinds"]


def message_classes():
    """Every message class of PACKAGES' Python modules, sorted by type name."""
    found = {}
    for package in PACKAGES:
        module = importlib.import_module(package + ".msg")
        for name in dir(module):
            cls = getattr(module, name)
            if isinstance(cls, type) and issubclass(cls, genpy.Message) and cls._type.startswith(package + "/"):
                found[cls._type] = cls
    return [found[name] for name in sorted(found)]


CLASSES = message_classes()

# --- strategies: a valid random value for every field type --------------------------------------------------

INT_RANGES = {"int8": 7, "byte": 7, "int16": 15, "int32": 31, "int64": 63}
UINT_BITS = {"uint8": 8, "char": 8, "uint16": 16, "uint32": 32, "uint64": 64}
NONFINITE = st.sampled_from([float("nan"), float("inf"), float("-inf")])
# Orion's forbidden characters, % and JSON's own specials, often
AWKWARD_TEXT = st.text(alphabet="<>\"'=;()%\\{}[]:,/ \u00e9\u20ac\U0001f600\x00\ta", max_size=8)


def _scalar(base):
    if base == "bool":
        return st.booleans()
    if base in INT_RANGES:
        bits = INT_RANGES[base]
        return st.integers(-2 ** bits, 2 ** bits - 1)
    if base in UINT_BITS:
        return st.integers(0, 2 ** UINT_BITS[base] - 1)
    if base == "float32":
        return st.floats(width=32, allow_nan=False) | NONFINITE
    if base == "float64":
        return st.floats(allow_nan=False) | NONFINITE
    if base == "string":
        return st.text(max_size=8) | AWKWARD_TEXT
    if base == "time":
        return st.builds(genpy.Time, st.integers(0, 2 ** 32 - 1), st.integers(0, 999999999))
    if base == "duration":
        return st.builds(genpy.Duration, st.integers(-2 ** 31, 2 ** 31 - 1), st.integers(0, 999999999))
    return None


def _field(field_type, depth):
    base, _, length = field_type.partition("[")
    base = "std_msgs/Header" if base == "Header" else base
    element = _scalar(base)
    if element is None:
        element = message_strategy(load_message_class(base), depth + 1)
    if not length:
        return element
    fixed = int(length[:-1]) if length[:-1] else None
    if base in ("uint8", "char"):                      # binary: genpy holds bytes
        return st.binary(min_size=fixed or 0, max_size=fixed if fixed is not None else 24)
    if fixed is not None:
        return st.lists(element, min_size=fixed, max_size=fixed)
    return st.lists(element, max_size=3 if _scalar(base) is not None else 2)


_STRATEGIES = {}


def message_strategy(cls, depth=0):
    """Random valid messages of ``cls`` (nested messages deeper than 6 levels keep their defaults)."""
    if depth > 6:
        return st.builds(cls)
    if cls not in _STRATEGIES:
        fields = {name: _field(field_type, depth) for name, field_type in zip(cls.__slots__, cls._slot_types)}
        _STRATEGIES[cls] = st.fixed_dictionaries(fields).map(lambda values: cls(**values))
    return _STRATEGIES[cls]


# --- the path through FIROS and a broker ------------------------------------------------------------------

def serialize(msg):
    buffer = io.BytesIO()
    msg.serialize(buffer)
    return buffer.getvalue()


def _refuse_constant(name):
    raise AssertionError(f"{name} in what FIROS sends: not strict JSON")


def stored_and_notified(client, body):
    """What the broker stores of the update ``body`` (bytes), as the version's notification of it (JSON)."""
    update = json.loads(body, parse_constant=_refuse_constant)
    if client.version == "v2":
        note = {"subscriptionId": "s", "data": update["entities"]}
    elif client.version == "v1":
        note = {"subscriptionId": "s", "originator": "localhost", "contextResponses": [
            {"contextElement": element, "statusCode": {"code": "200", "reasonPhrase": "OK"}}
            for element in update["contextElements"]]}
    else:
        note = {"id": "urn:ngsi-ld:Notification:1", "type": "Notification", "subscriptionId": "urn:s",
                "notifiedAt": "2026-01-01T00:00:00.000Z", "data": update}
    return json.loads(json.dumps(note, allow_nan=False))


CLIENTS_BY_VERSION = {version: cls(Settings(config_dir="/nowhere", environment="test", broker_address="127.0.0.1",
                                            ngsi_version=version))
                      for version, cls in CLIENTS.items()}


def check_round_trip(msg, cls):
    wire = serialize(msg)
    received = cls().deserialize(wire)                 # as rospy hands it over
    data = message_to_dict(received)
    compact = json.dumps(data, separators=(",", ":"), ensure_ascii=False, allow_nan=False).encode("utf-8")
    assert json_size_lower_bound(cls, wire) <= len(compact), "the size bound is above the real JSON size"
    atype = message_type_to_attribute_type(cls._type)
    for version, client in CLIENTS_BY_VERSION.items():
        text = client.encode_attribute(ATTR, atype, with_firosstamp(data, STAMP))
        note = stored_and_notified(client, client.update_body({ROBOT: [text]}))
        ((eid, _, attrs),) = client.parse_notification(note)
        assert client.robot_of(eid) == ROBOT
        back_type, value = attrs[ATTR]
        assert back_type == atype, version
        back, stamp = split_firosstamp(value)
        assert stamp == STAMP, version
        again = serialize(dict_to_message(back, cls))
        assert again == wire, f"{cls._type} through NGSI {version} is not the message it was"


SETTINGS = settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
                    suppress_health_check=list(HealthCheck))


def test_the_walk_finds_every_package_and_the_types_users_send():
    names = {cls._type for cls in CLASSES}
    assert {name.split("/")[0] for name in names} == set(PACKAGES)
    assert len(names) >= 100
    assert {"sensor_msgs/Image", "sensor_msgs/LaserScan", "sensor_msgs/PointCloud2", "nav_msgs/OccupancyGrid",
            "nav_msgs/Odometry", "trajectory_msgs/JointTrajectory", "diagnostic_msgs/DiagnosticArray",
            "actionlib_msgs/GoalStatusArray", "visualization_msgs/MarkerArray"} <= names


@pytest.mark.parametrize("cls", CLASSES + [ALL_KINDS], ids=lambda cls: cls._type)
def test_every_type_converts_both_ways_through_v1_v2_and_ld(cls):
    @SETTINGS
    @given(message_strategy(cls))
    def round_trip(msg):
        check_round_trip(msg, cls)

    round_trip()


@pytest.mark.parametrize("value", [float("nan"), float("inf"), float("-inf"), -0.0, 5e-324, 1.7976931348623157e308,
                                   3.4028234663852886e38])
def test_non_finite_and_extreme_floats_travel_as_the_conversion_table_says(value):
    from geometry_msgs.msg import Point
    from sensor_msgs.msg import LaserScan
    cases = [(Point(x=value, y=1.0), Point, lambda data: data["x"])]
    if not math.isfinite(value) or value == 3.4028234663852886e38:      # float32 holds these exactly
        cases.append((LaserScan(ranges=[value, 1.0], range_max=value), LaserScan,
                      lambda data: (data["range_max"], data["ranges"][0])))
    expected = {"nan": "NaN", "inf": "Infinity", "-inf": "-Infinity"}.get(repr(value), value)
    for msg, cls, pick in cases:
        check_round_trip(msg, cls)
        got = pick(message_to_dict(msg))
        for item in (got if isinstance(got, tuple) else (got,)):
            assert item == expected
            if isinstance(item, float):
                assert math.copysign(1, item) == math.copysign(1, value)
