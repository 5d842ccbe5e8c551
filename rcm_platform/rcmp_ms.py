"""Managed services: the process table and the service-space runtime of an agent.

This module owns every child process an agent starts and the service spaces built from them:

* ``ProcessTable`` / ``ManagedProcess``: one table per agent. Each child has one state from a closed set
  (``starting``, ``running``, ``stopping``, ``exited``, ``failed``) and changes state only through
  ``ManagedProcess._transition``, which checks the allowed source states and logs ``old -> new``. A child is
  ``running`` once its owner has proof that it started (``confirm_running``: a ROS node registered with its
  master, a master answered) or, failing that, after staying up ``settle_time`` seconds; only the reaping
  path (``processExited``) marks a child ``exited`` (we stopped it) or ``failed`` (it ended unasked).
* Children never run through a shell. Each runs in its own session and process group: Twisted's
  ``spawnProcess`` has no ``setsid``, so argv is prefixed with ``/usr/bin/setsid`` (util-linux; the forked
  child is not a group leader, so setsid calls setsid(2) and execs in place: same pid, and that pid is the
  process group id) and ``/usr/bin/setpriv --pdeathsig TERM`` (the child gets SIGTERM if the agent dies,
  even by SIGKILL, so a killed agent leaves nothing running). Both exec directly.
* Stopping follows roslaunch: SIGINT to the group, wait (default 5 s), SIGTERM, wait 2 s, SIGKILL. The
  descendants of the child are remembered when the stop begins (roslaunch puts each node in a session of
  its own, so they are not in the launcher's group) and get the SIGTERM and SIGKILL too. "No such process"
  means the process is already going. A stop's Deferred fires when the child is reaped and no process of
  its group or of its remembered descendants is left. ``stop_all`` stops ordinary children first and the
  ROS masters (``core=True``) last.
* Each child's stdout and stderr go to its own size-capped log file under the log directory (one rotated
  backup); ``tail(lines)`` gives the last lines of output, which become ``error`` when a child fails.
* All OS effects (spawn, signals, /proc reads) go through ``OsFacade`` so unit tests can record them.

On top of the table, the service-space runtime (see docs/SERVICE_SPACES.md):

* ``ServiceSpaceManager`` (master or server side): per connected robot a ``ServiceSpace``: a ROS master
  (``rosmaster --core`` plus ``rosout``, measured leaner and faster than ``roscore``) on a free port from
  ``config.ros_port_base`` upward, the S-side items, and the R-side items through a ``RemoteRobot``, all
  spawned at once (rospy nodes and ``roslaunch --wait`` wait for their master); ``paired`` when the ROS
  master answers and every item has started: its node(s) registered with the space's master (a launcher:
  every node it launches), or, for a node that never registers under its name, it stayed up for the settle
  time. rosout is watched but not waited for (it only collects logs). FIROS items get one of the inbound open
  ports (``-P``); rcm_driver items get a free local ``port=N`` and are told ``r_connection`` /
  ``r_disconnection`` over a TCP connection kept open. ``describe`` renders ``service_space/read``.
* ``RobotSideRunner`` (robot side): starts and stops the R-side items (and the ROS master when the service
  logic's ``ss_side`` is ``R``) for the master, and reports items that die later.
* ``RemoteRobot``: the protocol the master's agent layer implements over the network, one per robot.
"""

import collections
import json
import logging
import os
import re
import shlex
import signal
import socket
import time
import uuid
from typing import Protocol

from twisted.internet import defer, error as ierror, protocol, task, threads
from twisted.internet.endpoints import TCP4ClientEndpoint, connectProtocol
from twisted.protocols.basic import LineReceiver
from twisted.web import xmlrpc

xmlrpc.QueryFactory.noisy = False  # one "Starting factory" log line per XML-RPC call to a ROS master is noise

log = logging.getLogger(__name__)

# ---------------------------------------------------------------------------------------------------------
# Process states: a closed set, and the only transitions allowed between them (target -> allowed sources).

STARTING = "starting"
RUNNING = "running"
STOPPING = "stopping"
EXITED = "exited"
FAILED = "failed"

STATES = frozenset({STARTING, RUNNING, STOPPING, EXITED, FAILED})
LIVE_STATES = frozenset({STARTING, RUNNING, STOPPING})
DONE_STATES = frozenset({EXITED, FAILED})

_ALLOWED_SOURCES = {
    RUNNING: frozenset({STARTING}),            # proved it started (registered), or stayed up for the settle time
    STOPPING: frozenset({STARTING, RUNNING}),  # we asked it to stop
    EXITED: frozenset({STOPPING}),             # reaped after we asked (and its group is gone)
    FAILED: frozenset({STARTING, RUNNING}),    # reaped without being asked, or could not be spawned
}

SETSID = "/usr/bin/setsid"
SETPRIV = "/usr/bin/setpriv"
ROS_PATH_PREFIX = ["/usr/bin", "/bin", "/usr/sbin", "/sbin"]
_ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]|\x1b\][^\x07\x1b]*(?:\x07|\x1b\\)?")  # colours, terminal titles


class InvalidTransition(RuntimeError):
    """A state change that the closed state machine does not allow (a bug in the caller)."""


# ---------------------------------------------------------------------------------------------------------
# OS effects, behind one facade.

class OsFacade:
    """Every OS effect of the process table: spawn, signals, and reading /proc. Tests replace it."""

    def __init__(self, reactor):
        self.reactor = reactor
        self._devnull = None

    def spawn(self, process_protocol, argv, env, cwd=None):
        """Start ``argv`` in a new session (setsid) with SIGTERM on agent death; returns the pid."""
        if self._devnull is None:
            self._devnull = os.open(os.devnull, os.O_RDONLY)
        full = [SETSID, SETPRIV, "--pdeathsig", "TERM", "--"] + list(argv)
        transport = self.reactor.spawnProcess(process_protocol, full[0], full, env=env, path=cwd,
                                              childFDs={0: self._devnull, 1: "r", 2: "r"})
        return transport.pid

    def signal_group(self, pgid, sig):
        """Send ``sig`` to process group ``pgid``; False when no such group exists (it is already going)."""
        try:
            os.killpg(pgid, sig)
            return True
        except ProcessLookupError:
            return False

    def signal_child(self, pid, sig):
        """Send ``sig`` to our own not yet reaped child ``pid`` (its pid cannot have been reused)."""
        try:
            os.kill(pid, sig)
            return True
        except ProcessLookupError:
            return False

    def signal_process(self, pid, start_time, sig):
        """Send ``sig`` to ``pid`` if it is still the process that started at ``start_time``."""
        if not self.process_alive(pid, start_time):
            return False
        try:
            os.kill(pid, sig)
            return True
        except ProcessLookupError:
            return False

    def group_alive(self, pgid):
        """True while any process of group ``pgid`` exists that is not a zombie."""
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return False
        except PermissionError:
            return True
        return any(info[2] == pgid and info[0] != "Z" for info in _proc_table().values())

    def process_alive(self, pid, start_time):
        info = _proc_stat(pid)
        return info is not None and info[0] != "Z" and info[3] == start_time

    def is_group_leader(self, pid):
        info = _proc_stat(pid)
        return info is not None and info[2] == pid

    def descendants(self, pid):
        """{pid: start_time} of every living descendant of ``pid`` (children, grandchildren, ...)."""
        table = _proc_table()
        children = collections.defaultdict(list)
        for child, info in table.items():
            children[info[1]].append(child)
        found, pending = {}, [pid]
        while pending:
            for child in children.get(pending.pop(), ()):
                if child not in found and table[child][0] != "Z":
                    found[child] = table[child][3]
                    pending.append(child)
        return found


