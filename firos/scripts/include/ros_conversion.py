"""ROS messages as JSON-safe dicts and back: the one place FIROS converts message values.

Owns the mapping between ROS 1 (genpy) message instances and plain Python values that ``json.dumps`` accepts,
for any message type, and the loading of message classes by their ``pkg/Type`` name. Pure: no running node, no
ROS parameters, no module state besides read-only tables and a cache of the classes already loaded.

Public API
----------
``message_to_dict(msg) -> dict``
    Every field of ``msg`` (in slot order) as JSON-safe values.
``dict_to_message(data, msg_class_or_type, class_loader=load_message_class) -> msg``
    A new instance of the class (or of the ``"pkg/Type"`` name) filled from ``data``. Fields absent from ``data``
    keep the defaults a new message has; fields ``data`` names that the type lacks are an error.
    ``class_loader(type_name) -> class`` resolves the element types of message arrays; pass one in for message
    classes that cannot be imported by name (e.g. generated with ``genpy.dynamic``).
``load_message_class("pkg/Type") -> class``
    The class of any message type whose Python package is importable (Debian's ROS packages, the sourced catkin
    workspace); the Python form ``"pkg.msg.Type"`` that NGSI attribute types carry is accepted too. Only ROS
    package names that have a ``msg`` sub-package are imported, so a name from outside never imports an arbitrary
    Python module.
``SerializedMessage(msg_class, data)``
    A message as it came off the wire (rospy's ``AnyMsg`` buffer): ``size`` in bytes, ``message()`` deserializes
    it only when it is wanted.
``json_size_lower_bound(msg_class, data) -> int``
    A number of bytes the compact JSON of ``message_to_dict`` of the message serialized in ``data`` is certain to
    reach (UTF-8, no spaces), reckoned from the type's layout and the lengths the serialization holds, without
    deserializing: a message far too big for a broker is refused without being converted. See "Size without
    converting" below.
``ConversionError`` (a ``ValueError``)
    Raised for every problem; ``str()`` names the root type and the dotted path of the field, e.g.
    ``geometry_msgs/Twist.linear.x: expected float, got str``. Attributes ``root_type``, ``path``, ``problem``.

Field encodings (message -> dict, and what dict -> message accepts)
-------------------------------------------------------------------
=======================  ===============================  ==================================================
field type               message_to_dict gives             dict_to_message accepts
=======================  ===============================  ==================================================
bool                     true / false                      true / false only (no 0/1)
int8 .. uint64, byte,    int                               int in the type's range; a float with an integral
char (scalar)                                              value (``3.0``) is taken as that int; bool refused
float32, float64         float; NaN -> ``"NaN"``,          int or float (float32: finite values must fit);
                         +inf -> ``"Infinity"``,           the three strings (also ``"nan"``, ``"inf"``,
                         -inf -> ``"-Infinity"``           ``"+inf"``, ``"-inf"``, any case); ``null`` -> NaN
                                                           (JavaScript's JSON.stringify writes NaN as null)
string                   str (unicode)                     str that is valid UTF-8 text (no lone surrogates)
time, duration           ``{"secs": int, "nsecs": int}``   the same object; absent keys keep 0; nsecs in
                                                           0..999999999; secs uint32 (time) / int32 (duration)
uint8[], char[],         base64 text (standard alphabet)   base64 text, or a list of ints 0..255; fixed
uint8[N], char[N]                                          arrays need exactly N bytes
other T[] / T[N]         list                              list (fixed arrays: exactly N items)
nested message           object                            object (missing fields keep defaults)
=======================  ===============================  ==================================================

JSON has no NaN or infinities, hence the strings: the round trip message -> dict -> JSON -> dict -> message is
exact for every value, NaN included. ``null`` for a float, an integral float for an int and a list of ints for
binary data are accepted on the way in only (the asymmetric cases); ``header.stamp`` is a plain ``time`` and is
never filled in with the current time. A ``string`` field that holds ``bytes`` (possible in hand-made messages)
is decoded as UTF-8 with undecodable bytes replaced.

Size without converting
-----------------------
``json_size_lower_bound`` reads only what the serialization says about sizes: it walks the fields in order,
taking scalars by their size, and reading the length of each string and array (a ``uint8[]`` of n bytes gives
4*ceil(n/3) bytes of base64, an ``int8[]`` of n numbers at least 2n-1 bytes, a string of n bytes at least n+2,
every field its key); an array of messages of variable size is walked element by element. Where the walk cannot
go on it counts nothing more, and a second reckoning needs no walk at all: the serialized bytes split into a part
whose size the type fixes (scalars outside arrays, fixed arrays of fixed-size primitives, the 4-byte length of each
string and variable array outside arrays), which may give as little as nothing in JSON, and the rest, of which
every byte gives at least a known number of JSON bytes (a string's or an ``int8[]``'s content byte one, a
``uint8[]`` byte 4/3, a ``float64`` element 3/8, an ``int64`` element 1/8, ...). The bound is the larger of the
two. JSON keys, ``firosstamp`` and every NGSI encoding only add to it.
"""

