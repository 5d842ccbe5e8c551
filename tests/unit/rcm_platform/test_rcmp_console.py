"""The console's event stream (rcmp_console.Console) with Twisted's test tools: real RoboticsData (SQLite), the
RDAPI's own PlatformCommands, a real ProcessTable, requests from ``twisted.web.test.requesthelper`` and the trial
reactor. The service spaces are a small stand-in with the manager's interface (``spaces``, ``describe``,
``observers``)."""

import json
import os
import shutil
import tempfile

from twisted.internet import defer, reactor
from twisted.internet.address import IPv4Address
from twisted.trial import unittest
from twisted.web.test.requesthelper import DummyRequest

from rcm_platform import rcmp_console, rcmp_process
from rcm_platform.rcmp_platform_command import PlatformCommands
from rcm_platform.rcmp_robotics_data import RoboticsData
from tests.support.polling import until_deferred


class StreamRequest(DummyRequest):
    """A DummyRequest that accepts a push producer (DummyRequest only drives pull producers) and can be paused."""

    def __init__(self, path=b"/console/api/events", args=None, client="127.0.0.1"):
        super().__init__([])
        self.client = IPv4Address("TCP", client, 40000)
        self.path = path
        self.uri = path
        self.args = args or {}
        self.producer = None
        self.aborted = False
        self.transport = self

    def registerProducer(self, producer, streaming):
        self.producer = producer

    def unregisterProducer(self):
        self.producer = None

    def abortConnection(self):
        self.aborted = True

    def events(self):
        """[(event name, decoded data)] written so far; comments (heartbeats) as ("comment", text)."""
        found = []
        for block in b"".join(self.written).decode().split("\n\n"):
            if block.startswith(":"):
                found.append(("comment", block[1:].strip()))
                continue
            lines = dict(line.split(": ", 1) for line in block.splitlines() if ": " in line)
            if "event" in lines:
                found.append((lines["event"], json.loads(lines["data"])))
        return found

    def last(self, name):
        matching = [data for event, data in self.events() if event == name]
        return matching[-1] if matching else None


class FakeItem:
    def __init__(self, kind, name, process):
        self.kind, self.name, self.process, self.i_name, self.side = kind, name, process, "master", "S"


class FakeSpace:
    def __init__(self, name, items):
        self.name, self.items, self.ros_master_uri = name, items, None


class StandInSpaces:
    """What the console needs of a ServiceSpaceManager."""

    def __init__(self):
        self.spaces = {}
        self.observers = []

    def add(self, space):
        self.spaces[space.name] = space
        self._tell(space.name)

    def remove(self, name):
        del self.spaces[name]
        self._tell(name)

    def _tell(self, name):
        for observer in list(self.observers):
            observer(name)

    def describe(self, ss_name):
        space = self.spaces.get(ss_name)
        if space is None:
            return None
        nodes = []
        for item in space.items:
            entry = {"sn_name": item.name, "i_name": item.i_name, "state": item.process.state}
            if item.process.error:
                entry["error"] = item.process.error
            nodes.append(entry)
        return {"r_nodes": nodes, "r_launchers": [], "paired": all(n["state"] == "running" for n in nodes)}


class ConsoleCase(unittest.TestCase):
    """A console on real robotics data and a real (empty) process table, with a stand-in space manager."""

    limits = {"max_clients": 3}

    def setUp(self):
        tmp = tempfile.mkdtemp(prefix="console-stream-")
        self.addCleanup(shutil.rmtree, tmp, True)
        self.data = RoboticsData(os.path.join(tmp, "robotics_data.db"))
        self.addCleanup(self.data.close)
        self.table = rcmp_process.ProcessTable(reactor, os.path.join(tmp, "log"), settle_time=0.2,
                                          stop_timeouts=(1.0, 1.0))
        self.addCleanup(self.table.stop_all)
        self.spaces = StandInSpaces()
        self.console = rcmp_console.Console(reactor, self.data, PlatformCommands(self.data), self.spaces,
                                            self.table, coalesce=0.01, heartbeat=0.2, max_buffer=4096,
                                            **self.limits)
        self.console.start()
        self.addCleanup(self.console.stop)
        self.resource = rcmp_console.ConsoleResource(self.console)

    def open(self, args=None, client="127.0.0.1"):
        request = StreamRequest(args=args, client=client)
        result = self.resource.render(request)
        return request, result

    def wait_event(self, request, predicate, message):
        def found():
            return any(predicate(name, data) for name, data in request.events())
        return until_deferred(found, timeout=5.0, message=message)