def _parse_stat(text):
    """(state, ppid, pgrp, start_time) from the text of /proc/PID/stat."""
    fields = text.rsplit(")", 1)[1].split()
    return fields[0], int(fields[1]), int(fields[2]), int(fields[19])


def _proc_stat(pid):
    try:
        with open(f"/proc/{pid}/stat") as f:
            return _parse_stat(f.read())
    except (OSError, IndexError, ValueError):
        return None


def _proc_table():
    table = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            info = _proc_stat(int(entry))
            if info is not None:
                table[int(entry)] = info
    return table


# ---------------------------------------------------------------------------------------------------------
# Per-child log files.

class CappedLog:
    """An append-only log file that rotates to ``PATH.1`` when it would grow past ``max_bytes``."""

    def __init__(self, path, max_bytes):
        self.path = path
        self.max_bytes = max_bytes
        self._file = open(path, "ab")
        self._size = self._file.tell()

    def write(self, data):
        if self._file is None:
            return
        if self._size + len(data) > self.max_bytes and self._size > 0:
            self._file.close()
            os.replace(self.path, self.path + ".1")
            self._file = open(self.path, "ab")
            self._size = 0
        self._file.write(data)
        self._file.flush()
        self._size += len(data)

    def close(self):
        if self._file is not None:
            self._file.close()
            self._file = None


class _ChildProtocol(protocol.ProcessProtocol):
    """Forwards a child's output and end to its ManagedProcess."""

    def __init__(self, managed):
        self.managed = managed

    def outReceived(self, data):
        self.managed._output(data)

    errReceived = outReceived

    def processExited(self, reason):
        # reaped. Not processEnded: that waits for every holder of the output pipes, and a grandchild
        # (a roslaunch node, a daemonised helper) may hold them long after the child itself is gone.
        self.managed._reaped(reason)

    def processEnded(self, reason):
        self.managed._pipes_closed()


class ManagedProcess:
    """One child of the table: its argv, pid (= its process group id), state, log and error."""

    TAIL_KEEP = 200  # lines of recent output kept in memory for tail()

    def __init__(self, table, key, argv, env, log_path, core=False):
        self.table = table
        self.key = key
        self.argv = list(argv)
        self.env = env
        self.log_path = log_path
        self.core = core
        self.pid = None
        self.state = STARTING
        self.error = None
        self.exit_code = None
        self.exit_signal = None
        self.started_at = None
        self.listeners = []          # fn(managed, old_state, new_state) after each transition
        self._lines = collections.deque(maxlen=self.TAIL_KEEP)
        self._partial = b""
        self._log = None
        self._settle_call = None
        self._settled_waiters = []
        self._gone_waiters = []
        self._descendants = {}
        self._reaped_yet = False
        self._escalation = None
        self._poll = None
        self._kill_deadline = None

    def __repr__(self):
        return f"<ManagedProcess {self.key} pid={self.pid} {self.state}>"

    # -- state machine ------------------------------------------------------------------------------------
    def _transition(self, new, why):
        if new not in STATES:
            raise InvalidTransition(f"{self.key}: unknown state {new!r}")
        old = self.state
        if old not in _ALLOWED_SOURCES[new]:
            raise InvalidTransition(f"{self.key}: {old} -> {new} is not allowed")
        self.state = new
        level = logging.WARNING if new == FAILED else logging.INFO
        log.log(level, "process %s (pid %s): %s -> %s (%s)", self.key, self.pid, old, new, why)
        for listener in list(self.listeners):
            try:
                listener(self, old, new)
            except Exception:
                log.exception("state listener of %s failed", self.key)
        if new != STARTING and self._settled_waiters:
            waiters, self._settled_waiters = self._settled_waiters, []
            for d in waiters:
                d.callback(new == RUNNING)

    # -- output -------------------------------------------------------------------------------------------
    def _output(self, data):
        if self._log is not None:
            self._log.write(data)
        text = self._partial + data
        *complete, self._partial = text.split(b"\n")
        for line in complete:
            self._lines.append(_ANSI.sub("", line.decode("utf-8", "replace")).rstrip("\r"))
        if len(self._partial) > 4096:
            self._lines.append(_ANSI.sub("", self._partial.decode("utf-8", "replace")))
            self._partial = b""

    def tail(self, lines=10):
        """The last ``lines`` lines the child wrote (stdout and stderr interleaved), as one string."""
        recent = list(self._lines)
        if self._partial:
            recent.append(_ANSI.sub("", self._partial.decode("utf-8", "replace")))
        return "\n".join(recent[-lines:]) if lines > 0 else ""

    def useful_output(self, lines=5):
        """The last non-empty lines of output: what a user needs to see why the child ended."""
        recent = [line.strip() for line in list(self._lines) + [self._partial.decode("utf-8", "replace")]]
        return "\n".join([line for line in recent if line][-lines:])

    # -- lifecycle ----------------------------------------------------------------------------------------
    def _start(self):
        table = self.table
        self._log = CappedLog(self.log_path, table.log_max_bytes)
        self._log.write(f"=== {time.strftime('%Y-%m-%d %H:%M:%S')} start: {shlex.join(self.argv)}\n".encode())
        try:
            self.pid = table.os.spawn(_ChildProtocol(self), self.argv, self.env)
        except (OSError, ValueError, TypeError) as exc:
            self.error = f"could not start {self.argv[0]}: {exc}"
            self._log.close()
            self._transition(FAILED, self.error)
            return
        self.started_at = table.reactor.seconds()
        log.info("process %s started: pid %s, argv %s, log %s", self.key, self.pid, self.argv, self.log_path)
        self._settle_call = table.reactor.callLater(table.settle_time, self._settled)

    def remember_descendants(self):
        """Note the child's current descendants, so that they are stopped with it even if it dies first
        (roslaunch's nodes live in sessions of their own and outlive a crashed roslaunch otherwise)."""
        if self.pid is not None and not self._reaped_yet:
            self._descendants.update(self.table.os.descendants(self.pid))

    def _settled(self):
        self._settle_call = None
        self.remember_descendants()
        if self.state == STARTING:
            self._transition(RUNNING, f"up for {self.table.settle_time:g} s")

    def confirm_running(self, why):
        """The caller has proof that the child started (a ROS node registered, a master answered): it is
        running now, without waiting out the settle time. No effect unless it is still starting."""
        if self.state != STARTING:
            return
        if self._settle_call is not None and self._settle_call.active():
            self._settle_call.cancel()
        self._settle_call = None
        self.remember_descendants()
        self._transition(RUNNING, why)

    def when_settled(self):
        """Deferred(bool): True once the child is running, False if it failed or was stopped before."""
        if self.state == STARTING:
            d = defer.Deferred()
            self._settled_waiters.append(d)
            return d
        return defer.succeed(self.state == RUNNING)

    def _reaped(self, reason):
        """The reaping path: the only place where a child becomes exited or failed."""
        value = reason.value
        self.exit_code = getattr(value, "exitCode", None)
        self.exit_signal = getattr(value, "signal", None)
        self._reaped_yet = True
        if self._settle_call is not None and self._settle_call.active():
            self._settle_call.cancel()
        self._settle_call = None
        if self._log is not None:
            self._log.write(f"=== {time.strftime('%Y-%m-%d %H:%M:%S')} ended: {self._how_ended()}\n".encode())
        if self.state == STOPPING:
            self._check_gone()
            return
        uptime = self.table.reactor.seconds() - (self.started_at or 0)
        when = "before it settled" if self.state == STARTING else f"after running {uptime:.1f} s"
        output = self.useful_output()
        self.error = f"{self._how_ended()} {when}" + (f": {output}" if output else " (no output)")
        self._transition(FAILED, self.error)
        if self._leftovers_alive():  # the leader died: leave none of its group or descendants behind
            self._sweep_leftovers()

    def _pipes_closed(self):
        """No process holds the child's output pipes any more: flush the last partial line, close the log."""
        if self._partial:
            self._output(b"\n")
        if self._log is not None:
            self._log.close()
            self._log = None

    def _how_ended(self):
        if self.exit_signal is not None:
            return f"killed by signal {self.exit_signal}"
        return f"exited with status {self.exit_code}"

    def stop(self):
        """Stop the child and its group; the Deferred fires when no process of it is left."""
        d = defer.Deferred()
        if self.state in (STARTING, RUNNING):
            self._gone_waiters.append(d)
            self.remember_descendants()
            self._transition(STOPPING, "stop requested")
            self._signal(signal.SIGINT)
            self._escalation = self.table.reactor.callLater(self.table.stop_timeouts[0], self._escalate,
                                                            signal.SIGTERM)
            self._start_polling()
        elif self.state == STOPPING:
            self._gone_waiters.append(d)
        elif self._poll is not None:      # already sweeping the leftovers of a failed child
            self._gone_waiters.append(d)
            self._check_gone()
        elif self._leftovers_alive():
            self._gone_waiters.append(d)
            self._sweep_leftovers()
        else:
            d.callback(None)
        return d

    def _signal(self, sig):
        """Signal our group; from SIGTERM on also every remembered descendant (and its own group)."""
        os_ = self.table.os
        if not os_.signal_group(self.pid, sig):
            if not self._reaped_yet:  # forked but setsid has not run yet: our unreaped child, signal it alone
                os_.signal_child(self.pid, sig)
            else:
                log.debug("process %s: group %s already gone (%s)", self.key, self.pid, sig)
        if sig == signal.SIGINT:
            return
        for pid, start_time in self._descendants.items():
            signalled = os_.signal_process(pid, start_time, sig)
            if signalled and sig == signal.SIGKILL and os_.is_group_leader(pid):
                os_.signal_group(pid, sig)  # a descendant with a session of its own (a roslaunch node)

    def _escalate(self, sig):
        self._escalation = None
        self.remember_descendants()
        if not self._leftovers_alive():
            self._check_gone()
            return
        log.warning("process %s did not stop in time: sending %s", self.key, signal.Signals(sig).name)
        self._signal(sig)
        if sig == signal.SIGTERM:
            self._escalation = self.table.reactor.callLater(self.table.stop_timeouts[1], self._escalate,
                                                            signal.SIGKILL)
        else:
            self._kill_deadline = self.table.reactor.seconds() + self.table.kill_timeout

    def _leftovers_alive(self):
        os_ = self.table.os
        if self.pid is None:
            return False
        if not self._reaped_yet or os_.group_alive(self.pid):
            return True
        return any(os_.process_alive(pid, st) for pid, st in self._descendants.items())

    def _start_polling(self):
        if self._poll is None:
            self._poll = task.LoopingCall(self._check_gone)
            self._poll.clock = self.table.reactor
            self._poll.start(self.table.poll_interval, now=False)

    def _sweep_leftovers(self):
        """A reaped child whose group lives on: SIGTERM the rest now, SIGKILL after the second timeout."""
        self._signal(signal.SIGTERM)
        self._escalation = self.table.reactor.callLater(self.table.stop_timeouts[1], self._escalate,
                                                        signal.SIGKILL)
        self._start_polling()

    def _check_gone(self):
        if self._leftovers_alive():
            if self._kill_deadline is None or self.table.reactor.seconds() <= self._kill_deadline:
                return
            log.error("process %s: processes of group %s survive SIGKILL for %g s; giving up on them",
                      self.key, self.pid, self.table.kill_timeout)
        if self._poll is not None and self._poll.running:
            self._poll.stop()
        self._poll = None
        if self._escalation is not None and self._escalation.active():
            self._escalation.cancel()
        self._escalation = None
        if self.state == STOPPING and self._reaped_yet:
            self._transition(EXITED, self._how_ended())
        waiters, self._gone_waiters = self._gone_waiters, []
        for d in waiters:
            d.callback(None)


