"""Errors a user can cause and the validation of everything a user sends to the RDAPI.

Owns ``CommandError`` and its subclasses (each carries the HTTP status the RDAPI answers with and a sentence naming
the problem: ``BadRequest`` 400, ``Unauthorized`` 401, ``Forbidden`` 403, ``NotFound`` 404, ``MethodNotAllowed``
405, ``Conflict`` 409, ``TooLarge`` 413, ``UnsupportedMediaType`` 415, ``Unavailable`` 503); the validation of
names (the platform's name rule, ``rcmp_config.NAME_RE``: ROS graph names without slashes), of service nodes and
service launchers (``validate_service_item``, ``validate_service_logic``, ``logic_entries``) and of request
bodies; the splitting
of params as a shell would split them (``split_params``, the only place where params become words: ``shlex``,
no shell ever runs them) and the rules of what params may hold (``check_params``: a launcher's only
``arg:=value``; no item's the ROS specials that redirect a process); the RDAPI token roles (``TOKEN_ROLES``).

Also owns ``ReadCache``: the answers of the read commands kept in memory until the robotics data changes (see
``RoboticsData.generation``), so that reads do not go to SQLite (and to a thread) while nothing changed.

What a validated service item becomes when it runs (its command line, environment and user) is
``rcmp_service_item``'s.
"""

import functools
import re
import shlex

from twisted.internet import defer

from .rcmp_config import MAX_NAME_LENGTH, is_name

MAX_FIELD_LENGTH = 255
MAX_PARAMS_LENGTH = 4096
MAX_ITEMS = 256

PACKAGE_RE = re.compile(r"[A-Za-z][A-Za-z0-9_-]*\Z")
FILE_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.+-]*\Z")
SIDES = ("S", "R")
TOKEN_ROLES = ("read", "admin")   # an RDAPI token's role: read (GET calls only) or admin (every call)


class CommandError(Exception):
    """A request the platform refuses; ``str()`` is the sentence given back as ``reason``."""

    status = 400


class BadRequest(CommandError):
    """Malformed or invalid input (HTTP 400)."""

    status = 400


class Unauthorized(CommandError):
    """No token, or an unknown one, where the RDAPI needs one (HTTP 401)."""

    status = 401


class Forbidden(CommandError):
    """The caller is known but may not make this call: a read token on a write, a foreign page (HTTP 403)."""

    status = 403


class NotFound(CommandError):
    """Unknown name or path (HTTP 404)."""

    status = 404


class MethodNotAllowed(CommandError):
    """The path exists but not with this method (HTTP 405); ``allowed`` lists the methods it takes."""

    status = 405

    def __init__(self, message, allowed=()):
        super().__init__(message)
        self.allowed = tuple(allowed)


class Conflict(CommandError):
    """Duplicate name, or a service logic still in use (HTTP 409)."""

    status = 409


class TooLarge(CommandError):
    """The request body is over the size limit (HTTP 413)."""

    status = 413


class UnsupportedMediaType(CommandError):
    """A request body not sent as ``application/json`` (HTTP 415)."""

    status = 415


class Unavailable(CommandError):
    """This master cannot serve the call: a part of it is not installed (HTTP 503; ``/metrics`` without
    prometheus_client). Not the caller's mistake, but said as one sentence like the others."""

    status = 503


def _show(value, limit=40):
    """A short, printable rendering of a user value for an error sentence."""
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def validate_name(value, field):
    """Return ``value`` if it is a valid platform name (pi_name, slg_name, sn_name, sl_name); else BadRequest."""
    if not isinstance(value, str):
        raise BadRequest(f"'{field}' must be a string, not {type(value).__name__}")
    if not value:
        raise BadRequest(f"'{field}' must not be empty")
    if len(value) > MAX_NAME_LENGTH:
        raise BadRequest(f"'{field}' is longer than {MAX_NAME_LENGTH} characters")
    if not is_name(value):
        raise BadRequest(f"'{field}' {_show(value)} is not a valid name: use a letter, then letters, digits "
                         f"and underscores (no slashes, spaces or other characters)")
    return value


