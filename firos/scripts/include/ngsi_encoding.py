"""How FIROS writes values and names into NGSI attributes (CONTRACTS section 3), and reads them back.

Owns the value encodings of NGSI v1 and v2, the attribute names made from topic names, the attribute types made
from message types, the NGSI-LD entity ids made from robot names, and the ``firosstamp`` member added to every
value: the one place for FIROS's naming rules (every other module calls these). Pure functions, no I/O.

Public API
----------
``encode_v1(value: dict) -> str`` / ``decode_v1(text) -> dict``
    NGSI v1: the value is JSON text with every ``"`` written ``%27``, as the seed guide's end-to-end output shows:
    ``{%27firosstamp%27: 1443020619.58971, %27data%27: %27test%27}``. Orion refuses the characters
    ``< > " ' = ; ( )`` in values, so before the quotes are replaced, those characters and ``%`` itself (all of
    which can only occur inside JSON strings) are written as JSON escapes (``\\u003c``, ``\\u0025``, ...). The
    encoded text then holds no ``%`` other than the ``%27`` quotes, so decoding (``%27`` -> ``"``, then JSON) is
    exact. ``decode_v1`` also reads what the original FIROS and people with curl write: Python-literal text with
    single quotes, written ``%27`` (``{%27data%27: %27123%27}``, the seed's updateContext value) or raw
    (``{'data': 'test'}``), with ``True``/``False``/``None`` and ``u''`` strings. A dict (a v1 compound value)
    is returned as a copy.
``encode_v2(obj) -> obj`` / ``decode_v2(obj) -> obj``
    NGSI v2: the value is the JSON object itself. In every string, keys included, ``%`` and Orion's forbidden
    characters are percent-encoded with upper-case hex: ``%`` -> ``%25``, ``<`` -> ``%3C``, ``>`` -> ``%3E``,
    ``"`` -> ``%22``, ``'`` -> ``%27``, ``=`` -> ``%3D``, ``;`` -> ``%3B``, ``(`` -> ``%28``, ``)`` -> ``%29``.
    Because ``%`` is always encoded, every ``%`` in an encoded string starts one of these nine escapes, and
    ``decode_v2`` (which decodes exactly these nine, hex in either case, and leaves any other ``%`` text alone,
    e.g. ``50%`` typed into the broker by hand) gives back the original exactly. Numbers, booleans and null pass
    through; NaN and infinities are refused (JSON has none; ros_conversion writes them as strings).
``topic_to_attribute(robot, topic) -> str`` / ``attribute_to_topic(robot, attribute) -> str``
    ``("robot1", "/robot1/move_base/goal")`` <-> ``"move_base.goal"``: the topic relative to the robot's
    namespace with ``/`` written ``.``. ROS names never contain ``.``, so the mapping is one to one.
``relative_topic_to_attribute("move_base/goal") -> "move_base.goal"`` / ``attribute_to_relative_topic``
    The same for a topic already relative to its robot (or outside any namespace, as an RCM robot's ``/odom``).
``ld_entity_id("ROBOT", "robot1") -> "urn:ngsi-ld:ROBOT:robot1"`` / ``robot_from_ld_entity_id(id, "ROBOT")``
    NGSI-LD entity ids are URIs; FIROS's robots are ``urn:ngsi-ld:<type>:<robot>``.
``message_type_to_attribute_type("std_msgs/String") -> "std_msgs.msg.String"`` and the reverse
    ``attribute_type_to_message_type`` (which also accepts ``pkg/Type`` as it is).
``FIROSSTAMP``, ``with_firosstamp(message_dict, stamp) -> dict``, ``split_firosstamp(value) -> (dict, float|None)``
    Every value FIROS sends is the message's dict plus ``firosstamp`` (seconds since the epoch, a float), first,
    as in the seed's output. ``split_firosstamp`` removes it from a received value (a message field that is itself
    called ``firosstamp`` cannot be carried) and returns the stamp, or None when absent or not a number.
``json_safe(value) -> value``
    ``value`` (JSON-like) with every float JSON cannot carry written as FIROS writes it into the broker:
    ``"NaN"``, ``"Infinity"``, ``"-Infinity"``; for what FIROS answers (values read back from a broker may hold
    them: Python's JSON parser accepts bare ``NaN``).
``NgsiEncodingError`` (a ``ValueError``)
    Raised for every malformed input, with a sentence saying what was wrong.
"""

import ast
import json
import math
import re

