"""The agent-to-agent wire protocol over real loopback TCP: requests both ways, errors, limits, timeouts."""

import json
import struct

from twisted.internet import defer, reactor
from twisted.trial import unittest

from rcm_platform import rcmp_inter_communication as ic
from tests.support.polling import until_deferred


class Echo:
    """A handler: 'echo' returns its body, 'slow' never answers, 'boom' raises, 'no' refuses."""

    def __init__(self):
        self.connected = []
        self.lost = []
        self.never = []

    def peer_connected(self, peer):
        self.connected.append(peer)

    def peer_lost(self, peer, why):
        self.lost.append((peer, why))

    def request_received(self, peer, op, body):
        if op == "echo":
            return dict(body, echoed=True)
        if op == "slow":
            d = defer.Deferred()
            self.never.append(d)
            return d
        if op == "boom":
            raise RuntimeError("kaput")
        if op == "no":
            raise ic.Refused("not today", code="nope")
        raise ic.Refused(f"unknown op {op!r}", code="unknown_op")


def until(condition, timeout=5.0):
    return until_deferred(condition, timeout=timeout)


class ProtocolTests(unittest.TestCase):

    @defer.inlineCallbacks
    def setUp(self):
        self.server_handler = Echo()
        self.client_handler = Echo()
        self.port = yield ic.listen(reactor, "127.0.0.1", 0, self.server_handler)
        self.addCleanup(self.port.stopListening)
        port = self.port.getHost().port
        self.client = yield ic.connect(reactor, "127.0.0.1", port, self.client_handler)
        self.addCleanup(self._close)
        yield until(lambda: self.server_handler.connected)
        self.server = self.server_handler.connected[0]
        self.server.admit()          # the limits before admission have tests of their own

    @defer.inlineCallbacks
    def _close(self):
        for d in self.server_handler.never + self.client_handler.never:
            if not d.called:
                d.callback({})
        for peer in (self.client, self.server):
            peer.abort("test over")
        yield until(lambda: self.client.closed and self.server.closed)

    @defer.inlineCallbacks
    def test_request_answered_both_ways(self):
        answer = yield self.client.request("echo", {"x": 1}, timeout=2)
        self.assertEqual(answer, {"x": 1, "echoed": True})
        answer = yield self.server.request("echo", {"y": "é"}, timeout=2)
        self.assertEqual(answer, {"y": "é", "echoed": True})

    @defer.inlineCallbacks
    def test_many_requests_in_flight_match_their_answers(self):
        answers = yield defer.gatherResults([self.client.request("echo", {"n": n}) for n in range(50)])
        self.assertEqual([a["n"] for a in answers], list(range(50)))

    @defer.inlineCallbacks
    def test_refused_request_gets_err_and_connection_stays(self):
        with self.assertRaises(ic.RemoteError) as caught:
            yield self.client.request("no", {}, timeout=2)
        self.assertEqual((caught.exception.code, caught.exception.reason), ("nope", "not today"))
        answer = yield self.client.request("echo", {"still": "open"}, timeout=2)
        self.assertEqual(answer["still"], "open")

    @defer.inlineCallbacks
    def test_unknown_op_gets_err_and_connection_stays(self):
        with self.assertRaises(ic.RemoteError) as caught:
            yield self.client.request("teleport", {}, timeout=2)
        self.assertEqual(caught.exception.code, "unknown_op")
        self.assertFalse(self.client.closed)
        yield self.client.request("echo", {}, timeout=2)

    @defer.inlineCallbacks
    def test_handler_failure_is_an_internal_err(self):
        with self.assertRaises(ic.RemoteError) as caught:
            yield self.client.request("boom", {}, timeout=2)
        self.assertEqual(caught.exception.code, "internal")
        self.assertIn("kaput", caught.exception.reason)
        self.flushLoggedErrors()

    @defer.inlineCallbacks
    def test_unknown_version_gets_err_and_connection_stays(self):
        d = defer.Deferred()
        self.client.pending[900] = ("echo", d, reactor.callLater(2, lambda: None))
        self.client.sendString(json.dumps({"v": 7, "id": 900, "kind": "req", "op": "echo",
                                           "body": {}}).encode())
        with self.assertRaises(ic.RemoteError) as caught:
            yield d
        self.assertEqual(caught.exception.code, "unsupported_version")
        answer = yield self.client.request("echo", {"after": 1}, timeout=2)
        self.assertEqual(answer["after"], 1)

    @defer.inlineCallbacks
    def test_request_timeout_and_late_answer_ignored(self):
        started = reactor.seconds()
        with self.assertRaises(ic.RequestTimeout):
            yield self.client.request("slow", {}, timeout=0.2)
        self.assertGreaterEqual(reactor.seconds() - started, 0.19)
        self.assertEqual(self.client.pending, {})
        self.server_handler.never[0].callback({"late": True})   # answer arrives after the timeout
        answer = yield self.client.request("echo", {"next": 1}, timeout=2)
        self.assertEqual(answer, {"next": 1, "echoed": True})

    @defer.inlineCallbacks
    def test_oversize_frame_closes_the_connection_and_fails_pending(self):
        pending = self.client.request("slow", {}, timeout=5)
        yield until(lambda: self.server_handler.never)
        self.client.transport.write(struct.pack("!I", ic.MAX_FRAME + 1) + b"x" * 100)
        with self.assertRaises(ic.PeerGone):
            yield pending
        yield until(lambda: self.server.closed)
        self.assertIn("over the limit", self.server_handler.lost[0][1])

    @defer.inlineCallbacks
    def test_frame_at_the_limit_is_accepted(self):
        body = {"blob": "a" * (ic.MAX_FRAME - 200)}
        answer = yield self.client.request("echo", body, timeout=5)
        self.assertEqual(len(answer["blob"]), ic.MAX_FRAME - 200)

    @defer.inlineCallbacks
    def test_too_large_request_is_not_sent(self):
        with self.assertRaises(ic.ProtocolError):
            yield self.client.request("echo", {"blob": "a" * (ic.MAX_FRAME + 1)}, timeout=2)
        answer = yield self.client.request("echo", {"small": True}, timeout=2)
        self.assertTrue(answer["small"])

    @defer.inlineCallbacks
    def test_garbage_frames_close_the_connection(self):
        self.client.sendString(b"\xff not json")
        yield until(lambda: self.client.closed and self.server.closed)
        self.assertIn("not UTF-8 JSON", self.server_handler.lost[0][1])

    @defer.inlineCallbacks
    def test_frame_without_id_closes_the_connection(self):
        self.client.sendString(json.dumps({"v": 1, "kind": "req", "op": "echo", "body": {}}).encode())
        yield until(lambda: self.server.closed)
        self.assertIn("'id'", self.server_handler.lost[0][1])

    @defer.inlineCallbacks
    def test_non_object_body_closes_the_connection(self):
        self.client.sendString(json.dumps({"v": 1, "id": 3, "kind": "req", "op": "echo", "body": [1]}).encode())
        yield until(lambda: self.server.closed)

    @defer.inlineCallbacks
    def test_last_heard_moves_with_frames(self):
        before = self.server.last_heard
        yield self.client.request("echo", {}, timeout=2)
        self.assertGreaterEqual(self.server.last_heard, before)
        self.assertGreaterEqual(self.client.last_heard, before)

    @defer.inlineCallbacks
    def test_request_on_closed_peer_fails_at_once(self):
        self.client.close("done")
        yield until(lambda: self.client.closed)
        with self.assertRaises(ic.PeerGone):
            yield self.client.request("echo", {}, timeout=2)


