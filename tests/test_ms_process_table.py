"""rcmp_process.ProcessTable: one test per state transition with a recording OS facade and task.Clock, then
real children (setsid, process groups, escalation, logs) under a running Twisted reactor."""

import os
import shutil
import signal
import subprocess
import sys
import tempfile

import pytest
from twisted.internet import defer, error as ierror, reactor, task
from twisted.python.failure import Failure
from twisted.trial import unittest

from rcm_platform import rcmp_process
from rcm_platform.rcmp_process import EXITED, FAILED, RUNNING, STARTING, STOPPING, ProcessTable
from tests.support.processes import group_alive


class RecordingOs:
    """An OsFacade that records spawns and signals instead of making them; tests end children by hand."""

    def __init__(self):
        self.spawned = []          # (protocol, argv, env)
        self.signals = []          # ("group"|"process", pid, sig)
        self.alive_groups = set()
        self.alive_processes = {}  # pid -> start time
        self.children = {}         # pid -> {descendant pid: start time}
        self.next_pid = 1000
        self.fail_spawn = None

    def spawn(self, proto, argv, env, cwd=None, user=None):
        if self.fail_spawn:
            raise self.fail_spawn
        self.next_pid += 1
        self.spawned.append((proto, list(argv), env))
        self.alive_groups.add(self.next_pid)
        return self.next_pid

    def signal_group(self, pgid, sig):
        self.signals.append(("group", pgid, sig))
        return pgid in self.alive_groups

    def signal_child(self, pid, sig):
        self.signals.append(("child", pid, sig))
        return True

    def signal_process(self, pid, start_time, sig):
        self.signals.append(("process", pid, sig))
        return self.alive_processes.get(pid) == start_time

    def group_alive(self, pgid):
        return pgid in self.alive_groups

    def process_alive(self, pid, start_time):
        return self.alive_processes.get(pid) == start_time

    def is_group_leader(self, pid):
        return True

    def descendants(self, pid, max_age=0.0):
        return dict(self.children.get(pid, {}))

    # test helpers
    def end(self, managed, code=0, sig=None, group_too=True):
        """The child is reaped (as Twisted's processEnded reports it)."""
        if group_too:
            self.alive_groups.discard(managed.pid)
        proto = next(p for p, _, _ in self.spawned if p.managed is managed)
        if code == 0 and sig is None:
            reason = Failure(ierror.ProcessDone(0))
        else:
            reason = Failure(ierror.ProcessTerminated(code, sig))
        proto.processExited(reason)
        proto.processEnded(reason)

    def sent(self, pid):
        return [s for kind, p, s in self.signals if p == pid and kind == "group"]


def make_table(tmp_path, **kwargs):
    clock = task.Clock()
    fake = RecordingOs()
    kwargs.setdefault("settle_time", 1.0)
    table = ProcessTable(clock, str(tmp_path / "log"), os_facade=fake, **kwargs)
    return table, clock, fake


def spawn(table, key="item", core=False):
    return table.spawn(key, ["rosrun", "pkg", "node"], {"PATH": "/usr/bin"}, key, core=core)


def fired(d):
    results = []
    d.addBoth(results.append)
    return results


# -- one test per transition ------------------------------------------------------------------------------

def test_spawn_is_starting_until_settle_time(tmp_path):
    table, clock, fake = make_table(tmp_path)
    mp = spawn(table)
    assert mp.state == STARTING and mp.pid == 1001
    clock.advance(0.99)
    assert mp.state == STARTING


def test_starting_to_running_after_settle_time(tmp_path):
    table, clock, fake = make_table(tmp_path)
    mp = spawn(table)
    settled = fired(mp.when_settled())
    clock.advance(1.0)
    assert mp.state == RUNNING
    assert settled == [True]
    assert fired(mp.when_settled()) == [True]


