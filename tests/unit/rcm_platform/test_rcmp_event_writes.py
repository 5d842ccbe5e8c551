"""The master's live-state writes (``rcmp_event._BatchedWrites``) on a real RoboticsData: the writes asked for while
a batch runs go together into the next transaction, in the order asked; one that fails fails alone (a log line;
its caller goes on) while the others of its batch are kept; ``flush`` waits for everything asked before it."""

import logging
import os
import tempfile
import threading

from twisted.internet import defer
from twisted.trial import unittest

from rcm_platform import rcmp_event
from rcm_platform.rcmp_robotics_data import RoboticsData
from tests.unit.rcm_platform.test_rcmp_event import Logged, until


class BatchedWritesTests(unittest.TestCase):

    def setUp(self):
        folder = tempfile.mkdtemp()
        self.data = RoboticsData(os.path.join(folder, "robotics_data.db"))
        self.addCleanup(self.data.close)
        for name in ("r1", "r2", "r3"):
            self.data.provision_platform_instance(name, "fiware_base")
        self.batches = []
        real = self.data.write_batch

        def recorded(calls):
            self.batches.append([getattr(fn, "__name__", "?") for fn, _ in calls])
            return real(calls)
        self.data.write_batch = recorded
        self.writes = rcmp_event._BatchedWrites(self.data)
        self.gate = threading.Event()
        self.addCleanup(self.gate.set)
        self.log = Logged()
        logging.getLogger("rcmp").addHandler(self.log)
        self.addCleanup(logging.getLogger("rcmp").removeHandler, self.log)

    def gated(self):
        self.gate.wait(10)

    @defer.inlineCallbacks
    def test_writes_waiting_go_together_in_order(self):
        first = self.writes(self.gated)
        yield until(lambda: self.batches)                # the first batch runs (and waits for the gate)
        generation = self.data.generation
        later = [self.writes(self.data.set_connected, "r1", "198.51.100.6"),
                 self.writes(self.data.set_paired, "r1", True),
                 self.writes(self.data.set_connected, "r2", "198.51.100.7"),
                 self.writes(self.data.set_disconnected, "r2")]
        self.gate.set()
        yield first
        results = yield defer.gatherResults(later)
        self.assertEqual(results, [None, True, None, None])
        self.assertEqual(self.batches, [["gated"], ["set_connected", "set_paired", "set_connected",
                                                    "set_disconnected"]])
        self.assertEqual(self.data.generation, generation + 2)   # the gated batch, then one for the four
        self.assertEqual(self.data.platform_instance("r1")["paired"], True)
        self.assertEqual(self.data.platform_instance("r2")["connected"], False)

    @defer.inlineCallbacks
    def test_a_failing_write_fails_alone(self):
        first = self.writes(self.gated)
        yield until(lambda: self.batches)
        good = self.writes(self.data.set_connected, "r1", "198.51.100.6")
        bad = self.writes(self.data.set_connected, "ghost", "198.51.100.9")
        failures = []
        bad.addErrback(failures.append)
        after = self.writes(self.data.set_connected, "r3", "198.51.100.8")
        self.gate.set()
        yield defer.gatherResults([first, good, after])
        yield bad
        self.assertEqual(len(self.batches), 2)
        self.assertEqual(self.data.platform_instance("r1")["connected"], True)
        self.assertEqual(self.data.platform_instance("r3")["connected"], True)
        self.assertIsNone(self.data.platform_instance("ghost"))
        self.assertTrue(any("set_connected('ghost'" in line and "no platform instance" in line
                            for line in self.log.lines), self.log.lines)
        self.assertEqual(failures, [])                   # logged and handled: the caller goes on


    @defer.inlineCallbacks
    def test_a_failing_write_alone_is_logged_and_swallowed(self):
        done = self.writes(self.data.set_connected, "ghost", "198.51.100.9")
        result = yield done
        self.assertIsNone(result)                        # logged, then swallowed (see the log line)
        self.assertTrue(any("ghost" in line for line in self.log.lines))

    @defer.inlineCallbacks
    def test_flush_waits_for_what_was_asked_before_it(self):
        first = self.writes(self.gated)
        yield until(lambda: self.batches)
        self.writes(self.data.set_connected, "r1", "198.51.100.6")
        flushed = self.writes.flush()
        self.assertFalse(flushed.called)
        self.gate.set()
        yield flushed
        self.assertTrue(first.called)
        self.assertEqual(self.data.platform_instance("r1")["connected"], True)
        yield self.writes.flush()                        # nothing pending: at once

    @defer.inlineCallbacks
    def test_a_batch_is_bounded(self):
        self.patch(rcmp_event._BatchedWrites, "MAX_BATCH", 3)
        first = self.writes(self.gated)
        yield until(lambda: self.batches)
        later = [self.writes(self.data.set_paired, "r1", bool(n % 2)) for n in range(7)]
        self.gate.set()
        yield first
        yield defer.gatherResults(later)
        self.assertEqual([len(b) for b in self.batches], [1, 3, 3, 1])
        self.assertEqual(self.data.platform_instance("r1")["paired"], False)