class ConsoleStreamTest(ConsoleCase):
    @defer.inlineCallbacks
    def test_a_new_stream_gets_the_whole_state_first(self):
        self.data.provision_platform_instance("robot1", "empty")
        yield self.console.next_snapshot()
        request, result = self.open()
        self.assertEqual(result, rcmp_console.server.NOT_DONE_YET)
        self.assertEqual(request.responseHeaders.getRawHeaders(b"content-type"),
                         [b"text/event-stream; charset=utf-8"])
        yield self.wait_event(request, lambda n, d: n == "snapshot", "the snapshot")
        name, snapshot = [e for e in request.events() if e[0] != "comment"][0]
        self.assertEqual(name, "snapshot")
        self.assertEqual(snapshot["robots"], [{"pi_name": "robot1", "service_logic": "empty", "connected": False,
                                               "paired": False, "address": None}])
        self.assertEqual(sorted(snapshot["logics"]), ["empty", "fiware_base"])
        self.assertEqual(snapshot["spaces"], {})

    @defer.inlineCallbacks
    def test_connect_and_pair_are_pushed_as_patches_of_the_robots(self):
        self.data.provision_platform_instance("robot1", "empty")
        yield self.console.next_snapshot()
        request, _ = self.open()
        self.data.set_connected("robot1", "203.0.113.7")   # what the master's hello handler writes

        def robot1(data):
            return (data.get("robots") or {}).get("changed", {}).get("robot1", {})
        yield self.wait_event(request, lambda n, d: n == "patch" and robot1(d).get("connected"),
                              "the connection to be pushed")
        patch = request.last("patch")
        self.assertEqual(patch["robots"], {"changed": {"robot1": {
            "pi_name": "robot1", "service_logic": "empty", "connected": True, "paired": False,
            "address": "203.0.113.7"}}, "gone": []})
        self.assertNotIn("logics", patch)      # only what changed
        self.data.set_paired("robot1", True)
        yield self.wait_event(request, lambda n, d: n == "patch" and robot1(d).get("paired"),
                              "the pairing to be pushed")
        self.data.set_disconnected("robot1")
        yield self.wait_event(request, lambda n, d: n == "patch" and robot1(d) == {
            "pi_name": "robot1", "service_logic": "empty", "connected": False, "paired": False,
            "address": "203.0.113.7"}, "the disconnection to be pushed")

    @defer.inlineCallbacks
    def test_a_stream_gets_heartbeats_and_a_client_that_does_not_read_is_dropped(self):
        request, _ = self.open()
        yield self.wait_event(request, lambda n, d: n == "comment" and d == "heartbeat", "a heartbeat")
        stream = request.producer
        stream.pauseProducing()               # the connection's buffer is full: the client does not read
        written = len(request.written)
        for i in range(100):                  # a patch per robot, each some 150 bytes: 4096 reached long before
            self.data.provision_platform_instance(f"robot{i}", "empty")
            yield self.console.next_snapshot()
            if request.aborted:
                break
        self.assertTrue(request.aborted)
        self.assertEqual(len(request.written), written)
        self.assertNotIn(stream, self.console.streams)

    @defer.inlineCallbacks
    def test_streams_are_bounded_and_the_stop_ends_them(self):
        opened = [self.open()[0] for _ in range(3)]
        request = StreamRequest()
        body = self.resource.render(request)
        self.assertEqual(request.responseCode, 503)
        self.assertIn("already serves 3 streams", json.loads(body)["reason"])
        yield self.console.stop()
        self.assertTrue(all(r.finished for r in opened))

    def test_static_files_come_from_the_fixed_list_only(self):
        request = StreamRequest(path=b"/console/")
        body = self.resource.render(request)
        self.assertIn(b"RCM platform console", body)
        self.assertIn(b"default-src 'self'", request.responseHeaders.getRawHeaders(b"content-security-policy")[0])
        for path in (b"/console/../rcmp_node.py", b"/console/%2e%2e/rcmp_node.py", b"/console/nothing.js"):
            request = StreamRequest(path=path)
            self.resource.render(request)
            self.assertEqual(request.responseCode, 404, path)

    def test_a_bad_space_name_is_refused_with_the_rdapi_sentence(self):
        request = StreamRequest(path=b"/console/api/topic", args={b"ss_name": [b"../x"]})
        body = self.resource.render(request)
        self.assertEqual(request.responseCode, 400)
        self.assertIn("'ss_name'", json.loads(body)["reason"])
        request = StreamRequest(path=b"/console/api/topic", args={b"ss_name": [b"nobody"]})
        body = self.resource.render(request)
        self.assertEqual(request.responseCode, 404)
        self.assertEqual(json.loads(body)["reason"], "there is no running service space named 'nobody'")

    @defer.inlineCallbacks
    def test_a_process_that_is_not_a_watcher_is_closed_before_anything_is_read(self):
        from twisted.internet.endpoints import UNIXClientEndpoint, connectProtocol
        from twisted.internet.protocol import Protocol

        class Client(Protocol):
            def __init__(self):
                self.lost = defer.Deferred()

            def connectionLost(self, reason):
                self.lost.callback(None)
        path = self.console.watch_socket
        self.assertEqual(os.stat(path).st_mode & 0o777, 0o600)             # the agent's (and watchers') user only
        self.assertEqual(os.stat(os.path.dirname(path)).st_mode & 0o777, 0o700)
        for _ in range(3):
            client = yield connectProtocol(UNIXClientEndpoint(reactor, path), Client())
            client.transport.write(b'{"name": "robot1", "key": "guessed"}\n')
            yield client.lost                      # closed by the agent, not by the test
        self.assertEqual(self.console.notes.left_out_total, 0)
        self.assertTrue(all(w.link is None for w in self.console.watches.values()))

    def test_a_topic_name_that_is_not_one_is_refused(self):
        self.spaces.add(FakeSpace("robot3", []))
        for topic in (b"pose", b"/a b", b"/" + b"x" * 300):
            request = StreamRequest(path=b"/console/api/topic", args={b"ss_name": [b"robot3"], b"topic": [topic]})
            body = self.resource.render(request)
            self.assertEqual(request.responseCode, 400, topic)
            self.assertIn("ROS topic name", json.loads(body)["reason"])
        self.assertEqual(self.console.watches, {})

    @defer.inlineCallbacks
    def test_with_no_page_open_nothing_is_rebuilt_and_the_next_page_gets_the_present(self):
        yield self.console.next_snapshot()
        seq = self.console.seq
        for i in range(5):
            self.data.provision_platform_instance(f"quiet{i}", "empty")
        yield until_deferred(lambda: self.console.snapshot is None, message="the old snapshot to be dropped")
        self.assertIsNone(self.console._call)            # and none is scheduled
        self.assertEqual(self.console.seq, seq)          # no snapshot was built for nobody
        request, _ = self.open()
        yield self.wait_event(request, lambda n, d: n == "snapshot" and len(d["robots"]) == 5,
                              "a snapshot of the present")