import base64
import binascii
import functools
import importlib.util
import math
import os
import re
import struct

import genpy
import genpy.message

from include.ngsi_encoding import NON_FINITE, NgsiEncodingError, attribute_type_to_message_type

__all__ = ["ConversionError", "message_to_dict", "dict_to_message", "load_message_class", "SerializedMessage",
           "json_size_lower_bound"]


class ConversionError(ValueError):
    """A value that cannot be converted; the message names the root type and the dotted field path."""

    def __init__(self, root_type, path, problem):
        self.root_type = root_type
        self.path = path
        self.problem = problem
        super().__init__("%s%s: %s" % (root_type, path, problem))


# ---------------------------------------------------------------------------------------------------------------
# Type knowledge
# ---------------------------------------------------------------------------------------------------------------

# Inclusive ranges of the integer types (``byte`` is ROS's old name for int8, ``char`` for uint8).
_INT_RANGES = {
    "int8": (-2 ** 7, 2 ** 7 - 1),
    "byte": (-2 ** 7, 2 ** 7 - 1),
    "uint8": (0, 2 ** 8 - 1),
    "char": (0, 2 ** 8 - 1),
    "int16": (-2 ** 15, 2 ** 15 - 1),
    "uint16": (0, 2 ** 16 - 1),
    "int32": (-2 ** 31, 2 ** 31 - 1),
    "uint32": (0, 2 ** 32 - 1),
    "int64": (-2 ** 63, 2 ** 63 - 1),
    "uint64": (0, 2 ** 64 - 1),
}

# Largest finite magnitude each float type can hold (None: any Python float).
_FLOAT_LIMITS = {"float32": 3.4028234663852886e38, "float64": None}

# Element types whose arrays genpy holds as ``bytes`` and we write as base64 text.
_BINARY_ELEMENT_TYPES = frozenset(["uint8", "char"])

# time/duration: the genpy class and the range of ``secs``; nsecs is always 0..999999999 (genpy's canonical form).
_TIME_TYPES = {
    "time": (genpy.Time, _INT_RANGES["uint32"]),
    "duration": (genpy.Duration, _INT_RANGES["int32"]),
}
_NSECS_RANGE = (0, 999999999)

# Old message files name the header without its package.
_TYPE_ALIASES = {"Header": "std_msgs/Header", "roslib/Header": "std_msgs/Header"}

# Non-finite floats and their JSON-safe spellings, both ways (input matched case-insensitively).
_NONFINITE_TO_JSON = NON_FINITE
_NONFINITE_FROM_JSON = {
    "nan": float("nan"),
    "infinity": float("inf"), "+infinity": float("inf"), "inf": float("inf"), "+inf": float("inf"),
    "-infinity": float("-inf"), "-inf": float("-inf"),
}

# A field type: base type, then optionally "[]" (variable array) or "[N]" (fixed array).
_FIELD_TYPE_RE = re.compile(r"^([^\[\]]+)(?:\[(\d*)\])?$")


