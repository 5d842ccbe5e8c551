"""rcmp_process.ProcessTable with real children (setsid, process groups, escalation, logs) under a running Twisted
reactor, and children dying with a killed agent."""

import os
import shutil
import signal
import subprocess
import sys
import tempfile

from twisted.internet import defer, reactor, task
from twisted.trial import unittest

from rcm_platform import rcmp_process
from rcm_platform.rcmp_process import EXITED, FAILED, ProcessTable
from tests.support.processes import group_alive


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
