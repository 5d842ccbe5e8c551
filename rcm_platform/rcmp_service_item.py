"""What a service item is and how it becomes a process: its command line, its environment and its user.

A newcomer's question "where does a service item get its command line, environment and user?" has its answer here
(the runtime, ``rcmp_ms``, only asks; the process table, ``rcmp_process``, only applies what it is given):

- **what it is**: ``ServiceItem``, one node (``sn_*``) or launcher (``sl_*``) of a service logic, built only from
  ``rcmp_command.validate_service_item``'s result (``ServiceItem.from_entry``, ``items_of_logic``), so the runtime
  never sees an unchecked item (a robot refuses a malformed item from the master with the validation's sentence).
  Its state is its process's (``rcmp_process`` words), the robot's report when it runs there, or its own
  ``starting`` / ``failed`` while it has no process. A failed item says why in a sentence (``current_error``) and
  in one word of the closed set ``ITEM_FAILURES`` (``failure``; item reports carry it as ``"failure"``), which
  the master counts (``/metrics``).
- **its command line**: ``ServiceItem.argv`` (``node_argv``: ``rosrun PKG TYPE PARAMS __name:=NAME``;
  ``launcher_argv``: ``roslaunch --wait ... PKG FILE PARAMS``; params split by ``rcmp_command.split_params``, the
  only splitter, never a shell), changed by its special hooks when it is one of ``SPECIAL_ITEMS`` (FIROS gets
  ``-P`` and one of the inbound open ports, rcm_driver its own ``port=N`` and, in its environment, the one-time
  key it obeys the agent by), and ``ServiceItem.spawn_argv``: a
  node's ``rosrun PKG TYPE`` replaced by the file rosrun would run (``NodeExecutables``, roslaunch's own lookup:
  one exec instead of rosrun's bash, catkin_find and rospack, 0.2 CPU-seconds per node). What a launcher starts
  is read with roslaunch's own loader (``launcher_nodes``; ``launcher_nodes_as`` in a child running as the items'
  user), and a node's graph name from its params (``graph_name``).
- **its environment**: ``child_env``: the agent's environment (the ROS installation's and, on top of it, the
  catkin workspace's search paths, which ``apply_ros_environment`` and ``apply_workspace`` put there at start),
  ``/usr/bin`` first on PATH, the space's ``ROS_MASTER_URI``, ``ROS_IP``/``ROS_HOSTNAME`` and ``ROS_LOG_DIR``,
  and, for another user, that user's HOME, USER, ROS_HOME and the workspace's code paths when the workspace is
  theirs (``RunAs.environment``, ``WorkspaceOverlay.for_child``). ``workspace_overlay`` runs the workspace's
  ``devel/setup.bash`` as its owner, never as root, to learn them; ``ros_environment`` runs the ROS
  installation's setup script (``ros_setup``, CONTRACTS §1: ``/opt/ros/noetic/setup.bash`` on Ubuntu with ROS's
  packages, none with Debian's) as the agent's own user, a root agent only when nobody else can change it, and
  ``apply_ros_environment`` also puts ROS's Python packages on the agent's ``sys.path`` for its own lookups.
- **its user**: ``resolve_run_as(config)``: ``run_as`` (CONTRACTS §10), else the owner of the ROS workspace the
  installer made, as a ``RunAs`` (its ``setpriv_args`` are what the process table's ``setpriv`` switches to),
  or None for the agent's own user. ``RunAsError`` (one line) when that cannot be.
"""

import dataclasses
import importlib
import json
import logging
import os
import pwd
import secrets
import shlex
import signal
import stat
import subprocess
import sys
import tempfile
import time

from .rcmp_command import BadRequest, item_list_field, logic_entries, split_params, validate_service_item
from .rcmp_config import ROS_ROOT, ros_setup_script
from .rcmp_process import FAILED, RUNNING, SETPRIV, STARTING, nice_prefix

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------------------------------
# The command line and the environment.

ROS_PATH_PREFIX = ["/usr/bin", "/bin", "/usr/sbin", "/sbin"]


