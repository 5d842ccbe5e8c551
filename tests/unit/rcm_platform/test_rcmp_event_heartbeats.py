"""Heartbeats between the real MasterAgent and agents over loopback TCP: the master sends no beats of its own to a
peer that beats itself (the peer's beats and their answers keep both sides' watchdogs fed), still beats a peer
that never beats (an older agent) and one that stopped, and both ends of an agent connection set TCP_NODELAY."""

import socket

from twisted.internet import defer, reactor, task
from twisted.trial import unittest

from rcm_platform import rcmp_inter_communication as ic
from tests.unit.rcm_platform.test_rcmp_event_admission import MasterCase, hello_body, until

INTERVAL = 0.2                   # the master's heartbeat_interval in these tests (test_rcmp_event.config)


class Counting:
    """A client handler that answers what a robot would and counts the master's heartbeats."""

    def __init__(self):
        self.beats = 0

    def request_received(self, peer, op, body):
        if op == "heartbeat":
            self.beats += 1
        return {"ros_master_uri": body.get("ros_master_uri"), "items": []} if op == "start_items" else {}


class BeatsTests(MasterCase):

    @defer.inlineCallbacks
    def accepted(self, source="127.0.0.2"):
        handler = Counting()
        peer = yield ic.connect(reactor, "127.0.0.1", self.port, handler, bind_address=source)
        self.addCleanup(peer.abort, "test over")
        answer = yield peer.request("hello", hello_body("robot1"), timeout=5)
        self.assertTrue(answer["accepted"])
        return peer, handler

    def beating(self, peer):
        loop = task.LoopingCall(lambda: peer.request("heartbeat", {}, timeout=1).addErrback(lambda _: None))
        loop.start(INTERVAL)
        self.addCleanup(lambda: loop.running and loop.stop())
        return loop

    @defer.inlineCallbacks
    def wait(self, intervals):
        yield task.deferLater(reactor, intervals * INTERVAL, lambda: None)

    @defer.inlineCallbacks
    def test_a_peer_that_beats_itself_gets_no_beats_and_keeps_its_session(self):
        peer, handler = yield self.accepted()
        self.beating(peer)
        session = self.master.sessions["robot1"]
        yield self.wait(10)                                # three misses' worth, three times over
        self.assertFalse(session.ended)
        self.assertLessEqual(handler.beats, 1)             # at most one before its first beat arrived
        self.assertEqual(self.master.counters["heartbeats_sent_robot"], handler.beats)

    @defer.inlineCallbacks
    def test_a_peer_that_never_beats_gets_the_masters_beats(self):
        peer, handler = yield self.accepted()
        session = self.master.sessions["robot1"]
        yield until(lambda: handler.beats >= 5)
        self.assertFalse(session.ended)                    # its answers to the master's beats keep it alive
        self.assertGreaterEqual(self.master.counters["heartbeats_sent_robot"], 5)

    @defer.inlineCallbacks
    def test_a_peer_that_stops_beating_gets_the_masters_beats_again(self):
        peer, handler = yield self.accepted()
        loop = self.beating(peer)
        yield self.wait(5)
        before = handler.beats
        loop.stop()
        yield until(lambda: handler.beats >= before + 3)
        self.assertFalse(self.master.sessions["robot1"].ended)

    @defer.inlineCallbacks
    def test_a_real_robot_agent_is_not_beaten_by_the_master(self):
        agent, _ = self.robot()
        yield until(lambda: agent.accepted)
        yield self.wait(10)
        self.assertTrue(agent.accepted)
        self.assertFalse(self.master.sessions["robot1"].ended)
        self.assertLessEqual(self.master.counters["heartbeats_sent_robot"], 1)


class NoDelayTests(unittest.TestCase):

    @defer.inlineCallbacks
    def test_both_ends_set_tcp_nodelay(self):
        accepted = []
        handler = type("H", (), {"request_received": lambda self, peer, op, body: {},
                                 "peer_connected": lambda self, peer: accepted.append(peer)})()
        listening = ic.listen(reactor, "127.0.0.1", 0, handler)
        self.addCleanup(listening.stopListening)
        client = yield ic.connect(reactor, "127.0.0.1", listening.getHost().port, handler)
        self.addCleanup(client.abort, "test over")
        yield until(lambda: accepted)
        for peer in (client, accepted[0]):
            flag = peer.transport.getHandle().getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY)
            self.assertTrue(flag, peer)
