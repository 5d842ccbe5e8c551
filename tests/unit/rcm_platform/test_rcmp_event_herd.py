"""A fleet's hellos at the real MasterAgent over loopback TCP: the first ``HELLO_LINES`` accepted hellos of a window
are logged one line each, the rest counted in one line at the info level (a herd is ordinary news, not a warning);
every hello is still answered and timed."""

import logging

from twisted.internet import defer

from rcm_platform import rcmp_event
from tests.unit.rcm_platform.test_rcmp_event_admission import MasterCase, hello_body, until

HERD = rcmp_event.HELLO_LINES + 5


class HelloLinesTests(MasterCase):

    provisioned = tuple(f"robot{n}" for n in range(HERD))

    @defer.inlineCallbacks
    def test_a_herds_hellos_are_logged_up_to_the_budget_then_counted(self):
        timed = []
        self.master.timing_observers.append(lambda what, seconds: timed.append(what))
        peers = []
        for n in range(HERD):
            peer = yield self.connect(f"127.0.1.{n + 1}")
            peers.append(peer.request("hello", hello_body(f"robot{n}", f"127.0.1.{n + 1}"), timeout=5))
        answers = yield defer.gatherResults(peers)
        self.assertTrue(all(a["accepted"] for a in answers))
        yield until(lambda: timed.count("hello") == HERD)
        lines = [line for line in self.log.lines if " connected from " in line]
        self.assertEqual(len(lines), rcmp_event.HELLO_LINES)
        self.master._hello_lines.flush()
        counted = [(line, level) for line, level in zip(self.log.lines, self.log.levels)
                   if "more lines about accepted hellos were left out" in line]
        self.assertEqual(counted, [("5 more lines about accepted hellos were left out of the log in the last 10 s",
                                    logging.INFO)])