class ProcessTable:
    """The table of an agent's child processes, keyed by name. See the module docstring."""

    def __init__(self, reactor, log_dir, settle_time=1.0, stop_timeouts=(5.0, 2.0), os_facade=None,
                 log_max_bytes=1 << 20, poll_interval=0.1, kill_timeout=5.0):
        self.reactor = reactor
        self.log_dir = str(log_dir)
        self.settle_time = settle_time
        self.stop_timeouts = tuple(stop_timeouts)
        self.os = os_facade or OsFacade(reactor)
        self.log_max_bytes = log_max_bytes
        self.poll_interval = poll_interval
        self.kill_timeout = kill_timeout
        self._procs = {}
        os.makedirs(self.log_dir, exist_ok=True)

    def spawn(self, key, argv, env, log_name, core=False):
        """Start ``argv`` (a list; never a shell) as child ``key``; ``core`` marks a ROS master (stopped last).

        Returns the ManagedProcess at once, in state ``starting`` (or ``failed`` if it could not be spawned).
        """
        if not isinstance(argv, (list, tuple)) or not argv or not all(isinstance(a, str) for a in argv):
            raise TypeError(f"argv of {key} must be a non-empty list of strings, got {argv!r}")
        current = self._procs.get(key)
        if current is not None and (current.state in LIVE_STATES or current._gone_waiters):
            raise ValueError(f"a process named {key} is already {current.state}")
        safe = re.sub(r"[^A-Za-z0-9_.-]", "_", log_name) or "process"
        managed = ManagedProcess(self, key, argv, env, os.path.join(self.log_dir, safe + ".log"), core=core)
        self._procs[key] = managed
        managed._start()
        return managed

    def get(self, key):
        return self._procs.get(key)

    def processes(self):
        return list(self._procs.values())

    def stop(self, key):
        """Stop child ``key`` (escalating SIGINT, SIGTERM, SIGKILL); fires when it and its group are gone."""
        managed = self._procs.get(key)
        if managed is None:
            return defer.succeed(None)
        return managed.stop()

    def forget(self, key):
        """Drop a finished child from the table (its log file stays)."""
        managed = self._procs.get(key)
        if managed is not None and managed.state in DONE_STATES and not managed._gone_waiters:
            del self._procs[key]

    @defer.inlineCallbacks
    def stop_all(self):
        """Stop every child: ordinary ones first (together), then the ROS masters."""
        for core in (False, True):
            batch = [m for m in list(self._procs.values()) if m.core == core]
            yield defer.gatherResults([m.stop() for m in batch], consumeErrors=True)


# ---------------------------------------------------------------------------------------------------------
# Service items: argv, environment, launcher node lists.

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
    return ["rosrun", package, node_type, *shlex.split(params or ""), "__name:=" + name]


def launcher_argv(package, launch_file, params="", sigint_timeout=2.0, sigterm_timeout=1.0):
    """``roslaunch --wait PKG FILE PARAMS`` with roslaunch's own stop timeouts inside ours.

    ``--wait``: the space's master is already up when items start; should it be gone, a launcher must wait
    (and show as not paired) rather than start a ROS master of its own on the space's port.
    """
    return ["roslaunch", "--wait", f"--sigint-timeout={sigint_timeout:g}",
            f"--sigterm-timeout={sigterm_timeout:g}", package, launch_file, *shlex.split(params or "")]