def _kind_of(base_type):
    """The kind of a (non-array) base type: the key into the converter tables below."""
    if base_type == "bool":
        return "bool"
    if base_type in _INT_RANGES:
        return "int"
    if base_type in _FLOAT_LIMITS:
        return "float"
    if base_type == "string":
        return "string"
    if base_type in _TIME_TYPES:
        return "time"
    return "message"


@functools.lru_cache(maxsize=None)
def _parse_field_type(field_type):
    """``"float64[3]"`` -> ``("float64", "float", True, 3)``: base type, kind, is array, fixed length or None."""
    match = _FIELD_TYPE_RE.match(field_type)
    if match is None:
        raise ValueError("unparseable field type %r" % field_type)
    base, length = match.group(1), match.group(2)
    base = _TYPE_ALIASES.get(base, base)
    is_array = length is not None
    fixed = int(length) if length else None
    return base, _kind_of(base), is_array, fixed


def _type_name(value):
    return "None" if value is None else type(value).__name__


def _is_message(obj):
    return hasattr(obj, "__slots__") and hasattr(obj, "_slot_types") and hasattr(obj, "_type")


# ---------------------------------------------------------------------------------------------------------------
# Loading classes
# ---------------------------------------------------------------------------------------------------------------

def _has_msg_subpackage(package):
    """True when ``package`` is an importable Python package with a ``msg`` sub-package, found without importing."""
    try:
        spec = importlib.util.find_spec(package)
    except (ImportError, ValueError):
        return False
    if spec is None or not spec.submodule_search_locations:
        return False
    return any(os.path.isdir(os.path.join(location, "msg")) for location in spec.submodule_search_locations)


# Classes found so far, by every name they were asked for; failures are not kept (a package may be built later).
_LOADED_CLASSES = {}


def load_message_class(type_name):
    """The message class for ``"pkg/Type"`` (or ``"pkg.msg.Type"``); ConversionError when the name is malformed
    or no such type is installed."""
    cls = _LOADED_CLASSES.get(type_name) if isinstance(type_name, str) else None
    if cls is None:
        cls = _LOADED_CLASSES[type_name] = _find_message_class(type_name)
    return cls


def _find_message_class(type_name):
    if not isinstance(type_name, str):
        raise ConversionError(_type_name(type_name), "", "a message type must be a str like 'pkg/Type'")
    type_name = _TYPE_ALIASES.get(type_name, type_name)
    try:
        type_name = attribute_type_to_message_type(type_name)   # the naming rules are ngsi_encoding's
    except NgsiEncodingError:
        raise ConversionError(type_name, "", "not a message type name (expected 'pkg/Type')") from None
    package, name = type_name.split("/")
    if not _has_msg_subpackage(package):
        raise ConversionError(type_name, "", "unknown message type: no ROS package %r with messages is installed"
                              % package)
    try:
        cls = genpy.message.get_message_class(type_name)
    except (ImportError, ValueError, AttributeError, SyntaxError) as exc:
        raise ConversionError(type_name, "", "cannot load message class: %s" % exc) from None
    if cls is None or getattr(cls, "_type", None) != type_name:
        raise ConversionError(type_name, "", "unknown message type: package %r has no message %r"
                              % (package, name))
    return cls


# ---------------------------------------------------------------------------------------------------------------
# Message -> dict
# ---------------------------------------------------------------------------------------------------------------

def message_to_dict(msg):
    """All fields of a genpy message instance as JSON-safe values (see the module docstring for the encodings)."""
    if not _is_message(msg):
        raise ConversionError(type(msg).__name__, "", "not a ROS message instance")
    return _message_to_json(msg, msg._type, "")


def _message_to_json(msg, root, path):
    out = {}
    for name, field_type in zip(msg.__slots__, msg._slot_types):
        out[name] = _field_to_json(getattr(msg, name), field_type, root, "%s.%s" % (path, name))
    return out