__all__ = [
    "NgsiEncodingError", "FORBIDDEN_CHARACTERS", "FIROSSTAMP",
    "encode_v1", "decode_v1", "encode_v2", "decode_v2",
    "topic_to_attribute", "attribute_to_topic", "relative_topic_to_attribute", "attribute_to_relative_topic",
    "LD_ID_PREFIX", "ld_entity_id", "robot_from_ld_entity_id",
    "message_type_to_attribute_type", "attribute_type_to_message_type",
    "with_firosstamp", "split_firosstamp", "json_safe",
]


class NgsiEncodingError(ValueError):
    """A value, name or type that cannot be encoded or decoded; the message says why."""


# Floats JSON cannot carry, as FIROS writes them (ros_conversion writes message fields the same way).
NON_FINITE = {"nan": "NaN", "inf": "Infinity", "-inf": "-Infinity"}

# Characters Orion refuses in attribute values (and in v2 names) unless they are encoded.
FORBIDDEN_CHARACTERS = "<>\"'=;()"

FIROSSTAMP = "firosstamp"
MAX_NAME_LENGTH = 256

# NGSI-LD entity ids are URIs; FIROS names robots urn:ngsi-ld:<type>:<robot> (ETSI GS CIM 009, annex A.3).
LD_ID_PREFIX = "urn:ngsi-ld:"

# The v1 quote: the seed writes every JSON '"' as the URL escape of "'".
_V1_QUOTE = "%27"
# v1: characters written as JSON \u escapes before the quotes become %27 (only strings can contain them).
_V1_JSON_ESCAPES = tuple((ch, "\\u%04x" % ord(ch)) for ch in "%<>'=;()")

# v2: percent escapes for '%' (first, so that no escape is escaped again) and every forbidden character, and the
# reverse table.
_V2_ESCAPES = tuple((ch, "%%%02X" % ord(ch)) for ch in "%" + FORBIDDEN_CHARACTERS)
_V2_UNESCAPES = {"%02X" % ord(ch): ch for ch in "%" + FORBIDDEN_CHARACTERS}
_V2_ESCAPE_RE = re.compile("%(" + "|".join(sorted(_V2_UNESCAPES)) + ")", re.IGNORECASE)

# One segment of a ROS name (between slashes) or of an attribute name (between dots).
_NAME_SEGMENT_RE = re.compile(r"^[A-Za-z0-9_]+$")
_MESSAGE_TYPE_RE = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)/([A-Za-z][A-Za-z0-9_]*)$")
_ATTRIBUTE_TYPE_RE = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)\.msg\.([A-Za-z][A-Za-z0-9_]*)$")


# ---------------------------------------------------------------------------------------------------------------
# NGSI v1
# ---------------------------------------------------------------------------------------------------------------

