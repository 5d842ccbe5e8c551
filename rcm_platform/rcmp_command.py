"""Errors a user can cause and the validation of everything a user sends to the RDAPI.

Owns ``CommandError`` and its subclasses (each carries the HTTP status the RDAPI answers with and a sentence naming
the problem), the rules for names (ROS graph names without slashes: a letter, then letters, digits and
underscores, at most 64 characters), the validation of service nodes and service launchers, and the splitting of
params as a shell would split them (``shlex.split``; no shell ever runs them) and the rules of what params may
hold (``check_params``: a launcher's only ``arg:=value``; no item's the ROS specials that redirect a process).

Also owns ``ReadCache``: the answers of the read commands kept in memory until the robotics data changes (see
``RoboticsData.generation``), so that reads do not go to SQLite (and to a thread) while nothing changed.

And what a validated service item becomes when it runs: ``ServiceItem`` (built only from
``validate_service_item``'s result, so the runtime never sees an unchecked item) with the command lines and the
environment of its child (``node_argv``, ``launcher_argv``, ``child_env``), the node list of a launcher through
roslaunch's own loader (``launcher_nodes``), and the graph name a node registers under (``graph_name``).
``split_params`` is the only place where params are split into words. ``NodeExecutables`` finds the file that
``rosrun PKG TYPE`` would run, the way roslaunch finds it, so that a node starts as one exec instead of through
rosrun's bash, ``catkin_find`` and ``rospack`` (0.2 CPU-seconds per node, measured: docs/PERFORMANCE.md).
"""

import functools
import os
import re
import shlex
import time

from twisted.internet import defer

from .rcmp_config import MAX_NAME_LENGTH, is_name

MAX_FIELD_LENGTH = 255
MAX_PARAMS_LENGTH = 4096
MAX_ITEMS = 256

PACKAGE_RE = re.compile(r"[A-Za-z][A-Za-z0-9_-]*\Z")
FILE_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.+-]*\Z")
SIDES = ("S", "R")


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


def _item_list_field(entry):
    """``sn_list`` for a service node entry, ``sl_list`` for a launcher entry (BadRequest for neither)."""
    if isinstance(entry, dict) and "sn_name" in entry:
        return "sn_list"
    if isinstance(entry, dict) and "sl_name" in entry:
        return "sl_list"
    raise BadRequest(f"a service item must be an object with 'sn_name' or 'sl_name', not {_show(entry)}")


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


# ---------------------------------------------------------------------------------------------------------------
# Service items as they run: argv, environment, launcher node lists.

ROS_PATH_PREFIX = ["/usr/bin", "/bin", "/usr/sbin", "/sbin"]
# An item's own state while it has no process (or failed without one): the words of rcmp_ms's process states.
ITEM_STARTING = "starting"
ITEM_FAILED = "failed"


def child_env(base_env, ros_master_uri, address, ros_log_dir):
    """The environment of a ROS child: the agent's, /usr/bin first on PATH, the space's master and address."""
    env = dict(os.environ if base_env is None else base_env)
    rest = [p for p in env.get("PATH", "").split(":") if p and p not in ROS_PATH_PREFIX]
    env["PATH"] = ":".join(ROS_PATH_PREFIX + rest)
    env["ROS_MASTER_URI"] = ros_master_uri
    env["ROS_IP"] = address
    env["ROS_HOSTNAME"] = address
    env["ROS_LOG_DIR"] = ros_log_dir
    env["PYTHONUNBUFFERED"] = "1"
    env.pop("ROS_NAMESPACE", None)
    return env


def node_argv(package, node_type, name, params=""):
    """``rosrun PKG TYPE PARAMS __name:=NAME`` as an argv list (params split as a shell would, no shell)."""
    return ["rosrun", package, node_type, *split_params(params or ""), "__name:=" + name]