def _field_to_json(value, field_type, root, path):
    base, kind, is_array, _fixed = _parse_field_type(field_type)
    try:
        if not is_array:
            return _TO_JSON[kind](value, root, path)
        if base in _BINARY_ELEMENT_TYPES:
            return _binary_to_json(value)
        convert = _TO_JSON[kind]
        return [convert(item, root, "%s[%d]" % (path, index)) for index, item in enumerate(value)]
    except ConversionError:
        raise
    except (TypeError, ValueError, AttributeError, OverflowError) as exc:
        raise ConversionError(root, path, "cannot convert %s value for %s: %s"
                              % (_type_name(value), field_type, exc)) from None


def _bool_to_json(value, root, path):
    return bool(value)


def _int_to_json(value, root, path):
    return int(value)


def _float_to_json(value, root, path):
    value = float(value)
    if math.isfinite(value):
        return value
    return _NONFINITE_TO_JSON[repr(value)]


def _string_to_json(value, root, path):
    if isinstance(value, (bytes, bytearray)):
        return bytes(value).decode("utf-8", "replace")
    return str(value)


def _time_to_json(value, root, path):
    return {"secs": int(value.secs), "nsecs": int(value.nsecs)}


def _nested_to_json(value, root, path):
    if not _is_message(value):
        raise ConversionError(root, path, "expected a message instance, got %s" % _type_name(value))
    return _message_to_json(value, root, path)


def _binary_to_json(value):
    if isinstance(value, str):  # genpy of old held uint8[] as str; keep the bytes' values
        value = value.encode("latin-1")
    return base64.b64encode(bytes(value)).decode("ascii")


_TO_JSON = {
    "bool": _bool_to_json,
    "int": _int_to_json,
    "float": _float_to_json,
    "string": _string_to_json,
    "time": _time_to_json,
    "message": _nested_to_json,
}


# ---------------------------------------------------------------------------------------------------------------
# dict -> message
# ---------------------------------------------------------------------------------------------------------------

def dict_to_message(data, msg_class_or_type, class_loader=load_message_class):
    """A new message of the given class (or ``"pkg/Type"`` name) filled from ``data``; ConversionError if bad."""
    if isinstance(msg_class_or_type, str):
        cls = class_loader(msg_class_or_type)
    else:
        cls = msg_class_or_type
    if not (isinstance(cls, type) and _is_message(cls)):
        raise ConversionError(_type_name(msg_class_or_type), "", "not a ROS message class")
    msg = cls()
    _fill_message(msg, data, _Context(cls._type, class_loader), "")
    return msg


class _Context:
    """What every helper needs while filling one message: the root type (for errors) and the class loader."""

    __slots__ = ("root", "class_loader")

    def __init__(self, root, class_loader):
        self.root = root
        self.class_loader = class_loader

    def error(self, path, problem):
        return ConversionError(self.root, path, problem)


def _fill_message(msg, data, ctx, path):
    if not isinstance(data, dict):
        raise ctx.error(path, "expected object, got %s" % _type_name(data))
    slots = dict(zip(msg.__slots__, msg._slot_types))
    unknown = [key for key in data if key not in slots]
    if unknown:
        raise ctx.error(path, "unknown field(s) %s for %s (fields: %s)" % (
            ", ".join(repr(key) for key in unknown), msg._type, ", ".join(msg.__slots__) or "none"))
    for name, value in data.items():
        field_path = "%s.%s" % (path, name)
        setattr(msg, name, _field_from_json(value, slots[name], getattr(msg, name), ctx, field_path))
    return msg


def _field_from_json(value, field_type, current, ctx, path):
    base, kind, is_array, fixed = _parse_field_type(field_type)
    if not is_array:
        return _FROM_JSON[kind](value, base, current, ctx, path)
    if base in _BINARY_ELEMENT_TYPES:
        return _binary_from_json(value, fixed, ctx, path)
    if not isinstance(value, list):
        raise ctx.error(path, "expected list, got %s" % _type_name(value))
    if fixed is not None and len(value) != fixed:
        raise ctx.error(path, "expected %d items, got %d" % (fixed, len(value)))
    if kind == "message" and value:  # one class lookup for the whole array
        cls = _element_class(base, ctx, path)
        return [_fill_message(cls(), item, ctx, "%s[%d]" % (path, index)) for index, item in enumerate(value)]
    convert = _FROM_JSON[kind]
    return [convert(item, base, None, ctx, "%s[%d]" % (path, index)) for index, item in enumerate(value)]


