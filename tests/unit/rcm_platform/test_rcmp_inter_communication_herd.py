"""A herd at the agent port, over real loopback TCP: while ``max_unanswered`` connections are open and not admitted
the listener stops accepting (the kernel queues the others), and it accepts again once half of them are answered
or gone, then every queued connection gets in; the accept queue asks for the kernel's ``somaxconn``."""

import socket

from twisted.internet import defer, reactor, task
from twisted.trial import unittest

from rcm_platform import rcmp_inter_communication as ic
from tests.unit.rcm_platform.test_rcmp_event import until


class Silent:
    """A listener's handler that never answers anything (hellos stay unanswered)."""

    def request_received(self, peer, op, body):
        return defer.Deferred()


class HerdTests(unittest.TestCase):

    def setUp(self):
        self.listening = ic.listen(reactor, "127.0.0.1", 0, Silent(), max_connections=100, max_per_address=100,
                                   max_unanswered=4)
        self.addCleanup(self.listening.stopListening)
        self.factory = self.listening.factory
        self.sockets = []

    def tearDown(self):
        for sock in self.sockets:
            sock.close()
        for peer in list(self.factory.peers):
            peer.abort("test over")

    def connect(self, count):
        for _ in range(count):
            sock = socket.create_connection(("127.0.0.1", self.listening.getHost().port), timeout=5)
            self.sockets.append(sock)    # the kernel completes the handshake even while we do not accept

    def accepting(self):
        return self.listening in reactor.getReaders()

    @defer.inlineCallbacks
    def turns(self, count=5):
        """Let the reactor run ``count`` turns (reading whatever is ready)."""
        for _ in range(count):
            yield task.deferLater(reactor, 0, lambda: None)

    @defer.inlineCallbacks
    def test_accepting_pauses_while_hellos_wait_and_resumes_when_half_are_answered(self):
        self.connect(4)
        yield until(lambda: self.factory.paused)
        self.assertFalse(self.accepting())
        self.connect(4)                                     # the kernel completes them; we do not accept
        yield self.turns()
        self.assertEqual(len(self.factory.peers), 4)
        self.assertEqual(self.factory.unanswered, 4)
        peers = list(self.factory.peers)
        peers[0].admit()                                    # one answered: three waiting, still paused
        self.assertTrue(self.factory.paused)
        yield self.turns()
        self.assertEqual(len(self.factory.peers), 4)
        peers[1].abort("refused")                           # one gone: two waiting, half: accept again
        yield until(lambda: len(self.factory.peers) == 7)   # the queued four got in (and paused it again)
        self.assertEqual(self.factory.unanswered, 6)
        self.assertTrue(self.factory.paused)
        self.assertEqual(self.factory.pauses, 2)

    @defer.inlineCallbacks
    def test_admitted_connections_do_not_count(self):
        self.connect(3)
        yield until(lambda: len(self.factory.peers) == 3)
        for peer in self.factory.peers:
            peer.admit()
            peer.admit()                                    # twice is once
        self.assertEqual(self.factory.unanswered, 0)
        self.connect(3)
        yield until(lambda: len(self.factory.peers) == 6)
        self.assertFalse(self.factory.paused)
        self.assertTrue(self.accepting())

    @defer.inlineCallbacks
    def test_a_listener_stopped_while_paused_is_not_resumed(self):
        self.connect(4)
        yield until(lambda: self.factory.paused)
        yield self.listening.stopListening()
        for peer in list(self.factory.peers):
            peer.abort("gone")
        yield until(lambda: not self.factory.peers)
        self.assertFalse(self.accepting())

    def test_the_accept_queue_asks_for_the_kernels_cap(self):
        with open(ic.SOMAXCONN) as f:
            self.assertEqual(ic.somaxconn(), int(f.read()))
        self.assertEqual(self.listening.backlog, min(100, ic.somaxconn()))