def launcher_nodes(package, launch_file, params=""):
    """[(node name without leading slash, package, type)] that ``roslaunch PKG FILE PARAMS`` would start.

    Uses roslaunch's own loader (no output parsing); blocking: call it in a thread. Raises
    ``roslaunch.core.RLException`` (its message names the problem) for a missing package, file or arg.
    """
    import roslaunch.config
    import roslaunch.rlutil
    args = shlex.split(params or "")
    resolved = roslaunch.rlutil.resolve_launch_arguments([package, launch_file] + args)  # drops name:=value
    config = roslaunch.config.load_config_default([(resolved[0], [resolved[0]] + args)], None, verbose=False,
                                                  assign_machines=False)
    nodes = []
    for node in config.nodes:
        full = (node.namespace or "/") + node.name
        nodes.append((full.lstrip("/"), node.package, node.type))
    return nodes


def _tcp_port_free(port, host=""):
    """True when nothing listens on ``port`` on any address (a listener on one address makes it busy)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host, port))
            return True
        except OSError:
            return False


def _platform_address(config):
    """This machine's platform address now: ``rcmp_node.platform_address(config)`` (vpn_address or the VPN
    interface's IPv4 address); SpaceError when there is none yet."""
    address = getattr(config, "vpn_address", None)
    if not address:
        try:
            from rcm_platform import rcmp_node
            address = rcmp_node.platform_address(config)
        except (ImportError, AttributeError, OSError, ValueError) as exc:
            raise SpaceError(f"no platform address: {exc}") from None
    if not address:
        raise SpaceError(f"no platform address: interface {getattr(config, 'vpn_interface', '?')} has no "
                         "IPv4 address and vpn_address is not set")
    return address


RCM_DRIVER_PORT = 9998  # rcm_driver's default port (CONTRACTS §4); each further space takes the next free one
_PORT_TAKEN = "is already in use"  # rosmaster's words when its XML-RPC port is taken ("port N is already in use")


def _graph_name(name, params=""):
    """The ROS graph name ``rosrun PKG TYPE PARAMS __name:=NAME`` registers under: ``/NAME``, or
    ``/NS/NAME`` when the params hold ``__ns:=NS`` (unbalanced quotes: the plain name; spawning reports them)."""
    try:
        words = shlex.split(params or "")
    except ValueError:
        words = []
    namespace = next((w.split(":=", 1)[1] for w in reversed(words) if w.startswith("__ns:=")), "")
    namespace = namespace.strip("/")
    return f"/{namespace}/{name}" if namespace else f"/{name}"


class SpaceError(Exception):
    """Why a service space cannot be paired (a sentence shown in service_space/read as ``reason``)."""


class ServiceItem:
    """One node or launcher of a service space, run here (``process``) or on the robot (``remote``)."""

    def __init__(self, kind, name, package, type_or_file, params, side, i_name):
        self.kind = kind
        self.name = name
        self.package = package
        self.type_or_file = type_or_file
        self.params = params or ""
        self.side = side
        self.i_name = i_name
        self.process = None     # ManagedProcess, when run by this agent
        self.remote = None      # the robot's item report, when run there
        self.own_state = STARTING
        self.error = None       # set when the item failed before or without a process
        self.nodes = []         # ROS node names (the node itself, or the launcher's nodes)
        self.node_types = {}    # launcher node name -> (package, type)
        self.driver_port = None
        self.inbound_port = None

    @classmethod
    def from_dict(cls, item, i_name):
        """A ServiceItem from a service logic entry (``sn_*`` node or ``sl_*`` launcher fields)."""
        if not isinstance(item, dict):
            raise ValueError(f"a service item must be an object, got {item!r}")
        try:
            if "sn_name" in item:
                return cls("node", item["sn_name"], item["sn_package"], item["sn_type"],
                           item.get("sn_params", ""), str(item.get("sn_side", "S")).upper(), i_name)
            if "sl_name" in item:
                return cls("launcher", item["sl_name"], item["sl_package"], item["sl_file_launcher"],
                           item.get("sl_params", ""), str(item.get("sl_side", "S")).upper(), i_name)
        except KeyError as exc:
            raise ValueError(f"service item {item!r} lacks the field {exc.args[0]}") from None
        raise ValueError(f"service item {item!r} has neither sn_name nor sl_name")

    def to_dict(self):
        """The service logic entry this item came from (what a robot is sent)."""
        if self.kind == "node":
            return {"sn_package": self.package, "sn_type": self.type_or_file, "sn_name": self.name,
                    "sn_params": self.params, "sn_side": self.side}
        return {"sl_package": self.package, "sl_file_launcher": self.type_or_file, "sl_name": self.name,
                "sl_params": self.params, "sl_side": self.side}

    @property
    def is_rcm_driver(self):
        return self.kind == "node" and self.package == "rcm" and self.type_or_file == "rcm_driver.py"

    @property
    def is_firos(self):
        return self.kind == "node" and self.package == "firos" and self.type_or_file == "core.py"

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

    def fail(self, error):
        self.error = error
        self.own_state = FAILED

    def report(self):
        """The item report of docs/DESIGN.md (what a robot returns to the master)."""
        if self.remote is not None:
            return dict(self.remote)
        return {"kind": self.kind, "name": self.name, "package": self.package,
                "type_or_file": self.type_or_file, "side": self.side, "i_name": self.i_name,
                "state": self.state, "error": self.current_error, "nodes": list(self.nodes),
                "node_types": {n: list(t) for n, t in self.node_types.items()}}


class _DriverLink(LineReceiver):
    """The agent's end of the rcm_driver connection (CONTRACTS §4): one JSON object per line."""

    delimiter = b"\n"
    MAX_LENGTH = 65536

    def __init__(self, space):
        self.space = space

    def send(self, cmd, r_name):
        self.sendLine(json.dumps({"rcm_d_cmd": cmd, "r_name": r_name}).encode())

    def lineReceived(self, line):
        try:
            message = json.loads(line.decode("utf-8"))
            cmd, r_name = message["rcm_d_cmd"], message["r_name"]
        except (ValueError, KeyError, TypeError):
            log.warning("service space %s: rcm_driver sent garbage: %r", self.space.name, line[:200])
            return
        log.info("service space %s: rcm_driver says %s %s", self.space.name, cmd, r_name)
        self.space.driver_events.append({"rcm_d_cmd": cmd, "r_name": r_name})
        waiters, self.space.driver_waiters = self.space.driver_waiters, []
        for wanted, d in waiters:
            if wanted == (cmd, r_name):
                d.callback(True)
            else:
                self.space.driver_waiters.append((wanted, d))

    def connectionLost(self, reason=protocol.connectionDone):
        if self.space.driver_link is self:
            self.space.driver_link = None


class ServiceSpace:
    """The running context of one robot on this agent: ROS master, items, ports, pairing."""

    def __init__(self, name, ss_side, key_prefix, address, i_name):
        self.name = name
        self.ss_side = ss_side
        self.key_prefix = key_prefix
        self.address = address
        self.i_name = i_name
        self.ros_master_uri = None
        self.ros_master_port = None
        self.master = None          # ManagedProcess of rosmaster, when the master runs here
        self.core_env = None        # the environment of the space's rosmaster and rosout
        self.rosout = None
        self.items = []
        self.inbound_port = None
        self.reason = None
        self.paired = False
        self.creating = True
        self.cancelled = False
        self.robot = None
        self.driver_link = None
        self.driver_events = []
        self.driver_waiters = []
        self.reported = False       # robot side: the start report went out; later deaths are events
        self.told = set()           # robot side: keys of the failures already reported
        self.teardown_waiters = None

    def key(self, *parts):
        return "/".join((self.key_prefix, self.name) + parts)

    def core_processes(self):
        return [p for p in (self.rosout, self.master) if p is not None]