class NodeExecutables:
    """The file ``rosrun PKG TYPE`` runs, found with roslaunch's own lookup (``roslib.packages.find_node``) and
    remembered, so that an agent starting many nodes runs each directly (``direct_argv``).

    Same choice as rosrun: one executable match is it; of two, the one in the package's catkin ``libexec``
    folder (a devel-space relay of the other). Anything else (no such package or executable, an ambiguous
    name, an environment whose package paths differ from the agent's, where the lookup would not be the
    child's) keeps the ``rosrun`` argv, so rosrun's own error reaches the item's log. A remembered file is used
    while it is still executable; the package crawl is redone after ``ttl`` seconds. Blocking (a crawl of
    the package path the first time, a few milliseconds): called on the reactor thread when a node starts.
    rospkg, roslib and catkin are imported when this is made (at an agent's start, on its main thread: an
    import in a thread while the reactor forks a child can deadlock CPython, and one made during a fleet's
    arrival would stall the reactor while the cores are busiest).
    """

    PATH_KEYS = ("ROS_PACKAGE_PATH", "CMAKE_PREFIX_PATH")

    def __init__(self, ttl=60.0, clock=time.monotonic):
        try:   # python3-roslib (which brings rospkg and catkin) comes with rospy; without it, rosrun decides
            import catkin.find_in_workspaces  # noqa: F401  (see the docstring)
            import roslib.packages  # noqa: F401
            import rospkg  # noqa: F401
            self.available = True
        except ImportError:
            self.available = False
        self.ttl = ttl
        self.clock = clock
        self._rospack = None
        self._crawled = None
        self._found = {}

    def direct_argv(self, argv, env):
        """``argv`` with ``rosrun PKG TYPE`` replaced by the executable it would run, when that is certain."""
        if not self.available or len(argv) < 3 or argv[0] != "rosrun" or argv[1].startswith("-"):
            return list(argv)
        if any(env.get(key, "") != os.environ.get(key, "") for key in self.PATH_KEYS):
            return list(argv)
        path = self.find(argv[1], argv[2])
        return [path, *argv[3:]] if path else list(argv)

    def find(self, package, node_type):
        """The executable's path, or None when rosrun itself must decide (and say what is wrong)."""
        path = self._found.get((package, node_type))
        if path is not None and os.access(path, os.X_OK):
            return path
        path = self._lookup(package, node_type)
        if path is None:
            self._found.pop((package, node_type), None)
        else:
            if len(self._found) >= 1024:
                self._found.clear()
            self._found[(package, node_type)] = path
        return path

    def _lookup(self, package, node_type):
        import rospkg
        import roslib.packages
        from catkin.find_in_workspaces import find_in_workspaces
        now = self.clock()
        if self._rospack is None or now - self._crawled > self.ttl:
            self._rospack, self._crawled = rospkg.RosPack(), now
        try:
            matches = roslib.packages.find_node(package, node_type, rospack=self._rospack)
            if len(matches) == 2:
                libexec = find_in_workspaces(search_dirs=["libexec"], project=package,
                                             first_matching_workspace_only=True)
                matches = [m for m in matches if any(m.startswith(d.rstrip("/") + "/") for d in libexec)]
        except Exception:  # rospkg.ResourceNotFound, an unreadable package.xml: rosrun will say
            return None
        return matches[0] if len(matches) == 1 else None


def launcher_argv(package, launch_file, params="", sigint_timeout=2.0, sigterm_timeout=1.0):
    """``roslaunch --wait PKG FILE PARAMS`` with roslaunch's own stop timeouts inside ours.

    ``--wait``: the space's master is already up when items start; should it be gone, a launcher must wait
    (and show as not paired) rather than start a ROS master of its own on the space's port.
    """
    return ["roslaunch", "--wait", f"--sigint-timeout={sigint_timeout:g}",
            f"--sigterm-timeout={sigterm_timeout:g}", package, launch_file, *split_params(params or "")]


def launcher_nodes(package, launch_file, params=""):
    """[(node name without leading slash, package, type)] that ``roslaunch PKG FILE PARAMS`` would start.

    Uses roslaunch's own loader (no output parsing); blocking: call it in a thread. Raises
    ``roslaunch.core.RLException`` (its message names the problem) for a missing package, file or arg.
    """
    import roslaunch.config
    import roslaunch.rlutil
    args = split_params(params or "")
    resolved = roslaunch.rlutil.resolve_launch_arguments([package, launch_file] + args)  # drops name:=value
    config = roslaunch.config.load_config_default([(resolved[0], [resolved[0]] + args)], None, verbose=False,
                                                  assign_machines=False)
    nodes = []
    for node in config.nodes:
        full = (node.namespace or "/") + node.name
        nodes.append((full.lstrip("/"), node.package, node.type))
    return nodes