def _bool_from_json(value, base, current, ctx, path):
    if not isinstance(value, bool):
        raise ctx.error(path, "expected bool, got %s" % _type_name(value))
    return value


def _int_from_json(value, base, current, ctx, path):
    if isinstance(value, bool):
        raise ctx.error(path, "expected int, got bool")
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    if not isinstance(value, int):
        raise ctx.error(path, "expected int, got %s" % _type_name(value))
    low, high = _INT_RANGES[base]
    if not low <= value <= high:
        raise ctx.error(path, "%d is out of range for %s (%d..%d)" % (value, base, low, high))
    return value


def _float_from_json(value, base, current, ctx, path):
    if value is None:
        return float("nan")
    if isinstance(value, str):
        special = _NONFINITE_FROM_JSON.get(value.strip().lower())
        if special is None:
            raise ctx.error(path, "expected float, got str")
        return special
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ctx.error(path, "expected float, got %s" % _type_name(value))
    try:
        value = float(value)
    except OverflowError:
        raise ctx.error(path, "%d is out of range for %s" % (value, base)) from None
    limit = _FLOAT_LIMITS[base]
    if limit is not None and math.isfinite(value) and abs(value) > limit:
        raise ctx.error(path, "%r is out of range for %s" % (value, base))
    return value


def _string_from_json(value, base, current, ctx, path):
    if not isinstance(value, str):
        raise ctx.error(path, "expected str, got %s" % _type_name(value))
    try:
        value.encode("utf-8")
    except UnicodeEncodeError:
        raise ctx.error(path, "str is not valid unicode text (lone surrogate)") from None
    return value


def _time_from_json(value, base, current, ctx, path):
    if not isinstance(value, dict):
        raise ctx.error(path, "expected object with secs and nsecs for %s, got %s" % (base, _type_name(value)))
    unknown = [key for key in value if key not in ("secs", "nsecs")]
    if unknown:
        raise ctx.error(path, "unknown field(s) %s for %s (fields: secs, nsecs)"
                        % (", ".join(repr(key) for key in unknown), base))
    time_class, secs_range = _TIME_TYPES[base]
    secs = value.get("secs", current.secs if current is not None else 0)
    nsecs = value.get("nsecs", current.nsecs if current is not None else 0)
    secs = _checked_int(secs, secs_range, "secs", ctx, path)
    nsecs = _checked_int(nsecs, _NSECS_RANGE, "nsecs", ctx, path)
    return time_class(secs, nsecs)


def _checked_int(value, bounds, name, ctx, path):
    path = "%s.%s" % (path, name)
    if isinstance(value, bool):
        raise ctx.error(path, "expected int, got bool")
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    if not isinstance(value, int):
        raise ctx.error(path, "expected int, got %s" % _type_name(value))
    low, high = bounds
    if not low <= value <= high:
        raise ctx.error(path, "%d is out of range (%d..%d)" % (value, low, high))
    return value


def _nested_from_json(value, base, current, ctx, path):
    if current is None:
        current = _element_class(base, ctx, path)()
    return _fill_message(current, value, ctx, path)


def _element_class(base, ctx, path):
    try:
        cls = ctx.class_loader(base)
    except ConversionError as exc:
        raise ctx.error(path, exc.problem) from None
    if not (isinstance(cls, type) and _is_message(cls)):
        raise ctx.error(path, "unknown message type %s" % base)
    return cls