class RemoteRobot(Protocol):
    """A connected robot as the master sees it (implemented by rcmp_event over the network)."""

    name: str
    address: str

    def start_items(self, ss_name, ros_master_uri, items, start_ros_master_port=None):
        """Deferred({"ros_master_uri": str, "items": [item report, ...]}) once the robot's items settled."""

    def stop_items(self, ss_name):
        """Deferred fired when the robot stopped every item (and ROS master) of the space."""


# ---------------------------------------------------------------------------------------------------------
# The runtime shared by both sides: start a ROS master, start local items, stop a space.

class _SpaceHost:
    master_timeout = 20.0        # seconds for a new ROS master to answer
    driver_timeout = 20.0        # seconds for rcm_driver's port to accept
    driver_goodbye_timeout = 3.0 # seconds to wait for e_removed after r_disconnection (with FIROS)
    robot_timeout = 30.0         # seconds for a robot to stop its items before we carry on
    launcher_nodes_timeout = 15.0  # seconds for a launcher's nodes to register after it was spawned
    registration_poll = 0.02       # seconds between two looks at the ROS master while items register
    _roslaunch_imported = False    # launcher_nodes ran once on the reactor thread (see _prepare)

    key_prefix = "ss"

    def __init__(self, reactor, table, config, env=None, address=None):
        self.reactor = reactor
        self.table = table
        self.config = config
        self.env = env
        self._address = address
        self.spaces = {}
        self.ros_log_dir = os.path.join(table.log_dir, "ros")

    @property
    def address(self):
        """The platform address children advertise (ROS_IP): given, or looked up now (it may appear late)."""
        return self._address or _platform_address(self.config)

    # -- ports --------------------------------------------------------------------------------------------
    def _taken_ros_ports(self):
        return {s.ros_master_port for s in self.spaces.values() if s.ros_master_port}

    def _choose_ros_port(self, base):
        taken = self._taken_ros_ports()
        for port in range(base, min(base + 1000, 65536)):
            if port not in taken and _tcp_port_free(port):
                return port
        raise SpaceError(f"no free port for a ROS master between {base} and {min(base + 999, 65535)}")

    def _choose_driver_port(self):
        """A local port for a space's rcm_driver: rcm_driver's default (9998) or the next free one above it.
        Never a port-0 (ephemeral) port: any process's outgoing or port-0 socket can take one of those between
        our check and the driver's bind, and the agent would then say r_connection to a stranger."""
        taken = {i.driver_port for s in self.spaces.values() for i in s.items if i.driver_port}
        taken.add(getattr(self.config, "ic_port", None))
        for port in range(RCM_DRIVER_PORT, RCM_DRIVER_PORT + 1000):
            if port not in taken and _tcp_port_free(port):
                return port
        raise SpaceError(f"no free local port for rcm_driver between {RCM_DRIVER_PORT} and {RCM_DRIVER_PORT + 999}")

    def _take_inbound_port(self, space):
        ports = list(getattr(self.config, "inbound_open_ports", None) or [])
        users = {s.inbound_port: s.name for s in self.spaces.values() if s.inbound_port}
        for port in ports:
            if port not in users and _tcp_port_free(port):
                return port
        if not ports:
            raise SpaceError("FIROS needs an inbound open port but inbound_open_ports is empty")
        used = ", ".join(f"{p} ({users[p]})" if p in users else f"{p} (busy)" for p in ports)
        raise SpaceError(f"no inbound open port left for FIROS: all of {used} are in use")

    # -- ROS master -----------------------------------------------------------------------------------------
    def _spawn_master(self, space, base):
        """Spawn the space's ROS master on a free port from ``base``; its URI is known at once, so items can
        be started right away (rospy nodes and ``roslaunch --wait`` wait for their master themselves)."""
        port = self._choose_ros_port(base)
        space.ros_master_port = port
        space.ros_master_uri = f"http://{space.address}:{port}/"
        space.core_env = child_env(self.env, space.ros_master_uri, space.address, self.ros_log_dir)
        space.master = self.table.spawn(space.key("rosmaster"), ["rosmaster", "--core", "-p", str(port)],
                                        space.core_env, f"{space.name}-rosmaster", core=True)

    @defer.inlineCallbacks
    def _master_ready(self, space):
        """Wait for the spawned ROS master to answer, give it ``/run_id`` as roscore does, start rosout, and
        mark both running as soon as they prove it (the master answers, rosout registers)."""
        yield self._wait_for_master(space)
        if space.cancelled:
            return
        space.master.confirm_running("answers on its XML-RPC port")
        # roscore sets /run_id; roslaunch --wait (launchers) waits for it and rosout names its log dir after it
        yield self._call_master(space, "setParam", "/run_id", str(uuid.uuid1()), what="set /run_id")
        if space.cancelled:
            return
        space.rosout = self.table.spawn(space.key("rosout"), ["rosrun", "rosout", "rosout"], space.core_env,
                                        f"{space.name}-rosout", core=True)
        space.rosout.listeners.append(lambda mp, old, new: self._core_changed(space, mp, new))
        space.master.listeners.append(lambda mp, old, new: self._core_changed(space, mp, new))
        # rosout only collects logs: pairing does not wait for it to register (its failure still unpairs)
        watching = self._confirm_when_registered(space, space.rosout, ["/rosout"])
        watching.addErrback(lambda failure: log.error("service space %s: watching rosout: %s", space.name,
                                                      failure.getTraceback()))

    @defer.inlineCallbacks
    def _call_master(self, space, method, *args, what):
        """One XML-RPC call to the space's master, retried until ``master_timeout``: a machine saturated by
        starting processes can make a single call time out although the master is fine."""
        proxy = xmlrpc.Proxy(space.ros_master_uri.encode(), connectTimeout=1.0, reactor=self.reactor)
        deadline = self.reactor.seconds() + self.master_timeout
        while True:
            try:
                result = yield proxy.callRemote(method, "/rcmp_ms", *args)
                return result
            except Exception as exc:
                if space.cancelled:
                    return None
                if self.reactor.seconds() > deadline:
                    raise SpaceError(f"the ROS master on {space.ros_master_uri} could not {what} within "
                                     f"{self.master_timeout:g} s: {exc}")
            yield task.deferLater(self.reactor, 0.1, lambda: None)

    @defer.inlineCallbacks
    def _confirm_when_registered(self, space, managed, names, deadline=None):
        """Mark ``managed`` running as soon as every ROS node in ``names`` is registered with the space's
        master. Fires with the names still missing when it stopped looking: [] once all registered; the
        missing ones if the process ended, or (no ``deadline``) settled the slow way, or ``deadline`` passed."""
        proxy = xmlrpc.Proxy(space.ros_master_uri.encode(), connectTimeout=1.0, reactor=self.reactor)
        missing = list(names)
        while True:
            if space.cancelled or managed.state not in (STARTING, RUNNING):
                return missing
            still = []
            for name in missing:
                try:
                    code, _, _ = yield proxy.callRemote("lookupNode", "/rcmp_ms", name)
                except Exception:
                    code = 0
                if code != 1:
                    still.append(name)
            missing = still
            if not missing:
                managed.confirm_running("registered with the ROS master")
                managed.remember_descendants()  # its nodes now exist: they go wherever it goes
                return []
            if deadline is None and managed.state == RUNNING:
                return missing
            if deadline is not None and self.reactor.seconds() > deadline:
                return missing
            yield task.deferLater(self.reactor, self.registration_poll, lambda: None)

    @defer.inlineCallbacks
    def _wait_for_master(self, space):
        """Poll the new master's XML-RPC getPid until it answers (no sleeping in place of waiting)."""
        proxy = xmlrpc.Proxy(space.ros_master_uri.encode(), connectTimeout=1.0, reactor=self.reactor)
        deadline = self.reactor.seconds() + self.master_timeout
        while True:
            if space.cancelled:
                return
            if space.master.state not in (STARTING, RUNNING):
                raise SpaceError(f"the ROS master on port {space.ros_master_port} {space.master.error}")
            if _PORT_TAKEN in space.master.tail(20):
                # rosmaster stays alive without its XML-RPC server when its port was taken between our check
                # and its bind: say so now rather than after master_timeout
                raise SpaceError(f"the ROS master could not listen on port {space.ros_master_port}: "
                                 f"{space.master.useful_output(2)}")
            try:
                yield proxy.callRemote("getPid", "/rcmp_ms")
                log.info("service space %s: ROS master answers on %s", space.name, space.ros_master_uri)
                return
            except Exception as exc:
                if self.reactor.seconds() > deadline:
                    raise SpaceError(f"the ROS master on {space.ros_master_uri} did not answer within "
                                     f"{self.master_timeout:g} s: {exc}")
            yield task.deferLater(self.reactor, 0.05, lambda: None)

    @defer.inlineCallbacks
    def _core_settled(self, space):
        """Wait until the ROS master runs here (usually long since) and check that rosout has not failed;
        SpaceError if one did."""
        if space.master is not None:
            up = yield space.master.when_settled()
            if not up and not space.cancelled:
                raise SpaceError(f"the space's rosmaster {space.master.error}")
        if space.rosout is not None and space.rosout.state in DONE_STATES and not space.cancelled:
            raise SpaceError(f"the space's rosout {space.rosout.error}")

    def _core_changed(self, space, managed, new):
        if new == FAILED and not space.cancelled:
            space.reason = f"the space's {managed.key.rsplit('/', 1)[-1]} {managed.error}"
            self._pairing_may_have_changed(space)

    # -- local items ----------------------------------------------------------------------------------------
    @defer.inlineCallbacks
    def _start_local_items(self, space, items):
        """Prepare (launcher node lists, ports), spawn every item, and wait until each started or failed."""
        yield defer.gatherResults([self._prepare(space, item) for item in items], consumeErrors=True)
        if space.cancelled:
            return
        env = child_env(self.env, space.ros_master_uri, space.address, self.ros_log_dir)
        for item in items:
            if item.error is None:
                self._spawn_item(space, item, env)
        yield defer.gatherResults([self._item_started(space, item) for item in items if item.process],
                                  consumeErrors=True)

    @defer.inlineCallbacks
    def _item_started(self, space, item):
        """An item has started when its ROS node(s) registered with the space's master (or, for a node that
        never registers under its name, when it stayed up for the settle time). A launcher must see every node
        it launches register: roslaunch keeps running when one of its nodes cannot start, so its liveness
        alone proves nothing."""
        if item.kind == "node":
            yield self._confirm_when_registered(space, item.process, [_graph_name(item.name, item.params)])
            yield item.process.when_settled()
            return
        deadline = self.reactor.seconds() + self.launcher_nodes_timeout
        names = ["/" + n.lstrip("/") for n in item.nodes]
        missing = yield self._confirm_when_registered(space, item.process, names, deadline=deadline)
        if missing and not space.cancelled and item.process.state in (STARTING, RUNNING):
            output = item.process.useful_output()
            item.fail(f"node(s) {', '.join(n.lstrip('/') for n in missing)} of launcher {item.name} did not "
                      f"register with the ROS master within {self.launcher_nodes_timeout:g} s"
                      + (f": {output}" if output else ""))

    @defer.inlineCallbacks
    def _prepare(self, space, item):
        if item.kind == "node":
            item.nodes = [item.name]
            if item.is_firos:
                try:
                    item.inbound_port = self._take_inbound_port(space)
                    space.inbound_port = item.inbound_port
                except SpaceError as exc:
                    item.fail(str(exc))
                    space.reason = str(exc)
            if item.is_rcm_driver:
                try:
                    item.driver_port = self._choose_driver_port()
                except SpaceError as exc:
                    item.fail(str(exc))
                    space.reason = str(exc)
            return
        try:
            if self._roslaunch_imported:
                nodes = yield threads.deferToThread(launcher_nodes, item.package, item.type_or_file, item.params)
            else:
                # The first parse imports ~300 modules (roslaunch, rospkg, pkg_resources...). An import running
                # in a thread while the reactor forks a child deadlocks CPython (os.fork takes the import and
                # logging locks), so that first parse runs here, on the reactor thread, once per agent.
                _SpaceHost._roslaunch_imported = True
                nodes = launcher_nodes(item.package, item.type_or_file, item.params)
        except Exception as exc:  # roslaunch's RLException and its loader's errors: the message says why
            item.fail(f"roslaunch cannot load {item.package}/{item.type_or_file}: {exc}")
            return
        item.nodes = [n for n, _, _ in nodes]
        item.node_types = {n: (p, t) for n, p, t in nodes}

    def _item_argv(self, item):
        if item.kind == "launcher":
            return launcher_argv(item.package, item.type_or_file, item.params)
        params = item.params
        if item.is_rcm_driver:
            kept = [p for p in shlex.split(params) if not p.startswith("port=")]
            params = shlex.join(kept + [f"port={item.driver_port}"])
        argv = node_argv(item.package, item.type_or_file, item.name, params)
        if item.is_firos:
            argv += ["-P", str(item.inbound_port)]
        return argv

    def _spawn_item(self, space, item, env):
        try:
            argv = self._item_argv(item)
        except ValueError as exc:  # shlex: unbalanced quotes
            item.fail(f"cannot split the params {item.params!r}: {exc}")
            return
        item.process = self.table.spawn(space.key(item.kind, item.name), argv, env,
                                        f"{space.name}-{item.name}")
        item.process.listeners.append(lambda mp, old, new: self._item_changed(space, item, new))

    def _item_changed(self, space, item, new):
        if new == FAILED and not space.cancelled:
            self._pairing_may_have_changed(space)

    def _pairing_may_have_changed(self, space):
        """Hook: each side decides what a change means (master: on_state; robot: item-exited event)."""

    # -- stopping -------------------------------------------------------------------------------------------
    @defer.inlineCallbacks
    def _stop_local(self, space):
        """Stop the space's items here (together), then rosout, then the ROS master; forget them."""
        space.cancelled = True
        procs = [i.process for i in space.items if i.process is not None]
        yield defer.gatherResults([p.stop() for p in procs], consumeErrors=True)
        for managed in space.core_processes():
            yield managed.stop()
        for managed in procs + space.core_processes():
            self.table.forget(managed.key)