def child_env(base_env, ros_master_uri, address, ros_log_dir, user=None, agent_home=None):
    """The environment of a ROS child of a service space: the agent's own (``base_env``, else ``os.environ``, which
    holds the workspace's search paths since ``apply_workspace``), ``/usr/bin`` first on PATH, the space's
    ``ROS_MASTER_URI``, its address as ``ROS_IP`` and ``ROS_HOSTNAME``, ``ROS_LOG_DIR``. For a child running as
    ``user`` (a ``RunAs``): that user's HOME, USER, LOGNAME, ROS_HOME and ROS_LOG_DIR and the code paths of a
    workspace they own (``RunAs.environment``), and ``RCMP_HOME`` naming the agent's folder (``agent_home``)."""
    env = dict(os.environ if base_env is None else base_env)
    rest = [p for p in env.get("PATH", "").split(":") if p and p not in ROS_PATH_PREFIX]
    env["PATH"] = ":".join(ROS_PATH_PREFIX + rest)
    env["ROS_MASTER_URI"] = ros_master_uri
    env["ROS_IP"] = address
    env["ROS_HOSTNAME"] = address
    env["ROS_LOG_DIR"] = ros_log_dir
    env["PYTHONUNBUFFERED"] = "1"
    env.pop("ROS_NAMESPACE", None)
    if user is not None:
        env = user.environment(env)
        if agent_home is not None:
            env["RCMP_HOME"] = agent_home
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


# ---------------------------------------------------------------------------------------------------------------
# Special items: the nodes the runtime treats specially, recognised in one place, with hooks.

class SpecialItem:
    """Hooks the runtime calls for one kind of special node; the defaults do nothing."""

    name = None
    announces_entities = False   # it publishes the robot as an entity (rcm_driver waits for e_removed)

    def prepare(self, host, space, item):
        """Before spawning: take what the item needs (ports); raise SpaceError when it cannot."""

    def params(self, item):
        """The params the item runs with."""
        return item.params

    def extra_argv(self, item):
        """Words after the item's argv."""
        return []

    def environment(self, item, env):
        """The environment the item's process starts with (``env``: the space's)."""
        return env

    def started(self, host, space, item):
        """After the space's items started (the item runs): a Deferred or None."""

    def stopping(self, host, space, item):
        """When the space is torn down, before any item stops: a Deferred or None."""


class FirosItem(SpecialItem):
    """FIROS: one of the inbound open ports (``-P``); the space's ``inbound_port`` is that port."""

    name = "firos"
    announces_entities = True

    def prepare(self, host, space, item):
        item.inbound_port = host.take_inbound_port(space)
        space.inbound_port = item.inbound_port

    def extra_argv(self, item):
        return ["-P", str(item.inbound_port)]


class RcmDriverItem(SpecialItem):
    """rcm_driver: a free local ``port=N``, told ``r_connection`` once it runs and ``r_disconnection`` before
    the space stops, over a TCP connection kept open (``rcmp_inter_communication.DriverLink``). It gets a one-time
    key in its environment (``RCM_DRIVER_KEY``, never on its command line, which any local user can read), and
    obeys only connections whose first line carries it: no other local user can speak for the agent."""

    name = "rcm_driver"
    KEY_VARIABLE = "RCM_DRIVER_KEY"

    def prepare(self, host, space, item):
        item.driver_port = host.choose_driver_port()
        item.driver_key = secrets.token_hex(16)

    def environment(self, item, env):
        return dict(env, **{self.KEY_VARIABLE: item.driver_key})

    def params(self, item):
        kept = [p for p in split_params(item.params) if not p.startswith("port=")]
        return shlex.join(kept + [f"port={item.driver_port}"])

    def started(self, host, space, item):
        if item.process is not None and item.state == RUNNING:
            return host.connect_driver(space, item)
        return None

    def stopping(self, host, space, item):
        return host.say_goodbye_to_driver(space)