def _binary_from_json(value, fixed, ctx, path):
    if isinstance(value, str):
        try:
            data = base64.b64decode(value.encode("ascii"), validate=True)
        except (UnicodeEncodeError, binascii.Error, ValueError):
            raise ctx.error(path, "expected base64 text, got str that is not base64") from None
    elif isinstance(value, list):
        for index, item in enumerate(value):
            if isinstance(item, bool) or not isinstance(item, int) or not 0 <= item <= 255:
                raise ctx.error("%s[%d]" % (path, index), "expected int 0..255, got %r" % (item,))
        data = bytes(value)
    elif isinstance(value, (bytes, bytearray)):
        data = bytes(value)
    else:
        raise ctx.error(path, "expected base64 str or list of int, got %s" % _type_name(value))
    if fixed is not None and len(data) != fixed:
        raise ctx.error(path, "expected %d bytes, got %d" % (fixed, len(data)))
    return data


_FROM_JSON = {
    "bool": _bool_from_json,
    "int": _int_from_json,
    "float": _float_from_json,
    "string": _string_from_json,
    "time": _time_from_json,
    "message": _nested_from_json,
}


# ---------------------------------------------------------------------------------------------------------------
# Size without converting
# ---------------------------------------------------------------------------------------------------------------

# Serialized bytes of each fixed-size primitive, and the fewest JSON bytes message_to_dict's value gives for it.
_SERIALIZED_SIZE = {"bool": 1, "int8": 1, "byte": 1, "uint8": 1, "char": 1, "int16": 2, "uint16": 2,
                    "int32": 4, "uint32": 4, "float32": 4, "int64": 8, "uint64": 8, "float64": 8,
                    "time": 8, "duration": 8}
_MIN_JSON = {"bool": 4, "float32": 3, "float64": 3, "time": 20, "duration": 20}    # others: one digit
_LENGTH_PREFIX = 4          # uint32 before every string and variable array
_LENGTH_RATIO = 2 / 4       # inside an array: a 4-byte length gives at least "" or []
_TEXT_RATIO = 1.0           # a string's content byte gives at least one JSON byte
_BASE64_RATIO = 4 / 3       # uint8[] / char[] content
_NO_VARIABLE_PART = float("inf")


def _scalar_ratio(base):
    return _MIN_JSON.get(base, 1) / _SERIALIZED_SIZE[base]


@functools.lru_cache(maxsize=None)
def _layout(cls, inside_array):
    """(fixed bytes, smallest JSON bytes per other byte) of a message class. ``inside_array``: its bytes all
    belong to an array element (nothing is fixed; scalars and lengths count by their ratios)."""
    fixed, ratio = 0, _NO_VARIABLE_PART
    for field_type in cls._slot_types:
        base, kind, is_array, length = _parse_field_type(field_type)
        if kind == "message":
            try:
                element = _element_class(base, _Context(cls._type, load_message_class), "")
            except ConversionError:
                return 0, 0.0                      # an unknown nested type: no bound at all
            nested_fixed, nested_ratio = _layout(element, inside_array or is_array)
            if not is_array:
                fixed += nested_fixed
            elif length is None:
                fixed, ratio = (fixed + _LENGTH_PREFIX, ratio) if not inside_array else \
                    (fixed, min(ratio, _LENGTH_RATIO))
            ratio = min(ratio, nested_ratio)
            continue
        binary = is_array and base in _BINARY_ELEMENT_TYPES
        if base == "string":
            if inside_array or is_array:
                ratio = min(ratio, _LENGTH_RATIO, _TEXT_RATIO)
            else:
                fixed += _LENGTH_PREFIX
                ratio = min(ratio, _TEXT_RATIO)
            if is_array and length is None and not inside_array:
                fixed += _LENGTH_PREFIX
            continue
        if is_array and length is None:            # a variable array: its length, then its elements
            if inside_array:
                ratio = min(ratio, _LENGTH_RATIO)
            else:
                fixed += _LENGTH_PREFIX
            ratio = min(ratio, _BASE64_RATIO if binary else _scalar_ratio(base))
        elif inside_array:                         # a scalar or fixed array inside an array element
            ratio = min(ratio, _BASE64_RATIO if binary else _scalar_ratio(base))
        else:                                      # a scalar or fixed array of scalars at a fixed place
            fixed += _SERIALIZED_SIZE[base] * (length or 1)
    return fixed, ratio