# ---------------------------------------------------------------------------------------------------------
# Master side.

class ServiceSpaceManager(_SpaceHost):
    """The master's (or a server VM's) service spaces, one per connected robot. See docs/SERVICE_SPACES.md."""

    key_prefix = "ss"

    def __init__(self, reactor, table, config, public_ip, env=None, on_state=None, address=None):
        super().__init__(reactor, table, config, env=env, address=address)
        self.public_ip = public_ip
        self.on_state = on_state
        self.i_name = "master" if getattr(config, "role", "master") == "master" else config.name

    # -- create ---------------------------------------------------------------------------------------------
    @defer.inlineCallbacks
    def create(self, pi_name, service_logic, robot):
        """Build the space of robot ``pi_name``; fires with the ServiceSpace once everything settled.

        The Deferred fires (never fails) when the space is paired or known not to pair (``space.reason`` and
        the items' errors say why); a space that already exists is torn down first. Bad service logic
        (missing fields) fails the Deferred with ValueError before anything starts.
        """
        ss_side = str(service_logic.get("ss_side") or "S").upper()
        if ss_side not in ("S", "R"):
            raise ValueError(f"ss_side must be S or R, got {service_logic.get('ss_side')!r}")
        robot_name = getattr(robot, "name", pi_name) if robot is not None else pi_name
        items = []
        for entry in list(service_logic.get("sn_list") or []) + list(service_logic.get("sl_list") or []):
            item = ServiceItem.from_dict(entry, None)
            if item.side not in ("S", "R"):
                raise ValueError(f"item {item.name}: side must be S or R, got {item.side!r}")
            item.i_name = self.i_name if item.side == "S" else robot_name
            items.append(item)
        remote = [i for i in items if i.side == "R"]
        if (remote or ss_side == "R") and robot is None:
            raise ValueError(f"service space {pi_name} has robot-side parts but no robot to run them")
        if pi_name in self.spaces:
            yield self.teardown(pi_name)
        space = ServiceSpace(pi_name, ss_side, self.key_prefix, None, self.i_name)
        space.items = items
        space.robot = robot
        self.spaces[pi_name] = space
        log.info("service space %s: creating (%d S items, %d R items, ROS master on the %s side)", pi_name,
                 len(items) - len(remote), len(remote), "robot" if ss_side == "R" else "server")
        try:
            space.address = self.address
            if ss_side == "S":
                self._spawn_master(space, int(getattr(self.config, "ros_port_base", 11311)))
                work = [self._master_ready(space),
                        self._start_local_items(space, [i for i in items if i.side == "S"])]
                if remote:
                    work.append(self._start_remote(space, robot, remote, None))
                yield defer.gatherResults(work, consumeErrors=True)
            else:
                yield self._start_remote(space, robot, remote,
                                         int(getattr(self.config, "ros_port_base", 11311)))
                if not space.cancelled and space.ros_master_uri:
                    yield self._start_local_items(space, [i for i in items if i.side == "S"])
            if not space.cancelled:
                yield self._connect_drivers(space)
            yield self._core_settled(space)
        except SpaceError as exc:
            space.reason = str(exc)
        except defer.FirstError as exc:
            inner = exc.subFailure.value
            space.reason = str(inner) if isinstance(inner, SpaceError) else f"unexpected error: {inner!r}"
            if not isinstance(inner, SpaceError):
                log.error("service space %s: %s", pi_name, exc.subFailure.getTraceback())
        except Exception as exc:  # a bug: keep the space visible (and stoppable) with the reason
            space.reason = f"unexpected error: {exc!r}"
            log.exception("service space %s: unexpected error while creating", pi_name)
        finally:
            space.creating = False
        if not space.cancelled:
            self._pairing_may_have_changed(space)
            level = logging.INFO if space.paired else logging.WARNING
            log.log(level, "service space %s: %s", pi_name,
                    "paired" if space.paired else f"not paired: {self._why_unpaired(space)}")
        return space

    @defer.inlineCallbacks
    def _start_remote(self, space, robot, remote, start_ros_master_port):
        try:
            result = yield robot.start_items(space.name, space.ros_master_uri, [i.to_dict() for i in remote],
                                             start_ros_master_port=start_ros_master_port)
        except Exception as exc:
            raise SpaceError(f"robot {getattr(robot, 'name', space.name)} could not start its items: {exc}")
        if space.cancelled:
            return
        if result.get("reason"):
            raise SpaceError(f"robot {getattr(robot, 'name', space.name)}: {result['reason']}")
        if start_ros_master_port is not None:
            space.ros_master_uri = result.get("ros_master_uri")
            if not space.ros_master_uri:
                raise SpaceError(f"robot {robot.name} did not start the ROS master")
        reports = {(r.get("kind"), r.get("name")): r for r in result.get("items") or []}
        for item in remote:
            item.remote = reports.get((item.kind, item.name)) or {
                **item.report(), "state": FAILED, "error": "the robot did not report this item"}
            item.remote.setdefault("i_name", item.i_name)
            item.nodes = list(item.remote.get("nodes") or [])
            item.node_types = {n: tuple(t) for n, t in (item.remote.get("node_types") or {}).items()}

    @defer.inlineCallbacks
    def _connect_drivers(self, space):
        for item in space.items:
            if item.is_rcm_driver and item.process is not None and item.state == RUNNING:
                yield self._connect_driver(space, item)

    @defer.inlineCallbacks
    def _connect_driver(self, space, item):
        """Connect to rcm_driver's port once it accepts and say r_connection for the robot."""
        endpoint = TCP4ClientEndpoint(self.reactor, "127.0.0.1", item.driver_port, timeout=1)
        deadline = self.reactor.seconds() + self.driver_timeout
        while True:
            if space.cancelled or item.state not in (STARTING, RUNNING):
                return
            try:
                link = yield connectProtocol(endpoint, _DriverLink(space))
                break
            except (ierror.ConnectError, ierror.ConnectionRefusedError, ierror.TimeoutError) as exc:
                if self.reactor.seconds() > deadline:
                    raise SpaceError(f"rcm_driver did not accept connections on port {item.driver_port} "
                                     f"within {self.driver_timeout:g} s: {exc}")
            yield task.deferLater(self.reactor, 0.1, lambda: None)
        space.driver_link = link
        link.send("r_connection", space.name)
        log.info("service space %s: told rcm_driver (port %s) r_connection", space.name, item.driver_port)

    # -- pairing --------------------------------------------------------------------------------------------
    def _compute_paired(self, space):
        if space.creating or space.cancelled or space.reason:
            return False
        if not space.ros_master_uri:
            return False
        if space.master is not None and space.master.state != RUNNING:
            return False
        if space.rosout is not None and space.rosout.state not in (STARTING, RUNNING):
            return False
        return all(item.state == RUNNING for item in space.items)

    def _why_unpaired(self, space):
        if space.reason:
            return space.reason
        for item in space.items:
            if item.state != RUNNING:
                return f"{item.kind} {item.name} on {item.i_name} is {item.state}" + (
                    f": {item.current_error}" if item.current_error else "")
        return "starting"

    def _pairing_may_have_changed(self, space):
        if space.creating:
            return
        paired = self._compute_paired(space)
        if paired != space.paired:
            space.paired = paired
            if not paired:
                log.warning("service space %s: no longer paired: %s", space.name, self._why_unpaired(space))
            self._notify(space)

    def _notify(self, space):
        if self.on_state is not None:
            try:
                self.on_state(space.name, space.paired, space)
            except Exception:
                log.exception("on_state callback for %s failed", space.name)

    def item_exited(self, ss_name, report):
        """The robot says an R item (or, kind ``ros_master``, its ROS master) of ``ss_name`` ended."""
        space = self.spaces.get(ss_name)
        if space is None or space.cancelled or not isinstance(report, dict):
            return
        if report.get("kind") == "ros_master":
            space.reason = f"the ROS master on robot {report.get('i_name')} ended: {report.get('error')}"
        else:
            for item in space.items:
                if item.remote is not None and (item.kind, item.name) == (report.get("kind"), report.get("name")):
                    item.remote = dict(report)
                    break
            else:
                log.warning("service space %s: robot reported an unknown item %r", ss_name, report)
                return
        log.warning("service space %s: robot reports %s %s %s: %s", ss_name, report.get("kind"),
                    report.get("name"), report.get("state"), report.get("error"))
        self._pairing_may_have_changed(space)

    # -- teardown -------------------------------------------------------------------------------------------
    def teardown(self, pi_name):
        """Stop the space: R items on the robot, S items, then the ROS master. Fires when all are gone."""
        space = self.spaces.get(pi_name)
        if space is None:
            return defer.succeed(None)
        d = defer.Deferred()
        if space.teardown_waiters is not None:
            space.teardown_waiters.append(d)
            return d
        space.teardown_waiters = [d]
        self._teardown(space)
        return d

    @defer.inlineCallbacks
    def _teardown(self, space):
        was_paired = space.paired
        space.cancelled = True
        space.paired = False
        log.info("service space %s: tearing down", space.name)
        try:
            yield self._say_goodbye_to_driver(space)
            has_remote = any(i.side == "R" for i in space.items)
            if space.ss_side == "R":
                yield self._stop_local(space)          # S items first: the ROS master is on the robot
            if space.robot is not None and (has_remote or space.ss_side == "R"):
                yield self._stop_remote(space)
            if space.ss_side == "S":
                yield self._stop_local(space)
        except Exception:
            log.exception("service space %s: teardown error", space.name)
        finally:
            if self.spaces.get(space.name) is space:
                del self.spaces[space.name]
            log.info("service space %s: torn down", space.name)
            if was_paired:
                self._notify(space)
            waiters, space.teardown_waiters = space.teardown_waiters, []
            for d in waiters:
                d.callback(None)

    @defer.inlineCallbacks
    def _stop_remote(self, space):
        d = space.robot.stop_items(space.name)
        timeout = self.reactor.callLater(self.robot_timeout, d.cancel)
        try:
            yield d
        except Exception as exc:
            log.warning("service space %s: robot %s did not confirm stopping its items: %s", space.name,
                        getattr(space.robot, "name", "?"), exc)
        finally:
            if timeout.active():
                timeout.cancel()

    @defer.inlineCallbacks
    def _say_goodbye_to_driver(self, space):
        link = space.driver_link
        if link is None:
            return
        link.send("r_disconnection", space.name)
        log.info("service space %s: told rcm_driver r_disconnection", space.name)
        firos_up = any(i.is_firos and i.state == RUNNING for i in space.items)
        if firos_up:  # give FIROS the chance to remove the robot's entity before it is stopped
            waiter = defer.Deferred()
            space.driver_waiters.append((("e_removed", space.name), waiter))
            timeout = self.reactor.callLater(self.driver_goodbye_timeout, waiter.callback, False)
            removed = yield waiter
            if timeout.active():
                timeout.cancel()
            if not removed:
                log.warning("service space %s: no e_removed from rcm_driver within %g s", space.name,
                            self.driver_goodbye_timeout)
        link.transport.loseConnection()

    @defer.inlineCallbacks
    def teardown_all(self):
        yield defer.gatherResults([self.teardown(name) for name in list(self.spaces)], consumeErrors=True)

    # -- service_space/read ---------------------------------------------------------------------------------
    def describe(self, ss_name):
        """The ``service_space/read`` payload for ``ss_name`` (CONTRACTS §2), or None when there is none."""
        space = self.spaces.get(ss_name)
        if space is None:
            return None
        r_nodes, r_launchers = [], []
        for item in space.items:
            state, error = item.state, item.current_error
            if item.kind == "node":
                entry = {"sn_package": item.package, "sn_type": item.type_or_file, "sn_name": item.name,
                         "i_name": item.i_name, "state": state}
                if error:
                    entry["error"] = error
                r_nodes.append(entry)
                continue
            entry = {"sl_package": item.package, "sl_file_launcher": item.type_or_file, "sl_name": item.name,
                     "associated_r_nodes": list(item.nodes), "i_name": item.i_name, "state": state}
            if error:
                entry["error"] = error
            r_launchers.append(entry)
            for node in item.nodes:
                package, node_type = item.node_types.get(node, (item.package, ""))
                r_nodes.append({"sn_package": package, "sn_type": node_type, "sn_name": node,
                                "i_name": item.i_name, "state": state, "launcher": item.name})
        payload = {"r_nodes": r_nodes, "r_launchers": r_launchers, "public_ip": self.public_ip,
                   "inbound_port": space.inbound_port, "ros_master_uri": space.ros_master_uri,
                   "paired": space.paired}
        if not space.paired and not space.creating:
            payload["reason"] = self._why_unpaired(space)
        if space.driver_events:
            payload["rcm_driver_events"] = list(space.driver_events)
        return payload


