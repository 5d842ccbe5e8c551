"""The process table of an agent: every child process it starts, each with one state from a closed set.

Layer 1: imports no other module of ``rcm_platform`` (the runtime, the VPN and the console use it). Owns:

* ``ProcessTable`` / ``ManagedProcess``: one table per agent. Each child has one state from a closed set
  (``STARTING``, ``RUNNING``, ``STOPPING``, ``EXITED``, ``FAILED``: the words ``starting`` ... ``failed`` that the
  RDAPI and the console show) and changes state only through ``ManagedProcess._transition``, which checks the
  allowed source states and logs ``old -> new``. A child is ``running`` once its owner has proof that it started
  (``confirm_running``: a ROS node registered with its master, a master answered) or, failing that, after
  staying up ``settle_time`` seconds; only the reaping path (``processExited``) marks a child ``exited`` (we
  stopped it) or ``failed`` (it ended unasked). ``observers`` (the console) and each child's ``listeners`` are
  told of every transition.
* Children never run through a shell, and the agent is never forked to start them: Twisted's process transport
  starts them with ``posix_spawn`` (``_SpawnedProcess``). Each runs in its own session and process group:
  argv is prefixed with ``/usr/bin/setsid`` (util-linux; the spawned
  child is not a group leader, so setsid calls setsid(2) and execs in place: same pid, and that pid is the
  process group id) and ``/usr/bin/setpriv --pdeathsig TERM`` (the child gets SIGTERM if the agent dies,
  even by SIGKILL, so a killed agent leaves nothing running), switching to another user first when the caller
  gives one (``user``: an object with ``name``, ``home`` and ``setpriv_args()``, the service items'
  ``rcmp_service_item.RunAs``). Both exec directly. An agent started as root runs ``AGENT_PRIORITY_BOOST``
  nice levels above its children (``raise_agent_priority``; ``/usr/bin/nice`` in the same chain puts each child
  back at the agent's original niceness), so that hellos and heartbeats are served while the ROS processes of
  many spaces start at once (docs/DESIGN.md).
* Stopping follows roslaunch: SIGINT to the group, wait (default 5 s), SIGTERM, wait 2 s, SIGKILL. The
  descendants of the child are remembered when the stop begins (roslaunch puts each node in a session of
  its own, so they are not in the launcher's group) and get the SIGTERM and SIGKILL too. "No such process"
  means the process is already going. A stop's Deferred fires when the child is reaped and no process of
  its group or of its remembered descendants is left. ``stop_all`` stops ordinary children first and the
  ROS masters (``core=True``) last.
* Each child's stdout and stderr go to its own size-capped log file under the log directory (one rotated
  backup); ``tail(lines)`` gives the last lines of output, which become ``error`` when a child fails.
* All OS effects (spawn, signals, /proc reads) go through ``OsFacade`` so unit tests can record them.
* ``TableService``: the agent's top service; stops whatever is left in the table when the agent stops (the last
  safety net behind the agents' own teardown).
"""

import collections
import fcntl
import logging
import os
import re
import shlex
import signal
import time

from twisted.application import service
from twisted.internet import defer, process, protocol, task

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
# a child reaped before its spawn returned (it ended at once: an executable that is not there, a wrapper that
# fails) has its output still in the pipes: it is judged once they close, or after this many seconds
EARLY_END_OUTPUT_WAIT = 0.5
ENV = "/usr/bin/env"
SETPRIV = "/usr/bin/setpriv"
NICE = "/usr/bin/nice"
DESCENDANTS_MAX_AGE = 0.2  # seconds a /proc scan may serve a child that has just started (OsFacade.descendants)
AGENT_PRIORITY_BOOST = 5   # an agent runs this many nice levels above the processes it starts (when it may)
_children_nice = 0         # what children add to the agent's niceness to get back to where it started


def raise_agent_priority(boost=AGENT_PRIORITY_BOOST):
    """Give this agent ``boost`` nice levels over the processes it starts, so that hellos, heartbeats and RDAPI
    calls are served while those processes (dozens of ROS nodes starting at once) take the cores; children are
    started through ``nice -n BOOST`` and run at the niceness the agent started with. Only root may lower its
    niceness: otherwise nothing changes. Call it before any thread starts (niceness is per thread on Linux).
    Returns the boost applied (0 or ``boost``)."""
    global _children_nice
    try:
        before = os.nice(0)
        after = os.nice(-boost)
    except PermissionError:
        return 0
    _children_nice = before - after
    return _children_nice


def nice_prefix():
    """The argv prefix that starts a child at the agent's original niceness ([] when the agent kept its own)."""
    return [NICE, "-n", str(_children_nice)] if _children_nice else []

_ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]|\x1b\][^\x07\x1b]*(?:\x07|\x1b\\)?")  # colours, terminal titles


class InvalidTransition(RuntimeError):
    """A state change that the closed state machine does not allow (a bug in the caller)."""