def graph_name(name, params=""):
    """The ROS graph name ``rosrun PKG TYPE PARAMS __name:=NAME`` registers under: ``/NAME``, or
    ``/NS/NAME`` when the params hold ``__ns:=NS`` (params that do not split: the plain name)."""
    try:
        words = split_params(params or "")
    except BadRequest:
        words = []
    namespace = next((w.split(":=", 1)[1] for w in reversed(words) if w.startswith("__ns:=")), "")
    namespace = namespace.strip("/")
    return f"/{namespace}/{name}" if namespace else f"/{name}"


class ServiceItem:
    """One node or launcher of a service space, run here (``process``) or on the robot (``remote``).

    Built only from a validated entry (``from_entry``); ``special`` is the runtime's hooks for the nodes it
    treats specially (FIROS, rcm_driver: ``rcmp_ms.SPECIAL_ITEMS``), None for the others.
    """

    def __init__(self, kind, name, package, type_or_file, params, side, i_name):
        self.kind = kind
        self.name = name
        self.package = package
        self.type_or_file = type_or_file
        self.params = params or ""
        self.side = side
        self.i_name = i_name
        self.special = None
        self.process = None     # ManagedProcess, when run by this agent
        self.remote = None      # the robot's item report, when run there
        self.own_state = ITEM_STARTING
        self.error = None       # set when the item failed before or without a process
        self.nodes = []         # ROS node names (the node itself, or the launcher's nodes)
        self.node_types = {}    # launcher node name -> (package, type)
        self.driver_port = None
        self.inbound_port = None

    @classmethod
    def from_entry(cls, entry, i_name, index=0, list_field=None):
        """A ServiceItem from a service logic entry (``sn_*`` node or ``sl_*`` launcher fields; ``list_field``
        says which, else the name field does), validated by ``validate_service_item``; BadRequest says why."""
        list_field = list_field or _item_list_field(entry)
        checked = validate_service_item(list_field, entry, index)
        if list_field == "sn_list":
            return cls("node", checked["sn_name"], checked["sn_package"], checked["sn_type"],
                       checked["sn_params"], checked["sn_side"], i_name)
        return cls("launcher", checked["sl_name"], checked["sl_package"], checked["sl_file_launcher"],
                   checked["sl_params"], checked["sl_side"], i_name)

    def to_dict(self):
        """The service logic entry this item came from (what a robot is sent)."""
        if self.kind == "node":
            return {"sn_package": self.package, "sn_type": self.type_or_file, "sn_name": self.name,
                    "sn_params": self.params, "sn_side": self.side}
        return {"sl_package": self.package, "sl_file_launcher": self.type_or_file, "sl_name": self.name,
                "sl_params": self.params, "sl_side": self.side}

    def argv(self, params=None, extra=()):
        """The item's argv (never a shell): ``params`` replaces the item's own, ``extra`` words go last."""
        params = self.params if params is None else params
        if self.kind == "launcher":
            return launcher_argv(self.package, self.type_or_file, params) + list(extra)
        return node_argv(self.package, self.type_or_file, self.name, params) + list(extra)

    @property
    def state(self):
        if self.remote is not None:
            return self.remote.get("state", ITEM_FAILED)
        if self.process is not None and self.error is None:
            return self.process.state
        return self.own_state

    @property
    def current_error(self):
        if self.remote is not None:
            return self.remote.get("error")
        if self.error is not None:
            return self.error
        return self.process.error if self.process is not None else None

    def fail(self, error):
        self.error = error
        self.own_state = ITEM_FAILED

    def report(self):
        """The item report of docs/DESIGN.md (what a robot returns to the master)."""
        if self.remote is not None:
            return dict(self.remote)
        return {"kind": self.kind, "name": self.name, "package": self.package,
                "type_or_file": self.type_or_file, "side": self.side, "i_name": self.i_name,
                "state": self.state, "error": self.current_error, "nodes": list(self.nodes),
                "node_types": {n: list(t) for n, t in self.node_types.items()}}


def items_of_logic(service_logic, i_name=None):
    """The ServiceItems of a service logic dict (``sn_list`` nodes, then ``sl_list`` launchers); BadRequest
    names the first bad entry."""
    items = []
    for list_field in ("sn_list", "sl_list"):
        entries = service_logic.get(list_field) or []
        if not isinstance(entries, list):
            raise BadRequest(f"'{list_field}' must be a list, not {_json_type(entries)}")
        for index, entry in enumerate(entries):
            items.append(ServiceItem.from_entry(entry, i_name, index, list_field))
    return items