# ---------------------------------------------------------------------------------------------------------
# Robot side.

class RobotSideRunner(_SpaceHost):
    """The robot's part of its service spaces: R items (and the ROS master for ``ss_side`` R)."""

    key_prefix = "robot"

    def __init__(self, reactor, table, config, env=None, on_item_exited=None, address=None):
        super().__init__(reactor, table, config, env=env, address=address)
        self.on_item_exited = on_item_exited
        self.i_name = config.name

    @defer.inlineCallbacks
    def start_items(self, ss_name, ros_master_uri, items, start_ros_master_port=None):
        """Start R items against ``ros_master_uri`` (or a ROS master started here on a free port from
        ``start_ros_master_port`` upward); fires with {"ros_master_uri", "items": [reports]} once each item
        settled or failed. A space of the same name already here is stopped first."""
        parsed = []
        for entry in items or []:
            item = ServiceItem.from_dict(entry, self.i_name)
            item.side = "R"
            parsed.append(item)
        if ss_name in self.spaces:
            yield self.stop_items(ss_name)
        space = ServiceSpace(ss_name, "R" if start_ros_master_port else "S", self.key_prefix, None,
                             self.i_name)
        space.items = parsed
        space.ros_master_uri = ros_master_uri
        self.spaces[ss_name] = space
        try:
            space.address = self.address
            work = []
            if start_ros_master_port:
                self._spawn_master(space, int(start_ros_master_port))
                work.append(self._master_ready(space))
            if not space.ros_master_uri:
                raise SpaceError("no ROS master URI given and none started")
            work.append(self._start_local_items(space, parsed))
            try:
                yield defer.gatherResults(work, consumeErrors=True)
            except defer.FirstError as exc:
                if isinstance(exc.subFailure.value, SpaceError):
                    raise exc.subFailure.value
                raise
            yield self._core_settled(space)
        except SpaceError as exc:
            space.reason = str(exc)
            for item in parsed:
                if item.process is None and item.error is None:
                    item.fail(str(exc))
        finally:
            space.creating = False
        space.reported = True
        space.told.update((i.kind, i.name) for i in parsed if i.state == FAILED)
        return {"ros_master_uri": space.ros_master_uri, "items": [i.report() for i in parsed],
                "reason": space.reason}

    def _pairing_may_have_changed(self, space):
        if not space.reported or space.cancelled or self.on_item_exited is None:
            return
        for item in space.items:
            if item.state == FAILED and (item.kind, item.name) not in space.told:
                space.told.add((item.kind, item.name))
                self._tell(space, item.report())
        for managed in space.core_processes():
            if managed.state == FAILED and managed.key not in space.told:
                space.told.add(managed.key)
                self._tell(space, {"kind": "ros_master", "name": managed.key.rsplit("/", 1)[-1],
                                   "i_name": self.i_name, "state": FAILED, "error": managed.error})

    def _tell(self, space, report):
        try:
            self.on_item_exited(space.name, report)
        except Exception:
            log.exception("on_item_exited callback for %s failed", space.name)

    @defer.inlineCallbacks
    def stop_items(self, ss_name):
        """Stop every item (and the ROS master, if it runs here) of ``ss_name``; fires when all are gone."""
        space = self.spaces.pop(ss_name, None)
        if space is None:
            return
        log.info("service space %s: stopping the robot-side items", ss_name)
        yield self._stop_local(space)

    @defer.inlineCallbacks
    def stop_all(self):
        yield defer.gatherResults([self.stop_items(name) for name in list(self.spaces)], consumeErrors=True)