def test_starting_to_failed_when_it_exits_before_settling(tmp_path):
    table, clock, fake = make_table(tmp_path)
    mp = spawn(table)
    settled = fired(mp.when_settled())
    mp._output(b"\x1b[31m[rospack] Error: package 'nope' not found\x1b[0m\n")
    clock.advance(0.2)
    fake.end(mp, code=1)
    assert mp.state == FAILED
    assert settled == [False]
    assert mp.error.startswith("exited with status 1 before it settled")
    assert "[rospack] Error: package 'nope' not found" in mp.error
    clock.advance(5)
    assert mp.state == FAILED  # the cancelled settle timer does not revive it


def test_starting_to_failed_even_with_status_zero(tmp_path):
    table, clock, fake = make_table(tmp_path)
    mp = spawn(table)
    fake.end(mp, code=0)
    assert mp.state == FAILED
    assert "exited with status 0 before it settled (no output)" == mp.error


def test_running_to_failed_when_it_dies_unasked(tmp_path):
    table, clock, fake = make_table(tmp_path)
    mp = spawn(table)
    seen = []
    mp.listeners.append(lambda m, old, new: seen.append((old, new)))
    clock.advance(3)
    mp._output(b"Traceback...\nRuntimeError: lidar gone")
    fake.end(mp, sig=signal.SIGSEGV)
    assert mp.state == FAILED
    assert seen == [(STARTING, RUNNING), (RUNNING, FAILED)]
    assert mp.error.startswith(f"killed by signal {int(signal.SIGSEGV)} after running 3.0 s")
    assert mp.error.endswith("RuntimeError: lidar gone")


def test_failed_when_spawn_itself_fails(tmp_path):
    table, clock, fake = make_table(tmp_path)
    fake.fail_spawn = OSError(2, "No such file or directory")
    mp = spawn(table)
    assert mp.state == FAILED and mp.pid is None
    assert "could not start rosrun" in mp.error
    assert fired(mp.stop()) == [None]


def test_running_to_stopping_sends_sigint_to_the_group(tmp_path):
    table, clock, fake = make_table(tmp_path)
    mp = spawn(table)
    clock.advance(1)
    d = fired(table.stop("item"))
    assert mp.state == STOPPING
    assert fake.sent(mp.pid) == [signal.SIGINT]
    assert d == []


def test_starting_to_stopping(tmp_path):
    table, clock, fake = make_table(tmp_path)
    mp = spawn(table)
    settled = fired(mp.when_settled())
    table.stop("item")
    assert mp.state == STOPPING and settled == [False]
    clock.advance(2)
    assert mp.state == STOPPING  # the settle timer never makes a stopping child running


def test_stopping_to_exited_only_when_reaped(tmp_path):
    table, clock, fake = make_table(tmp_path)
    mp = spawn(table)
    clock.advance(1)
    d = fired(table.stop("item"))
    fake.alive_groups.discard(mp.pid)   # the group is gone, but the child has not been reaped yet
    clock.advance(0.5)
    assert mp.state == STOPPING and d == []
    fake.end(mp, sig=signal.SIGINT)
    assert mp.state == EXITED and d == [None]
    assert fake.sent(mp.pid) == [signal.SIGINT]


def test_stop_escalates_sigint_sigterm_sigkill(tmp_path):
    table, clock, fake = make_table(tmp_path, stop_timeouts=(5.0, 2.0))
    mp = spawn(table)
    clock.advance(1)
    d = fired(table.stop("item"))
    clock.advance(4.9)
    assert fake.sent(mp.pid) == [signal.SIGINT]
    clock.advance(0.2)
    assert fake.sent(mp.pid) == [signal.SIGINT, signal.SIGTERM]
    clock.advance(1.9)
    assert fake.sent(mp.pid) == [signal.SIGINT, signal.SIGTERM]
    clock.advance(0.2)
    assert fake.sent(mp.pid) == [signal.SIGINT, signal.SIGTERM, signal.SIGKILL]
    assert d == [] and mp.state == STOPPING
    fake.end(mp, sig=signal.SIGKILL)
    assert mp.state == EXITED and d == [None]


def test_stop_timeouts_are_configurable(tmp_path):
    table, clock, fake = make_table(tmp_path, stop_timeouts=(0.5, 0.3))
    mp = spawn(table)
    table.stop("item")
    clock.advance(0.5)
    clock.advance(0.3)
    assert fake.sent(mp.pid) == [signal.SIGINT, signal.SIGTERM, signal.SIGKILL]