def encode_v1(value):
    """The v1 attribute value text for a JSON-safe dict (see the module docstring)."""
    if not isinstance(value, dict):
        raise NgsiEncodingError("a v1 value must be a JSON object, got %s" % type(value).__name__)
    try:
        text = json.dumps(value, ensure_ascii=False, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise NgsiEncodingError("value is not JSON-safe: %s" % exc) from None
    return _replace_all(text, _V1_JSON_ESCAPES).replace('"', _V1_QUOTE)


def decode_v1(text):
    """The dict a v1 attribute value carries: FIROS's JSON form or the Python-literal form, quotes as %27 or raw."""
    if isinstance(text, dict):
        return _json_copy(text, "value")
    if not isinstance(text, str):
        raise NgsiEncodingError("a v1 value must be text, got %s" % type(text).__name__)
    try:
        value = json.loads(text.replace(_V1_QUOTE, '"'), parse_constant=_refuse_constant)
    except (ValueError, RecursionError):
        value = _python_literal(text.replace(_V1_QUOTE, "'"), text)
    if not isinstance(value, dict):
        raise NgsiEncodingError("a v1 value must hold a JSON object, got %s" % _json_kind(value))
    return value


def _refuse_constant(name):
    raise ValueError("%s is not JSON" % name)


def _python_literal(text, original):
    try:
        value = ast.literal_eval(text)
    except (ValueError, TypeError, SyntaxError, MemoryError, RecursionError):
        raise NgsiEncodingError("value is neither JSON nor a Python literal (quotes written %%27): %r%s"
                                % (original[:80], "..." if len(original) > 80 else "")) from None
    return _json_copy(value, "value")


def _json_copy(value, where):
    """A copy of a decoded literal made of JSON types only (tuples become lists); refuses anything else."""
    if isinstance(value, dict):
        out = {}
        for key, item in value.items():
            if not isinstance(key, str):
                raise NgsiEncodingError("%s: object keys must be strings, got %s" % (where, type(key).__name__))
            out[key] = _json_copy(item, "%s.%s" % (where, key))
        return out
    if isinstance(value, (list, tuple)):
        return [_json_copy(item, "%s[%d]" % (where, index)) for index, item in enumerate(value)]
    if value is None or isinstance(value, (str, bool, int, float)):
        return value
    raise NgsiEncodingError("%s: %s is not a JSON value" % (where, type(value).__name__))


def _json_kind(value):
    return {dict: "an object", list: "an array", str: "a string", bool: "a boolean",
            int: "a number", float: "a number"}.get(type(value), "null")


# ---------------------------------------------------------------------------------------------------------------
# NGSI v2
# ---------------------------------------------------------------------------------------------------------------

def encode_v2(obj):
    """A copy of a JSON-safe value with '%' and Orion's forbidden characters percent-encoded in every string."""
    return _walk(obj, _encode_v2_string, "value", refuse_nonfinite=True)


def decode_v2(obj):
    """The inverse of encode_v2: a copy with the nine escapes decoded in every string (other '%' text kept)."""
    return _walk(obj, _decode_v2_string, "value", refuse_nonfinite=False)


def _replace_all(text, pairs):
    """Each (character, escape) of ``pairs`` replaced in order; str.replace is much faster than translate on the
    long base64 texts of images, and the ``in`` test makes the common case (nothing to escape) cheap."""
    for character, escape in pairs:
        if character in text:
            text = text.replace(character, escape)
    return text


def _encode_v2_string(text):
    return _replace_all(text, _V2_ESCAPES)


def _decode_v2_string(text):
    if "%" not in text:
        return text
    return _V2_ESCAPE_RE.sub(lambda match: _V2_UNESCAPES[match.group(1).upper()], text)


def _walk(obj, convert, where, refuse_nonfinite):
    if isinstance(obj, str):
        return convert(obj)
    if isinstance(obj, dict):
        out = {}
        for key, item in obj.items():
            if not isinstance(key, str):
                raise NgsiEncodingError("%s: object keys must be strings, got %s" % (where, type(key).__name__))
            out[convert(key)] = _walk(item, convert, "%s.%s" % (where, key), refuse_nonfinite)
        return out
    if isinstance(obj, (list, tuple)):
        return [_walk(item, convert, "%s[%d]" % (where, index), refuse_nonfinite) for index, item in enumerate(obj)]
    if obj is None or isinstance(obj, (bool, int)):
        return obj
    if isinstance(obj, float):
        if refuse_nonfinite and not math.isfinite(obj):
            raise NgsiEncodingError("%s: %r is not a JSON number" % (where, obj))
        return obj
    raise NgsiEncodingError("%s: %s is not a JSON value" % (where, type(obj).__name__))


# ---------------------------------------------------------------------------------------------------------------
# Names and types
# ---------------------------------------------------------------------------------------------------------------

def _check_robot(robot):
    if not isinstance(robot, str) or len(robot) > MAX_NAME_LENGTH or not _NAME_SEGMENT_RE.match(robot):
        shown = robot[:60] + "..." if isinstance(robot, str) and len(robot) > 60 else robot
        raise NgsiEncodingError("robot name %r is not a ROS name segment (letters, digits, underscores; at most "
                                "%d characters)" % (shown, MAX_NAME_LENGTH))


def check_robot_name(robot):
    """``robot`` when it can be a robot's name (one ROS name segment, at most MAX_NAME_LENGTH characters);
    NgsiEncodingError otherwise. Names from requests go through this before they are used or logged."""
    _check_robot(robot)
    return robot


def relative_topic_to_attribute(relative):
    """``"move_base/goal"`` (a topic relative to the robot's namespace) -> ``"move_base.goal"``."""
    if not isinstance(relative, str):
        raise NgsiEncodingError("topic must be a str, got %s" % type(relative).__name__)
    segments = relative.strip("/").split("/")
    if not all(_NAME_SEGMENT_RE.match(segment) for segment in segments):
        raise NgsiEncodingError("topic %r is not a valid ROS topic name" % relative)
    return ".".join(segments)


def attribute_to_relative_topic(attribute):
    """``"move_base.goal"`` -> ``"move_base/goal"``; NgsiEncodingError when the name cannot be a topic."""
    if not isinstance(attribute, str):
        raise NgsiEncodingError("attribute name must be a str, got %s" % type(attribute).__name__)
    segments = attribute.split(".")
    if not all(_NAME_SEGMENT_RE.match(segment) for segment in segments):
        raise NgsiEncodingError("attribute name %r does not name a topic (dot-separated ROS name segments)"
                                % attribute)
    return "/".join(segments)


def topic_to_attribute(robot, topic):
    """``("robot1", "/robot1/move_base/goal")`` -> ``"move_base.goal"``; the topic must be in the robot's namespace."""
    _check_robot(robot)
    if not isinstance(topic, str):
        raise NgsiEncodingError("topic must be a str, got %s" % type(topic).__name__)
    prefix = "/%s/" % robot
    full = topic if topic.startswith("/") else "/" + topic
    if not full.startswith(prefix):
        raise NgsiEncodingError("topic %r is not in the namespace of robot %r" % (topic, robot))
    return relative_topic_to_attribute(full[len(prefix):])


def attribute_to_topic(robot, attribute):
    """``("robot1", "move_base.goal")`` -> ``"/robot1/move_base/goal"``."""
    _check_robot(robot)
    return "/%s/%s" % (robot, attribute_to_relative_topic(attribute))


def ld_entity_id(entity_type, robot):
    """NGSI-LD: the entity id of a robot, a URN: ``("ROBOT", "robot1")`` -> ``"urn:ngsi-ld:ROBOT:robot1"``."""
    _check_robot(robot)
    return "%s%s:%s" % (LD_ID_PREFIX, entity_type, robot)


def robot_from_ld_entity_id(entity_id, entity_type):
    """The robot name in ``urn:ngsi-ld:<entity_type>:<robot>``; NgsiEncodingError for any other id."""
    prefix = "%s%s:" % (LD_ID_PREFIX, entity_type)
    if not isinstance(entity_id, str) or not entity_id.startswith(prefix):
        raise NgsiEncodingError("entity id %r is not of the form %s<robot>" % (entity_id, prefix))
    robot = entity_id[len(prefix):]
    _check_robot(robot)
    return robot


def message_type_to_attribute_type(message_type):
    """``"std_msgs/String"`` -> ``"std_msgs.msg.String"``."""
    match = _MESSAGE_TYPE_RE.match(message_type) if isinstance(message_type, str) else None
    if match is None:
        raise NgsiEncodingError("message type %r is not of the form 'pkg/Type'" % (message_type,))
    return "%s.msg.%s" % match.groups()


def attribute_type_to_message_type(attribute_type):
    """``"std_msgs.msg.String"`` (or ``"std_msgs/String"``) -> ``"std_msgs/String"``."""
    if isinstance(attribute_type, str):
        match = _ATTRIBUTE_TYPE_RE.match(attribute_type) or _MESSAGE_TYPE_RE.match(attribute_type)
        if match is not None:
            return "%s/%s" % match.groups()
    raise NgsiEncodingError("attribute type %r is not a message type ('pkg.msg.Type')" % (attribute_type,))


# ---------------------------------------------------------------------------------------------------------------
# firosstamp
# ---------------------------------------------------------------------------------------------------------------

def with_firosstamp(message_dict, stamp):
    """A new dict: ``firosstamp`` (float seconds) first, then the message's fields."""
    if not isinstance(message_dict, dict):
        raise NgsiEncodingError("message value must be a dict, got %s" % type(message_dict).__name__)
    if isinstance(stamp, bool) or not isinstance(stamp, (int, float)) or not math.isfinite(stamp):
        raise NgsiEncodingError("firosstamp must be a finite number of seconds, got %r" % (stamp,))
    value = {FIROSSTAMP: float(stamp)}
    value.update((key, item) for key, item in message_dict.items() if key != FIROSSTAMP)
    return value


def split_firosstamp(value):
    """``(message_dict, stamp)``: a copy of ``value`` without ``firosstamp``, and the stamp or None."""
    if not isinstance(value, dict):
        raise NgsiEncodingError("attribute value must be a JSON object, got %s" % _json_kind(value))
    message_dict = {key: item for key, item in value.items() if key != FIROSSTAMP}
    stamp = value.get(FIROSSTAMP)
    if isinstance(stamp, str):
        try:
            stamp = float(stamp)
        except ValueError:
            stamp = None
    if isinstance(stamp, bool) or not isinstance(stamp, (int, float)) or not math.isfinite(stamp):
        stamp = None
    return message_dict, (float(stamp) if stamp is not None else None)


# ---------------------------------------------------------------------------------------------------------------
# Strict JSON out
# ---------------------------------------------------------------------------------------------------------------

def json_safe(value):
    """``value`` with its non-finite floats (keys too) as the strings of ``NON_FINITE``; the rest as it is."""
    if isinstance(value, float):
        return value if math.isfinite(value) else NON_FINITE[repr(value)]
    if isinstance(value, dict):
        return {json_safe(key): json_safe(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(item) for item in value]
    return value