def check_transition(what, old, new, states, sources):
    """Raise InvalidTransition unless ``new`` is one of ``states`` and ``old`` one of the states it may follow
    (``sources``: target -> allowed sources; a state that is no key is never a target). The check of every closed
    state machine here: a child's and (``rcmp_ms``) a service space's."""
    if new not in states:
        raise InvalidTransition(f"{what}: unknown state {new!r}")
    if old not in sources.get(new, ()):
        raise InvalidTransition(f"{what}: {old} -> {new} is not allowed")


# ---------------------------------------------------------------------------------------------------------
# OS effects, behind one facade.

class OsFacade:
    """Every OS effect of the process table: spawn, signals, and reading /proc. Tests replace it."""

    def __init__(self, reactor):
        self.reactor = reactor
        self._devnull = None
        self._scanned = None   # (monotonic time, the /proc table then): see descendants

    def spawn(self, process_protocol, argv, env, cwd=None, user=None):
        """Start ``argv`` in a new session (setsid) with SIGTERM on agent death, as ``user`` (a ``RunAs``) when
        given (one setpriv switches the user first, then sets the death signal, which a user switch would
        clear); returns the pid."""
        if self._devnull is None:
            self._devnull = os.open(os.devnull, os.O_RDONLY)
        switch = user.setpriv_args() if user is not None else []
        if user is not None and cwd is None:
            cwd = user.home
        full = [SETSID, *nice_prefix(), SETPRIV, *switch, "--pdeathsig", "TERM", "--"] + list(argv)
        if cwd is not None:   # posix_spawn cannot change directory: coreutils' env does, then execs
            full = [ENV, "-C", cwd, *full]
        transport = _SpawnedProcess(self.reactor, full[0], full, env, None, process_protocol, None, None,
                                    {0: self._devnull, 1: "r", 2: "r"})
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

    def descendants(self, pid, max_age=0.0):
        """{pid: start_time} of every living descendant of ``pid`` (children, grandchildren, ...). With
        ``max_age``, a scan of /proc up to that many seconds old may serve (a scan reads every process's stat:
        about 5 ms with 400 processes, and dozens of spaces starting at once ask for it many times a second)."""
        now = time.monotonic()
        if max_age and self._scanned is not None and now - self._scanned[0] <= max_age:
            table = self._scanned[1]
        else:
            table = _proc_table()
            self._scanned = (now, table)
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


class _SpawnedProcess(process.Process):
    """Twisted's process transport, the child started with ``os.posix_spawn`` (vfork and exec, in C) instead of
    ``os.fork``. Forking the agent's Python process held its event loop 70-100 ms per child on a busy machine for
    3 ms of CPU (the fork, then copy-on-write faults until the child execs; docs/PERFORMANCE.md): with a fleet
    arriving, hellos waited behind it. The child is set up as Twisted sets it up: fds 0-2 from ``childFDs``,
    every other descriptor closed (ours are close-on-exec; any that is not gets a close action), signals the
    agent ignores back to their defaults. Anything it cannot do so (a change of user, a relative executable, a
    source descriptor among 0-2) goes through Twisted's own fork."""

    def _fork(self, path, uid, gid, executable, args, environment, **kwargs):
        fdmap = kwargs["fdmap"]
        if (uid is not None or gid is not None or path is not None or not os.path.isabs(executable)
                or any(parent < 3 and parent != child for child, parent in fdmap.items())):
            return super()._fork(path, uid, gid, executable, args, environment, **kwargs)
        actions = [(os.POSIX_SPAWN_DUP2, parent, child) for child, parent in sorted(fdmap.items())]
        for fd in _inheritable_fds():
            if fd not in fdmap:
                actions.append((os.POSIX_SPAWN_CLOSE, fd))
        ignored = {n for n in signal.valid_signals()
                   if n not in (signal.SIGKILL, signal.SIGSTOP) and signal.getsignal(n) == signal.SIG_IGN}
        self.pid = os.posix_spawn(executable, args, environment, file_actions=actions, setsigdef=ignored)