def test_descendants_in_their_own_sessions_get_sigterm_and_sigkill(tmp_path):
    table, clock, fake = make_table(tmp_path)
    mp = spawn(table)
    fake.children[mp.pid] = {2001: 77}      # e.g. a node roslaunch put in a session of its own
    fake.alive_processes[2001] = 77
    d = fired(table.stop("item"))
    fake.end(mp, sig=signal.SIGINT)          # the launcher went, its node did not
    clock.advance(1)
    assert mp.state == STOPPING and d == []
    clock.advance(4)
    assert ("process", 2001, signal.SIGTERM) in fake.signals
    clock.advance(2)
    assert ("process", 2001, signal.SIGKILL) in fake.signals
    assert ("group", 2001, signal.SIGKILL) in fake.signals
    del fake.alive_processes[2001]
    clock.advance(0.1)
    assert mp.state == EXITED and d == [None]


def test_stop_fires_only_when_the_whole_group_is_gone(tmp_path):
    table, clock, fake = make_table(tmp_path)
    mp = spawn(table)
    d = fired(table.stop("item"))
    fake.end(mp, sig=signal.SIGINT, group_too=False)  # a grandchild in the group lingers
    clock.advance(1)
    assert mp.state == STOPPING and d == []
    fake.alive_groups.discard(mp.pid)
    clock.advance(0.1)
    assert mp.state == EXITED and d == [None]


def test_no_such_process_means_already_going(tmp_path):
    table, clock, fake = make_table(tmp_path)
    mp = spawn(table)
    fake.alive_groups.discard(mp.pid)  # killpg will say "no such process"
    d = fired(table.stop("item"))
    assert mp.state == STOPPING
    assert ("child", mp.pid, signal.SIGINT) in fake.signals  # not reaped yet: maybe before its setsid
    fake.end(mp, sig=signal.SIGINT)
    assert d == [None] and mp.state == EXITED


def test_stop_twice_gives_both_callers_the_end(tmp_path):
    table, clock, fake = make_table(tmp_path)
    mp = spawn(table)
    first, second = fired(table.stop("item")), fired(table.stop("item"))
    assert fake.sent(mp.pid) == [signal.SIGINT]
    fake.end(mp, sig=signal.SIGINT)
    assert first == [None] and second == [None]


def test_failed_child_with_leftover_group_is_swept(tmp_path):
    table, clock, fake = make_table(tmp_path)
    mp = spawn(table)
    clock.advance(2)
    fake.end(mp, code=1, group_too=False)
    assert mp.state == FAILED
    assert fake.sent(mp.pid) == [signal.SIGTERM]
    d = fired(table.stop("item"))
    clock.advance(2)
    assert fake.sent(mp.pid)[-1] == signal.SIGKILL
    fake.alive_groups.discard(mp.pid)
    clock.advance(0.1)
    assert d == [None] and mp.state == FAILED


def test_descendants_of_a_child_that_dies_are_swept(tmp_path):
    table, clock, fake = make_table(tmp_path)
    mp = spawn(table)
    fake.children[mp.pid] = {2002: 5}
    fake.alive_processes[2002] = 5
    clock.advance(1)                     # settled: its descendants are remembered
    fake.end(mp, code=1)                 # dies unasked; its node in a session of its own lives on
    assert mp.state == FAILED
    assert ("process", 2002, signal.SIGTERM) in fake.signals
    clock.advance(2)
    assert ("process", 2002, signal.SIGKILL) in fake.signals
    del fake.alive_processes[2002]
    d = fired(table.stop("item"))
    assert d == [None]


def test_stop_of_unknown_or_finished_child_fires_at_once(tmp_path):
    table, clock, fake = make_table(tmp_path)
    assert fired(table.stop("nobody")) == [None]
    mp = spawn(table)
    fake.end(mp, code=2)
    assert fired(table.stop("item")) == [None]