def _validate_token(value, field, pattern, what):
    if not isinstance(value, str):
        raise BadRequest(f"'{field}' must be a string, not {type(value).__name__}")
    if not value:
        raise BadRequest(f"'{field}' must not be empty")
    if len(value) > MAX_FIELD_LENGTH:
        raise BadRequest(f"'{field}' is longer than {MAX_FIELD_LENGTH} characters")
    if not pattern.match(value):
        raise BadRequest(f"'{field}' {_show(value)} is not a valid {what}")
    return value


def validate_side(value, field):
    """Return ``value`` if it is ``S`` (server side) or ``R`` (robot side)."""
    if value not in SIDES or not isinstance(value, str):
        raise BadRequest(f"'{field}' must be \"S\" (server side) or \"R\" (robot side), not {_show(value)}")
    return value


def split_params(value, field="params"):
    """Split ``value`` as a POSIX shell would (quotes, escapes) into an argv list; BadRequest if it cannot."""
    if not isinstance(value, str):
        raise BadRequest(f"'{field}' must be a string, not {type(value).__name__}")
    if len(value) > MAX_PARAMS_LENGTH:
        raise BadRequest(f"'{field}' is longer than {MAX_PARAMS_LENGTH} characters")
    if "\x00" in value:
        raise BadRequest(f"'{field}' contains a NUL character")
    try:
        return shlex.split(value)
    except ValueError as exc:
        raise BadRequest(f"'{field}' cannot be split into arguments: {exc}") from None


# ROS's special arguments that would redirect a process: where it logs, which master, which address it uses
ROS_SPECIALS = ("__log:=", "__master:=", "__ip:=", "__hostname:=")
LAUNCH_ARG_RE = re.compile(r"[A-Za-z][A-Za-z0-9_]*:=", re.S)


def check_params(words, field, launcher):
    """Refuse params that would become options or files of our tools (CONTRACTS §10): BadRequest naming the word.

    In any item, the ROS specials of ``ROS_SPECIALS``; in a launcher, anything but ``arg:=value`` words (no
    roslaunch option such as ``--pid=FILE``, no extra launch file). A node's other words are its own program's.
    """
    for word in words:
        for special in ROS_SPECIALS:
            if word.startswith(special):
                raise BadRequest(f"'{field}' must not set the ROS special argument {special!r}: it would redirect "
                                 f"the process (its log file, ROS master or address); see docs/RDAPI.md")
        if launcher and not LAUNCH_ARG_RE.match(word):
            raise BadRequest(f"'{field}' may hold only arg:=value words for roslaunch (an arg name is a letter, "
                             f"then letters, digits and _); {_show(word)} is not one")
    return words


def _check_fields(item, where, required, optional):
    if not isinstance(item, dict):
        raise BadRequest(f"{where} must be a JSON object, not {_json_type(item)}")
    for key in item:
        if key not in required and key not in optional:
            raise BadRequest(f"{where} has an unknown field {_show(key)}")
    for key in required:
        if key not in item:
            raise BadRequest(f"{where} lacks the required field '{key}'")


# The two kinds of service item: list field, field prefix, and the (field, pattern, what) of their ROS tokens.
ITEM_KINDS = {
    "sn_list": ("sn", (("sn_package", PACKAGE_RE, "package name"),
                       ("sn_type", FILE_RE, "node type (executable name)"))),
    "sl_list": ("sl", (("sl_package", PACKAGE_RE, "package name"),
                       ("sl_file_launcher", FILE_RE, "launch file name"))),
}


def validate_service_item(list_field, item, index=0):
    """Return a normalised service node (``sn_list``) or launcher (``sl_list``) dict, or raise BadRequest.

    The result has all five fields of its kind, with params a string that splits as a shell would split it.
    """
    prefix, tokens = ITEM_KINDS[list_field]
    where = f"{list_field}[{index}]"
    name_field, params_field, side_field = f"{prefix}_name", f"{prefix}_params", f"{prefix}_side"
    _check_fields(item, where, tuple(f for f, _, _ in tokens) + (name_field, side_field), (params_field,))
    params = item.get(params_field)
    params = "" if params is None else params
    check_params(split_params(params, f"{where}.{params_field}"), f"{where}.{params_field}",
                 launcher=list_field == "sl_list")
    result = {field: _validate_token(item[field], f"{where}.{field}", pattern, what)
              for field, pattern, what in tokens}
    result[name_field] = validate_name(item[name_field], f"{where}.{name_field}")
    result[params_field] = params
    result[side_field] = validate_side(item[side_field], f"{where}.{side_field}")
    return result