class FrameTests(unittest.TestCase):

    def test_decode_rejects_what_it_cannot_route(self):
        bad = [b"[]", b"{}", b'{"id": "1", "kind": "req", "op": "x"}', b'{"id": 1, "kind": "ask", "op": "x"}',
               b'{"id": 1, "kind": "req", "op": ""}', b'{"id": true, "kind": "req", "op": "x"}',
               b'{"id": -1, "kind": "req", "op": "x"}']
        for data in bad:
            with self.assertRaises(ic.ProtocolError, msg=data):
                ic.decode_frame(data)

    def test_decode_defaults_body(self):
        self.assertEqual(ic.decode_frame(b'{"v":1,"id":0,"kind":"res","op":"x"}')["body"], {})

    def test_backoff_doubles_to_the_cap_and_resets(self):
        backoff = ic.Backoff(initial=0.25, factor=2.0, cap=5.0, jitter=0)
        delays = [backoff.next_delay() for _ in range(8)]
        self.assertEqual(delays, [0.25, 0.5, 1.0, 2.0, 4.0, 5.0, 5.0, 5.0])
        backoff.reset()
        self.assertEqual(backoff.next_delay(), 0.25)

    def test_backoff_is_jittered_so_a_fleet_spreads_out(self):
        firsts = [ic.Backoff(initial=0.25, cap=5.0, jitter=1.0).next_delay() for _ in range(40)]
        self.assertTrue(all(0.25 <= d <= 1.25 for d in firsts), firsts)
        self.assertGreater(len({round(d, 3) for d in firsts}), 30)     # not in lockstep
        self.assertGreater(max(firsts) - min(firsts), 0.5)

    def test_deeply_nested_json_is_a_protocol_error(self):
        with self.assertRaisesRegex(ic.ProtocolError, "nested too deeply"):
            ic.decode_frame(b'{"v":1,"id":1,"kind":"req","op":"x","body":' + b"[" * 100000 + b"]" * 100000 + b"}")

    def test_ops_are_short_words(self):
        for op in ("Hello", "a" * 33, "x-y", "x y", "\u00e9"):
            with self.assertRaises(ic.ProtocolError, msg=op):
                ic.decode_frame(json.dumps({"v": 1, "id": 1, "kind": "req", "op": op}).encode())