# Why an item failed, a closed set (counted by the master for /metrics, so it must stay small; "other" for a
# report without one, or with a word not in the set, from another agent):
ITEM_FAILURES = (
    "spawn",            # its process could not be started
    "exited",           # its process ended by itself (before or after it started)
    "not_registered",   # a launcher's nodes did not register with the space's ROS master in time
    "launch_file",      # roslaunch cannot load the launch file (missing package, file or arg)
    "params",           # its params do not split into words
    "port",             # no port for it (FIROS's inbound port, rcm_driver's local port)
    "space",            # its service space failed around it before it started (its ROS master, ...)
    "not_reported",     # the agent that should run it did not report it
    "other",
)


# (package, node type) -> hooks; only nodes (kind "node") are special
SPECIAL_ITEMS = {
    ("firos", "core.py"): FirosItem(),
    ("rcm", "rcm_driver.py"): RcmDriverItem(),
}


# ---------------------------------------------------------------------------------------------------------------
# What a service item is.

class ServiceItem:
    """One node or launcher of a service space, run here (``process``) or on the robot (``remote``).

    Built only from a validated entry (``from_entry``); ``special`` is the runtime's hooks for the nodes it
    treats specially (FIROS, rcm_driver: ``SPECIAL_ITEMS``), set once here, None for the others.
    """

    def __init__(self, kind, name, package, type_or_file, params, side, i_name):
        self.kind = kind
        self.name = name
        self.package = package
        self.type_or_file = type_or_file
        self.params = params or ""
        self.side = side
        self.i_name = i_name
        self.special = SPECIAL_ITEMS.get((package, type_or_file)) if kind == "node" else None
        self.process = None     # ManagedProcess, when run by this agent
        self.remote = None      # the robot's item report, when run there
        self.own_state = STARTING
        self.error = None       # set when the item failed before or without a process
        self.why_failed = None  # its ITEM_FAILURES word then
        self.nodes = []         # ROS node names (the node itself, or the launcher's nodes)
        self.node_types = {}    # launcher node name -> (package, type)
        self.driver_port = None
        self.driver_key = None
        self.inbound_port = None

    @classmethod
    def from_entry(cls, entry, i_name, index=0, list_field=None):
        """A ServiceItem from a service logic entry (``sn_*`` node or ``sl_*`` launcher fields; ``list_field``
        says which, else the name field does), validated by ``validate_service_item``; BadRequest says why."""
        list_field = list_field or item_list_field(entry)
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

    def spawn_argv(self, env, executables):
        """The argv its process starts with: ``argv`` with the params and words of its special hooks, and a node's
        ``rosrun PKG TYPE`` replaced by the file rosrun would run with ``env`` (``executables``, a
        ``NodeExecutables``). BadRequest when its params do not split (validation lets none through)."""
        special = self.special
        argv = self.argv(special.params(self), special.extra_argv(self)) if special else self.argv()
        if self.kind == "node":
            argv = executables.direct_argv(argv, env)
        return argv

    @property
    def state(self):
        if self.remote is not None:
            return self.remote.get("state", FAILED)
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

    def fail(self, error, failure="other"):
        """The item failed before or without a process: ``error`` says why, ``failure`` in one ITEM_FAILURES word."""
        self.error = error
        self.why_failed = failure if failure in ITEM_FAILURES else "other"
        self.own_state = FAILED

    @property
    def failure(self):
        """Why it failed, one word of ITEM_FAILURES; None while it has not failed."""
        if self.state != FAILED:
            return None
        if self.remote is not None:
            word = self.remote.get("failure")
            return word if isinstance(word, str) and word in ITEM_FAILURES else "other"
        if self.error is not None:
            return self.why_failed
        if self.process is not None:
            return "spawn" if self.process.pid is None else "exited"
        return "other"

    def report(self):
        """The item report of docs/DESIGN.md (what a robot returns to the master)."""
        if self.remote is not None:
            return dict(self.remote)
        return {"kind": self.kind, "name": self.name, "package": self.package,
                "type_or_file": self.type_or_file, "side": self.side, "i_name": self.i_name,
                "state": self.state, "error": self.current_error, "failure": self.failure,
                "nodes": list(self.nodes), "node_types": {n: list(t) for n, t in self.node_types.items()}}