def _json_type(value):
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, (int, float)):
        return "a number"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, list):
        return "a list"
    if isinstance(value, dict):
        return "an object"
    return type(value).__name__


def item_list_field(entry):
    """``sn_list`` for a service node entry, ``sl_list`` for a launcher entry (BadRequest for neither)."""
    if isinstance(entry, dict) and "sn_name" in entry:
        return "sn_list"
    if isinstance(entry, dict) and "sl_name" in entry:
        return "sl_list"
    raise BadRequest(f"a service item must be an object with 'sn_name' or 'sl_name', not {_show(entry)}")


def logic_entries(service_logic):
    """``(list_field, index, entry)`` of every item entry of a service logic dict (as stored, or as the master
    sends it): the ``sn_list`` nodes, then the ``sl_list`` launchers; BadRequest when a list is not a list. Each
    entry still needs ``validate_service_item``."""
    entries = []
    for list_field in ("sn_list", "sl_list"):
        found = service_logic.get(list_field) or []
        if not isinstance(found, list):
            raise BadRequest(f"'{list_field}' must be a list, not {_json_type(found)}")
        entries.extend((list_field, index, entry) for index, entry in enumerate(found))
    return entries


def require_fields(body, required, optional=()):
    """Check that the request body ``body`` (a dict) has every required field and no unknown one."""
    if not isinstance(body, dict):
        raise BadRequest(f"the request body must be a JSON object, not {_json_type(body)}")
    for key in body:
        if key not in required and key not in optional:
            raise BadRequest(f"unknown field {_show(key)} (expected: {', '.join(tuple(required) + tuple(optional))})")
    for key in required:
        if key not in body:
            raise BadRequest(f"the required field '{key}' is missing")


def validate_service_logic(body):
    """Validate a ``service_logic/provisioning`` body; return ``(slg_name, sn_list, sl_list, ss_side)``."""
    require_fields(body, ("slg_name",), ("sn_list", "sl_list", "ss_side"))
    slg_name = validate_name(body["slg_name"], "slg_name")
    lists = []
    for field in ("sn_list", "sl_list"):
        value = body.get(field)
        if value is None:
            value = []
        if not isinstance(value, list):
            raise BadRequest(f"'{field}' must be a list, not {_json_type(value)}")
        if len(value) > MAX_ITEMS:
            raise BadRequest(f"'{field}' has more than {MAX_ITEMS} items")
        lists.append([validate_service_item(field, item, i) for i, item in enumerate(value)])
    sn_list, sl_list = lists
    ss_side = validate_side(body["ss_side"], "ss_side") if body.get("ss_side") is not None else "S"
    seen = set()
    for name in [n["sn_name"] for n in sn_list] + [l["sl_name"] for l in sl_list]:
        if name in seen:
            raise BadRequest(f"the item name '{name}' is used twice in service logic '{slg_name}'")
        seen.add(name)
    return slg_name, sn_list, sl_list, ss_side


def command(func):
    """Make a command method always return a Deferred, failing (not raising) on a CommandError."""
    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        return defer.maybeDeferred(func, *args, **kwargs)
    return wrapper


class ReadCache:
    """Answers of read commands, valid while the robotics data's ``generation`` has not moved.

    Writes bump ``RoboticsData.generation`` (in the same lock as their transaction), so a cached answer is
    served only if no write committed since it was read. The number of entries is bounded.
    """

    def __init__(self, data, max_entries=512):
        self.data = data
        self.max_entries = max_entries
        self._entries = {}

    def get(self, key):
        entry = self._entries.get(key)
        if entry is not None and entry[0] == self.data.generation:
            return entry[1]
        return None

    def put(self, key, generation, value):
        if len(self._entries) >= self.max_entries:
            self._entries.clear()
        self._entries[key] = (generation, value)
        return value