class StreamPoolTest(ConsoleCase):
    """The streams are a pool with a share per address, and a stream must be read (issue 18 row 3)."""

    limits = {"max_clients": 6, "max_per_address": 2, "drain_deadline": 0.2, "stream_lifetime": 0.5}

    def test_one_address_holding_its_share_leaves_the_others_served(self):
        held = [self.open(client="127.0.0.2")[0] for _ in range(2)]
        self.assertTrue(all(r.responseCode == 200 for r in held))
        for _ in range(5):                      # the holder asks again and again: refused, nothing is held
            refused, body = self.open(client="127.0.0.2")
            self.assertEqual(refused.responseCode, 503)
            self.assertIn("2 streams to 127.0.0.2", json.loads(body)["reason"])
        operator, result = self.open(client="127.0.0.3")
        self.assertEqual((operator.responseCode, result), (200, rcmp_console.server.NOT_DONE_YET))
        topic = StreamRequest(path=b"/console/api/topic", args={b"ss_name": [b"robot9"]}, client="127.0.0.2")
        self.resource.render(topic)                            # topic streams count in the same share
        self.assertEqual(topic.responseCode, 503)
        held[0].processingFailed(Exception("gone"))             # one of the holder's streams closes: room again
        again, _ = self.open(client="127.0.0.2")
        self.assertEqual(again.responseCode, 200)

    @defer.inlineCallbacks
    def test_a_stream_whose_client_stops_reading_is_dropped_after_the_drain_deadline(self):
        reading, _ = self.open()
        reading.producer.pauseProducing()       # full for a moment, then drained: kept
        reading.producer.resumeProducing()
        stuck, _ = self.open(client="127.0.0.2")
        stuck.producer.pauseProducing()         # full and never drained
        yield until_deferred(lambda: stuck.aborted, message="the stream that is not read to be dropped")
        self.assertFalse(reading.aborted)
        self.assertEqual(self.console.caps.per_address, {"127.0.0.1": 1})

    @defer.inlineCallbacks
    def test_a_stream_ends_normally_at_its_lifetime_and_the_page_opens_the_next(self):
        request, _ = self.open()
        yield until_deferred(lambda: request.finished, message="the stream to end at its lifetime")
        self.assertFalse(request.aborted)
        self.assertEqual(self.console.caps.open, {})

    def test_what_a_stream_sends_is_strict_json(self):
        event = rcmp_console.sse("sample", {"topic": "/pose", "sample": {"x": float("nan"), "y": float("inf"),
                                                                        "theta": -float("inf"), "t": 1.5}})

        def refuse(constant):
            raise ValueError(constant)
        data = json.loads(event.decode().split("data: ", 1)[1], parse_constant=refuse)
        self.assertEqual(data["sample"], {"x": "NaN", "y": "Infinity", "theta": "-Infinity", "t": 1.5})