def items_of_logic(service_logic, i_name=None):
    """The ServiceItems of a service logic dict (``sn_list`` nodes, then ``sl_list`` launchers); BadRequest
    names the first bad entry."""
    return [ServiceItem.from_entry(entry, i_name, index, list_field)
            for list_field, index, entry in logic_entries(service_logic)]


# ---------------------------------------------------------------------------------------------------------------
# The user items run as, and the workspace as their children see it.

class RunAsError(Exception):
    """The items' user cannot be used (no such user; another user while the agent is not root); ``str()`` is one
    line naming the configuration file and key."""


# catkin's variables: search paths naming packages (safe for root to read) and code-loading ones (safe only for
# a child running as the workspace's owner, or when the workspace is root's alone)
OVERLAY_SEARCH_KEYS = ("ROS_PACKAGE_PATH", "CMAKE_PREFIX_PATH", "ROSLISP_PACKAGE_DIRECTORIES")
OVERLAY_CODE_KEYS = ("PYTHONPATH", "LD_LIBRARY_PATH", "PKG_CONFIG_PATH", "PATH")
SYSTEM_PATH = "/usr/bin:/bin:/usr/sbin:/sbin"


@dataclasses.dataclass(frozen=True)
class RunAs:
    """The user service items run as (CONTRACTS §10 ``run_as``), with their own HOME and ROS_HOME.

    ``home`` is the user's home folder when it exists and is theirs; otherwise (``nobody``) a private folder
    made for them under the system's temp folder. ``ros_home`` is ``home/.ros`` (ROS logs go to its ``log``).
    """

    name: str
    uid: int
    gid: int
    home: str
    ros_home: str
    overlay: object = None   # the workspace overlay (``rcmp_node.WorkspaceOverlay``) when this user owns it

    @classmethod
    def for_user(cls, entry, overlay=None):
        """From a ``pwd`` entry; makes the fallback home (0700, theirs) when theirs is missing or not theirs.
        ``overlay``: the workspace this user owns, whose code paths their children may use."""
        home = entry.pw_dir
        try:
            usable = os.path.isdir(home) and os.stat(home).st_uid == entry.pw_uid
        except OSError:
            usable = False
        if not usable:
            home = cls._private_home(entry)
        return cls(entry.pw_name, entry.pw_uid, entry.pw_gid, home, os.path.join(home, ".ros"), overlay)

    @staticmethod
    def _private_home(entry):
        """``TMP/rcmp-home-NAME`` (0700, the user's), reused across starts when it is still a real folder of
        theirs that nobody else can enter; else a fresh ``mkdtemp`` (someone else made that name first)."""
        path = os.path.join(tempfile.gettempdir(), f"rcmp-home-{entry.pw_name}")
        try:
            os.mkdir(path, 0o700)
            os.chown(path, entry.pw_uid, entry.pw_gid)
            return path
        except FileExistsError:
            info = os.lstat(path)
            if stat.S_ISDIR(info.st_mode) and info.st_uid == entry.pw_uid and not info.st_mode & 0o077:
                return path
        path = tempfile.mkdtemp(prefix=f"rcmp-home-{entry.pw_name}-")
        os.chown(path, entry.pw_uid, entry.pw_gid)
        return path

    def setpriv_args(self):
        """``setpriv`` options that make a child this user, with their groups."""
        return [f"--reuid={self.uid}", f"--regid={self.gid}", "--init-groups"]

    def environment(self, env):
        """``env`` with this user's HOME, USER, LOGNAME, ROS_HOME and ROS_LOG_DIR (ROS_HOME/log), and the code
        paths of the workspace they own."""
        env = self.overlay.for_child(env, as_owner=True) if self.overlay is not None else dict(env)
        env.update(HOME=self.home, USER=self.name, LOGNAME=self.name, ROS_HOME=self.ros_home,
                   ROS_LOG_DIR=os.path.join(self.ros_home, "log"))
        return env