def test_invalid_transitions_are_refused(tmp_path):
    table, clock, fake = make_table(tmp_path)
    mp = spawn(table)
    with pytest.raises(rcmp_process.InvalidTransition):
        mp._transition(EXITED, "not stopping")
    fake.end(mp, code=1)
    for target in (RUNNING, STOPPING, FAILED, EXITED):
        with pytest.raises(rcmp_process.InvalidTransition):
            mp._transition(target, "from failed")
    with pytest.raises(rcmp_process.InvalidTransition):
        mp._transition("zombie", "not a state")


def test_transitions_are_logged_old_to_new(tmp_path, caplog):
    table, clock, fake = make_table(tmp_path)
    caplog.set_level("INFO", logger="rcm_platform.rcmp_process")
    mp = spawn(table)
    clock.advance(1)
    assert f"process item (pid {mp.pid}): starting -> running" in caplog.text


def test_spawn_refuses_a_live_key_and_shell_strings(tmp_path):
    table, clock, fake = make_table(tmp_path)
    spawn(table)
    with pytest.raises(ValueError):
        spawn(table)
    with pytest.raises(TypeError):
        table.spawn("x", "rosrun pkg node", {}, "x")
    fake.end(table.get("item"), code=1)
    assert spawn(table).state == STARTING  # a finished key can be reused


def test_stop_all_stops_ros_masters_last(tmp_path):
    table, clock, fake = make_table(tmp_path)
    master = spawn(table, "master", core=True)
    node_a, node_b = spawn(table, "a"), spawn(table, "b")
    d = fired(table.stop_all())
    assert fake.sent(node_a.pid) == [signal.SIGINT] and fake.sent(node_b.pid) == [signal.SIGINT]
    assert fake.sent(master.pid) == []
    fake.end(node_a, sig=signal.SIGINT)
    assert fake.sent(master.pid) == []
    fake.end(node_b, sig=signal.SIGINT)
    assert fake.sent(master.pid) == [signal.SIGINT]
    fake.end(master, sig=signal.SIGINT)
    assert d == [None]


def test_output_goes_to_a_capped_log_file(tmp_path):
    table, clock, fake = make_table(tmp_path, log_max_bytes=300)
    mp = spawn(table, "node/with slash")
    assert mp.log_path == os.path.join(str(tmp_path / "log"), "node_with_slash.log")
    for i in range(40):
        mp._output(f"line {i:03d}\n".encode())
    assert os.path.getsize(mp.log_path) <= 300
    assert os.path.getsize(mp.log_path + ".1") <= 300
    with open(mp.log_path) as f:
        assert "line 039" in f.read()
    assert mp.tail(2) == "line 038\nline 039"


# -- real children ----------------------------------------------------------------------------------------

PY = sys.executable if sys.executable.startswith("/usr/bin") else "/usr/bin/python3"
IGNORE_SIGINT = "import signal, time, sys; signal.signal(signal.SIGINT, signal.SIG_IGN); print('ready', flush=True); time.sleep(60)"
SPAWN_GRANDCHILD = ("import subprocess, sys, time; subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'], "
                    "start_new_session=True); print('ready', flush=True); time.sleep(60)")