class StrictJsonTests(unittest.TestCase):
    """Nothing the agent sends holds a bare NaN or Infinity (strict parsers, a browser's JSON.parse, refuse them)."""

    @staticmethod
    def strict(text):
        def refuse(constant):
            raise ValueError(f"{constant} is not JSON")
        return json.loads(text, parse_constant=refuse)

    def test_non_finite_numbers_become_strings_everywhere_else_untouched(self):
        value = {"x": float("nan"), "ys": [float("inf"), -float("inf"), 1.5, 2], "t": (3, float("nan")),
                 "nested": {"deep": [{"v": float("nan")}]}, "s": "NaN", "n": None, "b": True}
        self.assertEqual(self.strict(ic.strict_dumps(value)), {
            "x": "NaN", "ys": ["Infinity", "-Infinity", 1.5, 2], "t": [3, "NaN"],
            "nested": {"deep": [{"v": "NaN"}]}, "s": "NaN", "n": None, "b": True})
        self.assertEqual(ic.strict_dumps({"a": [1.0, "x"]}, sort_keys=True), json.dumps({"a": [1.0, "x"]}))

    def test_an_agent_frame_with_nan_is_strict_json(self):
        data = ic.encode_frame({"v": 1, "id": 1, "kind": "req", "op": "item_exited",
                                "body": {"report": {"error": float("nan")}}})
        self.assertEqual(self.strict(data.decode())["body"]["report"]["error"], "NaN")


class DriverLinkTests(unittest.TestCase):
    """The agent's end of rcm_driver's port: the key on every line, garbage logged through a budget."""

    def link(self, key=None):
        try:
            from twisted.internet.testing import StringTransport
        except ImportError:      # Twisted before 19.7 (Ubuntu 20.04)
            from twisted.test.proto_helpers import StringTransport
        said = []
        link = ic.DriverLink("robot1", lambda cmd, name: said.append((cmd, name)), key=key)
        link.makeConnection(StringTransport())
        return link, said

    def test_each_line_carries_the_key_the_driver_was_started_with(self):
        link, _ = self.link(key="k" * 32)
        link.send("r_connection", "robot1")
        line = link.transport.value()
        self.assertTrue(line.endswith(b"\n"))
        self.assertEqual(json.loads(line), {"rcm_d_cmd": "r_connection", "r_name": "robot1", "key": "k" * 32})
        link, _ = self.link()
        link.send("r_disconnection", "robot1")
        self.assertEqual(json.loads(link.transport.value()), {"rcm_d_cmd": "r_disconnection", "r_name": "robot1"})

    def test_garbage_from_the_driver_is_budgeted_and_good_lines_still_count(self):
        link, said = self.link()
        for n in range(40):
            link.dataReceived(b'{"rcm_d_cmd": 7, "r_name": "' + b"x" * 3000 + b'"}\n')
        link.dataReceived(b'{"rcm_d_cmd": "e_created", "r_name": "robot1"}\n')
        self.assertEqual(said, [("e_created", "robot1")])
        self.assertEqual(link.garbage.left_out_total, 40 - link.garbage.burst)