# What ``launcher_nodes_as`` runs in its child, as the run_as user: roslaunch's loader, as ``launcher_nodes`` uses
# it in the agent, answering JSON on stdout (exit 3 and the message on stderr for roslaunch's own errors).
LAUNCHER_NODES_PROGRAM = r"""
import json, sys
import roslaunch.config, roslaunch.core, roslaunch.rlutil
package, launch_file, args = sys.argv[1], sys.argv[2], sys.argv[3:]
try:
    resolved = roslaunch.rlutil.resolve_launch_arguments([package, launch_file] + args)
    config = roslaunch.config.load_config_default([(resolved[0], [resolved[0]] + args)], None, verbose=False,
                                                  assign_machines=False)
except roslaunch.core.RLException as exc:
    sys.stderr.write(str(exc))
    sys.exit(3)
json.dump([[((n.namespace or "/") + n.name).lstrip("/"), n.package, n.type] for n in config.nodes], sys.stdout)
"""


def launcher_nodes_as(user, env, package, launch_file, params="", timeout=30.0):
    """``launcher_nodes`` read in a child process running as ``user`` (a ``RunAs``), so that what a launch file
    runs while it is loaded (``<param command=...>``, ``$(eval ...)``) never runs as the agent's root.

    Blocking: call it in a thread. Raises RuntimeError with roslaunch's message (or why the child failed).
    """
    import subprocess
    argv = [*nice_prefix(), SETPRIV, *user.setpriv_args(), "--pdeathsig", "KILL", "--", "/usr/bin/python3", "-c",
            LAUNCHER_NODES_PROGRAM, package, launch_file, *split_params(params or "")]
    child = subprocess.Popen(argv, env=user.environment(env), cwd=user.home, stdin=subprocess.DEVNULL,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
    try:
        out, err = child.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(child.pid, signal.SIGKILL)
        child.communicate()
        raise RuntimeError(f"reading the launch file as {user.name} took more than {timeout:g} s") from None
    message = err.decode("utf-8", "replace").strip()
    if child.returncode == 3:
        raise RuntimeError(message.splitlines()[-1] if message else "roslaunch refused the launch file")
    if child.returncode != 0:
        last = message.splitlines()[-1] if message else f"exit status {child.returncode}"
        raise RuntimeError(f"reading the launch file as {user.name} failed: {last}")
    try:
        return [tuple(entry) for entry in json.loads(out)]
    except ValueError:
        raise RuntimeError(f"reading the launch file as {user.name} gave no node list") from None


def root_only(path):
    """True when ``path`` and every folder above it are root's and not writable by group or others (a sticky
    folder such as /tmp excepted): nobody but root can change what is there."""
    path = os.path.abspath(path)
    while True:
        try:
            st = os.lstat(path)
        except OSError:
            return False
        if st.st_uid != 0:
            return False
        if stat.S_ISLNK(st.st_mode):
            if not root_only(os.path.realpath(path)):
                return False
        elif st.st_mode & 0o022 and not (stat.S_ISDIR(st.st_mode) and st.st_mode & stat.S_ISVTX):
            return False
        parent = os.path.dirname(path)
        if parent == path:
            return True
        path = parent


def _system_path_first(env_path, first=(), last=()):
    """A PATH with the system's folders first (the PATH trap: another ``python3`` before ``/usr/bin`` breaks
    ROS's scripts), then ``first``, then the other folders of ``env_path``, then ``last``; each folder once."""
    system = SYSTEM_PATH.split(":")
    folders = []
    for p in system + list(first) + env_path.split(":") + list(last):
        if p and p not in folders:
            folders.append(p)
    return ":".join(folders)


# what sources a setup script: no profile, no rc file, no arguments for it (a sourced catkin setup.bash hands its
# caller's to _setup_util.py), its path an argument of bash (never part of the program), its output discarded
SOURCE_PROGRAM = 'script=$1; set --; . "$script" >/dev/null 2>&1 || exit 3; exec env -0'


def _sourced_environment(script, home, user=None, timeout=30.0):
    """The environment ``script`` leaves when bash sources it in an empty one (PATH=SYSTEM_PATH, HOME, LC_ALL=C),
    as ``user`` ((uid, gid, setpriv group option)) when given, else as ourselves. OSError when it fails."""
    argv = ["/bin/bash", "--noprofile", "--norc", "-c", SOURCE_PROGRAM, "rcmp_n-source", script]
    if user is not None:
        uid, gid, groups = user
        argv = [SETPRIV, f"--reuid={uid}", f"--regid={gid}", groups, "--", *argv]
    result = subprocess.run(argv, env={"PATH": SYSTEM_PATH, "HOME": home, "LC_ALL": "C"}, cwd="/",
                            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                            timeout=timeout, check=False)
    if result.returncode != 0:
        raise OSError(f"{script} failed (exit status {result.returncode})")
    found = dict(item.decode("utf-8", "replace").split("=", 1)
                 for item in result.stdout.split(b"\0") if b"=" in item)
    if "PATH" not in found:   # it ran 'exit 0': the shell that sourced it ended before printing anything
        raise OSError(f"{script} ended the shell that sourced it (a setup script must not exit)")
    return found


@dataclasses.dataclass(frozen=True)
class WorkspaceOverlay:
    """A catkin workspace's environment, obtained by running its ``devel/setup.bash`` as the workspace's owner."""
    workspace: str
    owner_uid: int
    owner_gid: int
    trusted: bool      # the workspace is root's alone: its code may run as root
    search: dict       # OVERLAY_SEARCH_KEYS found
    code: dict         # OVERLAY_CODE_KEYS found

    def for_child(self, env, as_owner=False):
        """``env`` plus this overlay: the search paths always, the code paths only for a child running as the
        workspace's owner (``as_owner``) or when the workspace is trusted. System folders stay first on PATH."""
        env = dict(env)
        env.update(self.search)
        if as_owner or self.trusted:
            for key, value in self.code.items():
                if key == "PATH":
                    env["PATH"] = _system_path_first(env.get("PATH", ""), last=value.split(":"))
                else:
                    env[key] = value
        return env


_overlays = {}


def workspace_overlay(workspace, timeout=30.0):
    """The overlay of ``workspace`` (``None`` without ``devel/setup.bash``), computed once per path.

    The script runs in an empty environment as the owner of the workspace folder (``setpriv`` when we are root
    and the owner is not), never as root for somebody else's files. Raises ``OSError`` when it cannot be run.
    """
    workspace = os.path.abspath(workspace)
    if workspace in _overlays:
        return _overlays[workspace]
    setup = os.path.join(workspace, "devel", "setup.bash")
    if not os.path.isfile(setup):
        return None
    st = os.stat(workspace)
    try:
        user = pwd.getpwuid(st.st_uid)
        home, groups = user.pw_dir, "--init-groups"
    except KeyError:
        home, groups = "/", "--clear-groups"
    as_owner = (st.st_uid, st.st_gid, groups) if os.geteuid() == 0 and st.st_uid != 0 else None
    found = _sourced_environment(setup, home, as_owner, timeout)
    overlay = WorkspaceOverlay(
        workspace, st.st_uid, st.st_gid, root_only(workspace) and st.st_uid == 0,
        {k: found[k] for k in OVERLAY_SEARCH_KEYS if found.get(k)},
        {k: found[k] for k in OVERLAY_CODE_KEYS if found.get(k)})
    _overlays[workspace] = overlay
    return overlay


def apply_workspace(environ):
    """With ``RCMP_WS`` set (rcmpd sets it), put the workspace's overlay into ``environ`` as ``for_child`` says
    for a root child; returns the overlay or None. Problems are logged, never fatal."""
    workspace = environ.get("RCMP_WS")
    if not workspace:
        return None
    try:
        overlay = workspace_overlay(workspace)
    except (OSError, subprocess.SubprocessError) as exc:
        log.warning("workspace %s: no overlay: %s", workspace, exc)
        return None
    if overlay is None:
        log.warning("workspace %s has no devel/setup.bash: items find only the system's packages", workspace)
        return None
    environ.update(overlay.for_child(environ))
    log.info("workspace %s (owner uid %d): %s", workspace, overlay.owner_uid,
             "root's alone: its code may run as root" if overlay.trusted
             else "not root's: its packages are found, its code runs only as its owner")
    return overlay


# -- the ROS installation under it ---------------------------------------------------------------------------------

class RosSetupError(Exception):
    """The ROS installation's setup script cannot be used; ``str()`` is one line naming the configuration file,
    the key and the problem."""


# what the agent keeps of a ROS setup script's environment: the additions to PATH, these path lists and ROS's own
# variables, but never a ROS master or an address to advertise (each service space sets those for its children)
ROS_PATH_KEYS = ("PYTHONPATH", "LD_LIBRARY_PATH", "PKG_CONFIG_PATH", "CMAKE_PREFIX_PATH", "ROS_PACKAGE_PATH",
                 "ROSLISP_PACKAGE_DIRECTORIES")
ROS_DROPPED_KEYS = ("ROS_MASTER_URI", "ROS_IP", "ROS_HOSTNAME")


def ros_variables(found):
    """What the agent keeps of ``found``, the environment a ROS setup script left (sourced with
    PATH=SYSTEM_PATH): ``PATH`` as the folders it added, the lists of ``ROS_PATH_KEYS`` and every other
    ``ROS_*`` variable but ``ROS_DROPPED_KEYS``; empty values left out."""
    kept = {}
    added = [p for p in found.get("PATH", "").split(":") if p and p not in SYSTEM_PATH.split(":")]
    if added:
        kept["PATH"] = ":".join(added)
    for key, value in found.items():
        if value and (key in ROS_PATH_KEYS or (key.startswith("ROS_") and key not in ROS_DROPPED_KEYS)):
            kept[key] = value
    return kept


@dataclasses.dataclass(frozen=True)
class RosEnvironment:
    """The environment of a ROS installation's setup script (``ros_environment``), as ``ros_variables`` keeps
    it; ``for_child`` puts it under an environment, the workspace overlay then goes on top."""
    setup: str
    variables: dict

    def for_child(self, env):
        """``env`` as sourcing the script in it would leave it: each path list with this ROS's entries first and
        the ones already there after them; PATH with the system's folders first, then this ROS's; the other
        variables set."""
        env = dict(env)
        for key, value in self.variables.items():
            if key == "PATH":
                env["PATH"] = _system_path_first(env.get("PATH", ""), first=value.split(":"))
            elif key in ROS_PATH_KEYS:
                ours = [p for p in value.split(":") if p]
                env[key] = ":".join(ours + [p for p in env.get(key, "").split(":") if p and p not in ours])
            else:
                env[key] = value
        return env

    @property
    def python_path(self):
        """The folders of its PYTHONPATH (ROS's Python packages), in order."""
        return [p for p in self.variables.get("PYTHONPATH", "").split(":") if p]


_ros_environments = {}


def ros_environment(setup, timeout=30.0):
    """The ``RosEnvironment`` of the setup script ``setup``, computed once per path: sourced by bash in an empty
    environment as the agent's own user (``_sourced_environment``). OSError when it fails."""
    if setup not in _ros_environments:
        home = os.environ.get("HOME") or pwd.getpwuid(os.geteuid()).pw_dir
        _ros_environments[setup] = RosEnvironment(setup, ros_variables(_sourced_environment(setup, home,
                                                                                            timeout=timeout)))
    return _ros_environments[setup]


def _config_file_of(config):
    """The configuration file a message about ``config`` names (the one the role reads, also when absent)."""
    return config.config_file or os.path.join(config.home, "init.cfg" if config.role != "master" else ".init.cfg")


def apply_ros_environment(config, environ, path=None, search_root=ROS_ROOT):
    """Put the ROS installation (``rcmp_config.ros_setup_script``) under ``environ`` (``RosEnvironment.for_child``)
    and its Python packages into ``path`` (``sys.path``, where PYTHONPATH would have put them), so that the
    agent's own ROS lookups and every child use that ROS. Called once at start, before the workspace overlay and
    before any ROS module is imported. Returns the RosEnvironment, or None when ROS is on the system's paths
    (nothing changes). RosSetupError (one line) when the script is not a readable file, when a root agent's
    script could be changed by somebody else than root (``root_only``), or when it fails."""
    setup, how = ros_setup_script(config, search_root)
    if setup is None:
        log.debug("ROS on the system's paths (no setup script: %s)", how)   # nothing changes, nothing said
        return None
    key = "key 'ros_setup'" if how == "ros_setup" else f"key 'ros_setup' (not set; {setup} {how})"
    where = f"{_config_file_of(config)}: {key}"
    if not os.path.isfile(setup) or not os.access(setup, os.R_OK):
        raise RosSetupError(f"{where}: {setup} is not a readable file")
    if os.geteuid() == 0 and not root_only(setup):
        raise RosSetupError(f"{where}: {setup} or a folder above it is not root's alone (another owner, or "
                            f"writable by group or others): the root agent runs no setup script that somebody "
                            f"else can change")
    try:
        ros = ros_environment(setup)
    except (OSError, subprocess.SubprocessError) as exc:
        raise RosSetupError(f"{where}: {exc}") from None
    environ.update(ros.for_child(environ))
    path = sys.path if path is None else path
    missing = [p for p in ros.python_path if p not in path]
    path[min(1, len(path)):min(1, len(path))] = missing
    importlib.invalidate_caches()
    log.info("ROS from %s (%s): ROS_DISTRO=%s, %s", setup, how, ros.variables.get("ROS_DISTRO", "not set"),
             ", ".join(f"{k}={ros.variables[k]}" for k in ("PATH", "PYTHONPATH") if k in ros.variables)
             or "no PATH or PYTHONPATH of its own")
    return ros


# -- the user service items run as ---------------------------------------------------------------------------------

def default_workspace(environ=None):
    """The ROS workspace the installer made: ``$RCMP_WS`` (``rcmpd`` passes it), else ``~/rcmp_ws``."""
    environ = os.environ if environ is None else environ
    return environ.get("RCMP_WS") or os.path.join(environ.get("HOME") or os.path.expanduser("~"), "rcmp_ws")


def resolve_run_as(config, environ=None):
    """The ``RunAs`` service items run as, or None when they run as the agent's own user.

    ``run_as`` if set, else the owner of the workspace (``default_workspace``). The agent must be root to run
    them as anyone else; without ``run_as`` and without a workspace (a platform not installed, run by hand) the
    items run as the agent's own user, and a root agent says so in the log. RunAsError (one line) for a user
    that does not exist, or a non-root agent asked to run items as another user.
    """
    where = _config_file_of(config)
    euid = os.geteuid()
    name = config.run_as
    if name is None:
        workspace = default_workspace(environ)
        try:
            owner = os.stat(workspace).st_uid
        except OSError:
            if euid == 0:
                log.warning("service items run as root: no run_as in %s and no ROS workspace at %s to take its "
                            "owner from (set run_as=USER; docs/SECURITY.md)", where, workspace)
            return None
        try:
            name = pwd.getpwuid(owner).pw_name
        except KeyError:
            raise RunAsError(f"{workspace}: owned by uid {owner}, which is no user of this machine: set run_as "
                             f"in {where}") from None
        how = f"the owner of {workspace}"
    else:
        how = f"run_as in {where}"
    try:
        entry = pwd.getpwnam(name)
    except KeyError:
        raise RunAsError(f"{where}: key 'run_as': there is no user {name!r} on this machine") from None
    if entry.pw_uid == euid:
        if euid == 0:
            log.info("service items run as root (%s)", how)
        return None
    if euid != 0:
        raise RunAsError(f"{where}: key 'run_as': the agent runs as uid {euid}, not root, so it cannot run "
                         f"service items as {name!r}: remove run_as or start the agent as root")
    overlay = None
    if (environ if environ is not None else os.environ).get("RCMP_WS"):
        try:
            overlay = workspace_overlay(default_workspace(environ))
        except (OSError, subprocess.SubprocessError):
            overlay = None   # apply_workspace has said why
    # the workspace's code paths (PYTHONPATH, ...) are safe for children running as its owner only
    run_as = RunAs.for_user(entry, overlay if overlay is not None and overlay.owner_uid == entry.pw_uid else None)
    log.info("service items run as %s (uid %d, %s), HOME %s%s", name, entry.pw_uid, how, run_as.home,
             ", with its workspace's code paths" if run_as.overlay is not None else "")
    return run_as