class RealProcessTests(unittest.TestCase):
    """Real children under the real reactor: setsid, pid == pgid, escalation, output, leftovers."""

    timeout = 30

    def setUp(self):
        self.log_dir = tempfile.mkdtemp(prefix="ms-table-")
        self.addCleanup(shutil.rmtree, self.log_dir, True)
        self.table = ProcessTable(reactor, self.log_dir, settle_time=0.3, stop_timeouts=(0.5, 0.5))
        self.pgids = []

    @defer.inlineCallbacks
    def tearDown(self):
        yield self.table.stop_all()
        for pgid in self.pgids:
            self.assertFalse(group_alive(pgid), f"process group {pgid} left behind")

    def spawn(self, key, code):
        mp = self.table.spawn(key, [PY, "-c", code], dict(os.environ), key)
        self.pgids.append(mp.pid)
        return mp

    @defer.inlineCallbacks
    def wait_for(self, condition, timeout=10.0):
        deadline = reactor.seconds() + timeout
        while not condition():
            self.assertLess(reactor.seconds(), deadline, "condition not met in time")
            yield task.deferLater(reactor, 0.02, lambda: None)

    @defer.inlineCallbacks
    def test_child_runs_in_its_own_session_with_pid_as_group(self):
        mp = self.spawn("sleeper", "import time; print('up', flush=True); time.sleep(60)")
        settled = yield mp.when_settled()
        self.assertTrue(settled)
        self.assertEqual(os.getpgid(mp.pid), mp.pid)
        self.assertEqual(os.getsid(mp.pid), mp.pid)
        self.assertNotEqual(os.getpgid(mp.pid), os.getpgid(0))
        yield self.wait_for(lambda: "up" in mp.tail())
        yield self.table.stop("sleeper")
        self.assertEqual(mp.state, EXITED)
        self.assertEqual(mp.exit_signal, signal.SIGINT)  # python dies of KeyboardInterrupt -> SIGINT status
        with open(mp.log_path) as f:
            self.assertIn("up", f.read())

    @defer.inlineCallbacks
    def test_crashing_child_fails_with_its_last_output(self):
        mp = self.spawn("crasher", "import sys; sys.stderr.write('cannot open /dev/lidar\\n'); sys.exit(3)")
        settled = yield mp.when_settled()
        self.assertFalse(settled)
        self.assertEqual(mp.state, FAILED)
        self.assertEqual(mp.exit_code, 3)
        self.assertIn("cannot open /dev/lidar", mp.error)

    @defer.inlineCallbacks
    def test_child_ignoring_sigint_is_terminated(self):
        mp = self.spawn("stubborn", IGNORE_SIGINT)
        yield self.wait_for(lambda: "ready" in mp.tail())
        start = reactor.seconds()
        yield self.table.stop("stubborn")
        self.assertEqual(mp.state, EXITED)
        self.assertEqual(mp.exit_signal, signal.SIGTERM)
        self.assertGreaterEqual(reactor.seconds() - start, 0.45)

    @defer.inlineCallbacks
    def test_descendant_in_its_own_session_is_stopped_too(self):
        mp = self.spawn("parent", SPAWN_GRANDCHILD)
        yield self.wait_for(lambda: "ready" in mp.tail())
        grandchildren = rcmp_process.OsFacade(reactor).descendants(mp.pid)
        self.assertEqual(len(grandchildren), 1)
        self.pgids.extend(grandchildren)
        yield self.table.stop("parent")
        self.assertEqual(mp.state, EXITED)
        for pid in grandchildren:
            self.assertFalse(group_alive(pid), "the grandchild in its own session survived")

    @defer.inlineCallbacks
    def test_descendant_of_a_crashed_child_is_swept(self):
        code = SPAWN_GRANDCHILD.replace(
            "print('ready', flush=True); time.sleep(60)", "print('ready', flush=True); time.sleep(0.8); sys.exit(1)")
        mp = self.spawn("crashing-parent", code)
        settled = yield mp.when_settled()
        self.assertTrue(settled)
        grandchildren = rcmp_process.OsFacade(reactor).descendants(mp.pid)
        self.assertEqual(len(grandchildren), 1)
        self.pgids.extend(grandchildren)
        yield self.wait_for(lambda: mp.state == FAILED)
        yield self.wait_for(lambda: not any(group_alive(pid) for pid in grandchildren))

    @defer.inlineCallbacks
    def test_a_child_is_spawned_without_a_fork_and_gets_only_its_own_descriptors(self):
        """Children start through posix_spawn (the agent is never forked): stdin is /dev/null, stdout and stderr
        the log pipes, nothing else of the agent's (even a descriptor left inheritable), signals the agent
        ignores back to their defaults, and its own session."""
        leak_r, leak_w = os.pipe()
        os.set_inheritable(leak_w, True)
        self.addCleanup(os.close, leak_r)
        self.addCleanup(os.close, leak_w)
        code = ("import os, sys; print('fds', sorted(int(f) for f in os.listdir('/proc/self/fd'))); "
                "print('stdin', os.readlink('/proc/self/fd/0')); "
                "print('session', os.getsid(0) == os.getpid(), flush=True); sys.stderr.write('to the log\\n')")
        mp = self.spawn("fds", code)
        yield self.wait_for(lambda: mp.state in (FAILED, EXITED) or "session" in mp.tail())
        out = mp.tail(10)
        self.assertIn("fds [0, 1, 2, 3]", out)       # 3: the listing's own descriptor
        self.assertIn("stdin /dev/null", out)
        self.assertIn("session True", out)
        yield self.wait_for(lambda: "to the log" in mp.tail())
        # Python ignores SIGPIPE and SIGXFSZ; a child (cat, which leaves its signals alone) ignores nothing
        cat = self.table.spawn("signals", ["/bin/cat", "/proc/self/status"], dict(os.environ), "signals")
        self.pgids.append(cat.pid)
        yield self.wait_for(lambda: "SigIgn" in cat.tail(80))
        ignored = int(next(l for l in cat.tail(80).splitlines() if l.startswith("SigIgn:")).split()[1], 16)
        for sig in (signal.SIGPIPE, signal.SIGXFSZ):
            self.assertFalse(ignored & (1 << (sig - 1)), f"{sig!r} still ignored in the child")

    def test_a_recent_proc_scan_may_serve_but_a_plain_look_is_fresh(self):
        facade = rcmp_process.OsFacade(reactor)
        facade.descendants(os.getpid(), max_age=60)             # scans /proc, remembered
        child = subprocess.Popen(["/bin/sleep", "30"])
        try:
            self.assertNotIn(child.pid, facade.descendants(os.getpid(), max_age=60))   # the old scan served
            self.assertIn(child.pid, facade.descendants(os.getpid()))                  # afresh
            self.assertIn(child.pid, facade.descendants(os.getpid(), max_age=60))      # and remembered anew
        finally:
            child.kill()
            child.wait()

    def test_missing_executable_fails_with_the_reason(self):
        mp = self.table.spawn("ghost", ["/nonexistent/ghost-binary"], dict(os.environ), "ghost")
        self.pgids.append(mp.pid)
        d = mp.when_settled()

        def check(settled):
            self.assertFalse(settled)
            self.assertEqual(mp.state, FAILED)
            self.assertIn("ghost-binary", mp.error)
        return d.addCallback(check)

    @defer.inlineCallbacks
    def test_stopping_the_agents_services_stops_what_they_left_in_the_table(self):
        """TableService: the last safety net. An agent service that forgets a child does not leave it running."""
        from twisted.application import service
        top = rcmp_process.TableService(self.table)
        forgetful = service.Service()             # an agent whose own teardown stops nothing
        forgetful.setServiceParent(top)
        top.startService()
        mp = self.spawn("left", "import time; time.sleep(60)")
        yield mp.when_settled()
        yield top.stopService()
        self.assertEqual(mp.state, EXITED)
        self.assertFalse(group_alive(mp.pid))


