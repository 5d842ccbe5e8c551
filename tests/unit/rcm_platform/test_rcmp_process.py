"""rcmp_process.ProcessTable: one test per state transition, with a recording OS facade and task.Clock (no child
process is started)."""

import os
import signal

import pytest
from twisted.internet import error as ierror, task
from twisted.python.failure import Failure

from rcm_platform import rcmp_process
from rcm_platform.rcmp_process import EXITED, FAILED, RUNNING, STARTING, STOPPING, ProcessTable


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


def reaped_inside_the_spawn(fake):
    """Make ``fake`` spawn children that Twisted reaps before the spawn returns (they ended at once); returns the
    list their protocols go into."""
    protocols = []

    def spawn_and_end_at_once(proto, argv, env, cwd=None, user=None):
        proto.makeConnection(type("Transport", (), {"pid": 1234})())
        proto.processExited(Failure(ierror.ProcessTerminated(127, None)))
        protocols.append(proto)
        return 1234
    fake.spawn = spawn_and_end_at_once
    return protocols


def test_a_child_reaped_inside_the_spawn_is_judged_with_its_output_once_its_pipes_close(tmp_path):
    """Twisted reaps a child that ended at once (here: a wrapper that could not exec) from inside the spawn,
    before a byte of its output was read: the table knows its pid (the transport's, from connectionMade), waits
    for the output that says why, and leaves no timer behind."""
    table, clock, fake = make_table(tmp_path)
    protocols = reaped_inside_the_spawn(fake)
    mp = spawn(table)
    settled = fired(mp.when_settled())
    assert mp.pid == 1234 and settled == []
    protocols[0].outReceived(b"setsid: failed to execute rosrun: No such file or directory\n")
    protocols[0].processEnded(Failure(ierror.ProcessTerminated(127, None)))
    assert mp.state == FAILED and settled == [False]
    assert "before it settled" in mp.error and "failed to execute rosrun" in mp.error
    assert clock.getDelayedCalls() == []


def test_a_child_reaped_inside_the_spawn_whose_pipes_stay_open_is_judged_after_a_moment(tmp_path):
    table, clock, fake = make_table(tmp_path)
    reaped_inside_the_spawn(fake)
    mp = spawn(table)
    assert mp.state == STARTING
    clock.advance(rcmp_process.EARLY_END_OUTPUT_WAIT)
    assert mp.state == FAILED and "exited with status 127 before it settled" in mp.error
    assert clock.getDelayedCalls() == []


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