def json_size_lower_bound(msg_class, data):
    """Bytes the compact JSON of the message of ``msg_class`` serialized in ``data`` is certain to reach (see
    "Size without converting" in the module docstring); 0 when nothing can be said."""
    fixed, ratio = _layout(msg_class, False)
    by_ratio = 0 if ratio == _NO_VARIABLE_PART else max(0, int((len(data) - fixed) * ratio))
    walk = _Walk(data)
    try:
        by_walk = walk.message(msg_class)
    except _WalkEnd:
        by_walk = walk.bound
    return max(by_ratio, by_walk)


class _WalkEnd(Exception):
    """The walk cannot go on (a type it cannot load, or bytes that end early)."""


_LENGTH = struct.Struct("<I")
_WALK_BUDGET = 4096         # fields and array elements a walk visits at most: it must stay far cheaper than converting


class _Walk:
    """Walks a serialization by the lengths it holds, adding up the JSON bytes each field is sure to give; stops
    (keeping what it has) after _WALK_BUDGET fields or elements of arrays of strings or messages."""

    def __init__(self, data):
        self.data = data
        self.offset = 0
        self.bound = 0
        self.budget = _WALK_BUDGET

    def _spend(self, count):
        self.budget -= count
        if self.budget < 0:
            raise _WalkEnd()

    def _skip(self, count):
        self.offset += count
        if self.offset > len(self.data):
            raise _WalkEnd()

    def _length(self):
        start = self.offset
        self._skip(4)
        return _LENGTH.unpack_from(self.data, start)[0]

    def message(self, cls):
        """Walk one message; returns the bound so far (also left in ``self.bound`` when the walk ends early)."""
        self._spend(len(cls.__slots__))
        self.bound += 2 + max(0, len(cls.__slots__) - 1)            # braces and commas
        for name, field_type in zip(cls.__slots__, cls._slot_types):
            self.bound += len(name) + 3                             # "name":
            base, kind, is_array, length = _parse_field_type(field_type)
            if is_array:
                self._array(base, kind, length)
            elif kind == "message":
                self.message(self._class(base))
            elif base == "string":
                size = self._length()
                self._skip(size)
                self.bound += size + 2
            else:
                self._skip(_SERIALIZED_SIZE[base])
                self.bound += _MIN_JSON.get(base, 1)
        return self.bound

    def _array(self, base, kind, length):
        count = self._length() if length is None else length
        if base in _BINARY_ELEMENT_TYPES:
            self._skip(count)
            self.bound += 2 + 4 * ((count + 2) // 3)                # base64 in quotes
            return
        self.bound += 2 + max(0, count - 1)                         # brackets and commas
        if base in _SERIALIZED_SIZE:
            self._skip(count * _SERIALIZED_SIZE[base])
            self.bound += count * _MIN_JSON.get(base, 1)
            return
        cls = self._class(base) if kind == "message" else None
        for _ in range(count):
            self._spend(1)
            if cls is None:
                size = self._length()
                self._skip(size)
                self.bound += size + 2
            else:
                self.message(cls)

    def _class(self, base):
        try:
            return load_message_class(base)
        except ConversionError:
            raise _WalkEnd() from None


class SerializedMessage:
    """A message of ``msg_class`` still in its ROS serialization ``data`` (bytes-like)."""

    __slots__ = ("msg_class", "data")

    def __init__(self, msg_class, data):
        self.msg_class = msg_class
        self.data = data

    @property
    def size(self):
        return len(self.data)

    def message(self):
        """The deserialized message; ConversionError when the bytes are not one of ``msg_class``."""
        data = self.data if isinstance(self.data, bytes) else bytes(self.data)
        try:
            return self.msg_class().deserialize(data)
        except (genpy.DeserializationError, struct.error, UnicodeDecodeError, ValueError, TypeError,
                IndexError) as exc:
            raise ConversionError(self.msg_class._type, "", "cannot deserialize %d bytes: %s"
                                  % (len(data), exc)) from None