AGENT = """
import os, sys
from twisted.internet import reactor
from rcm_platform.rcmp_process import ProcessTable
table = ProcessTable(reactor, sys.argv[1])
def start():
    child = table.spawn("sleeper", [sys.executable, "-c", "import time; time.sleep(120)"], dict(os.environ), "s")
    print(child.pid, flush=True)
reactor.callWhenRunning(start)
reactor.run()
"""


def test_children_die_with_a_killed_agent(procs, tmp_path):
    """--pdeathsig: SIGKILL the agent and its children get SIGTERM from the kernel; nothing is left."""
    from tests.support.polling import wait_until
    env = dict(os.environ, PYTHONPATH=os.getcwd() + ":" + os.environ.get("PYTHONPATH", ""))
    agent = procs.start(["/usr/bin/python3", "-c", AGENT, str(tmp_path / "agent-log")], env=env, name="agent")
    child_pid = int(wait_until(lambda: procs.output(agent).strip().splitlines()[0], timeout=20,
                               message="the agent to start its child"))
    wait_until(lambda: group_alive(child_pid), timeout=10, message="the child's own group (after setsid)")
    os.kill(agent.pid, signal.SIGKILL)
    wait_until(lambda: not group_alive(child_pid), timeout=10, message="the orphaned child to die")