def _inheritable_fds():
    """This process's open descriptors that an exec would pass on (close-on-exec not set)."""
    found = []
    for entry in os.listdir("/proc/self/fd"):
        fd = int(entry)
        try:
            if not fcntl.fcntl(fd, fcntl.F_GETFD) & fcntl.FD_CLOEXEC:
                found.append(fd)
        except OSError:      # the listing's own descriptor, closed by now
            continue
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

    def connectionMade(self):
        # Twisted may reap a child that ended at once before the spawn returns: its pid is known from here on
        self.managed.pid = self.transport.pid

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

    def __init__(self, table, key, argv, env, log_path, core=False, user=None):
        self.table = table
        self.key = key
        self.argv = list(argv)
        self.user = user             # RunAs, or None: the agent's own user
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
        self._spawning = False      # inside table.os.spawn: a child reaped then is judged after it returns
        self._early_end = None      # the call that judges such a child if its pipes stay open
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
        old = self.state
        check_transition(self.key, old, new, STATES, _ALLOWED_SOURCES)
        self.state = new
        level = logging.WARNING if new == FAILED else logging.INFO
        log.log(level, "process %s (pid %s): %s -> %s (%s)", self.key, self.pid, old, new, why)
        for listener in list(self.listeners) + list(self.table.observers):
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
        self._log.write(f"=== {time.strftime('%Y-%m-%d %H:%M:%S')} start{' as ' + self.user.name if self.user else ''}: {shlex.join(self.argv)}\n".encode())
        self.started_at = table.reactor.seconds()
        self._spawning = True
        try:
            self.pid = table.os.spawn(_ChildProtocol(self), self.argv, self.env, user=self.user)
        except (OSError, ValueError, TypeError) as exc:
            self._spawning = False
            self.started_at = None
            self.error = f"could not start {self.argv[0]}: {exc}"
            self._log.close()
            self._transition(FAILED, self.error)
            return
        self._spawning = False
        log.info("process %s started: pid %s, argv %s, log %s", self.key, self.pid, self.argv, self.log_path)
        if self._reaped_yet:      # it ended before the spawn returned: judged with its output, nothing to settle
            self._early_end = table.reactor.callLater(EARLY_END_OUTPUT_WAIT, self._ended)
            return
        self._settle_call = table.reactor.callLater(table.settle_time, self._settled)

    def remember_descendants(self, max_age=0.0):
        """Note the child's current descendants, so that they are stopped with it even if it dies first
        (roslaunch's nodes live in sessions of their own and outlive a crashed roslaunch otherwise). When it
        starts, a look at /proc up to ``max_age`` seconds old will do; a stop always looks afresh."""
        if self.pid is not None and not self._reaped_yet:
            self._descendants.update(self.table.os.descendants(self.pid, max_age=max_age))

    def _settled(self):
        self._settle_call = None
        self.remember_descendants(max_age=DESCENDANTS_MAX_AGE)
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
        self.remember_descendants(max_age=DESCENDANTS_MAX_AGE)
        self._transition(RUNNING, why)

    def when_settled(self):
        """Deferred(bool): True once the child is running, False if it failed or was stopped before."""
        if self.state == STARTING:
            d = defer.Deferred()
            self._settled_waiters.append(d)
            return d
        return defer.succeed(self.state == RUNNING)

    def _reaped(self, reason):
        """The reaping path: the only way to ``_ended``, where a child becomes exited or failed."""
        value = reason.value
        self.exit_code = getattr(value, "exitCode", None)
        self.exit_signal = getattr(value, "signal", None)
        self._reaped_yet = True
        if self._settle_call is not None and self._settle_call.active():
            self._settle_call.cancel()
        self._settle_call = None
        if self._log is not None:
            self._log.write(f"=== {time.strftime('%Y-%m-%d %H:%M:%S')} ended: {self._how_ended()}\n".encode())
        if not self._spawning:
            self._ended()

    def _ended(self):
        """Judge a reaped child: exited as asked (stopping) or failed, with the output that says why."""
        if self._early_end is not None and self._early_end.active():
            self._early_end.cancel()
        self._early_end = None
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
        """No process holds the child's output pipes any more: flush the last partial line, close the log (and
        judge a child that ended before its spawn returned, now that its output is all in)."""
        if self._partial:
            self._output(b"\n")
        if self._early_end is not None:
            self._ended()
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
        self.observers = []   # fn(managed, old_state, new_state) after every transition of any child (the console)
        os.makedirs(self.log_dir, exist_ok=True)

    def spawn(self, key, argv, env, log_name, core=False, user=None):
        """Start ``argv`` (a list; never a shell) as child ``key``; ``core`` marks a ROS master (stopped last);
        ``user`` (a ``RunAs``) runs it as that user.

        Returns the ManagedProcess at once, in state ``starting`` (or ``failed`` if it could not be spawned).
        """
        if not isinstance(argv, (list, tuple)) or not argv or not all(isinstance(a, str) for a in argv):
            raise TypeError(f"argv of {key} must be a non-empty list of strings, got {argv!r}")
        current = self._procs.get(key)
        if current is not None and (current.state in LIVE_STATES or current._gone_waiters):
            raise ValueError(f"a process named {key} is already {current.state}")
        safe = re.sub(r"[^A-Za-z0-9_.-]", "_", log_name) or "process"
        managed = ManagedProcess(self, key, argv, env, os.path.join(self.log_dir, safe + ".log"), core=core,
                                 user=user)
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


class TableService(service.MultiService):
    """The agent's services (``rcmp_node`` puts them in it) and, once they have stopped, whatever is still in
    the table stopped too: the last safety net behind the agents' own teardown."""

    def __init__(self, table):
        super().__init__()
        self.table = table

    @defer.inlineCallbacks
    def stopService(self):
        try:
            yield super().stopService()
        finally:
            left = [m for m in self.table.processes() if m.state in LIVE_STATES]
            if left:
                log.warning("stopping %d process(es) still running: %s", len(left),
                            ", ".join(m.key for m in left))
            yield self.table.stop_all()


