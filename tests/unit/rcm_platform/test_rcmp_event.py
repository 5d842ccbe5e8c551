"""MasterAgent and RobotAgent talking over real loopback TCP, with recording stand-ins for the data and rcmp_ms.

What is checked here is the agents' own logic: hello accepted or refused against the robotics data, retries,
the order of the live-state writes, the service space asked for on hello and torn down when the robot goes,
heartbeats both ways, a robot saying hello again, r_provisioning's disconnect. The multi-process tests
(``tests/system/test_lifecycle_processes.py``) run the same story with real agents, real SQLite and real ROS.
"""

import logging
import threading
import types

from twisted.internet import defer, reactor
from twisted.trial import unittest

from rcm_platform import rcmp_event
from rcm_platform import rcmp_inter_communication as ic
from rcm_platform.rcmp_config import make_config
from tests.support.paths import REPO
from tests.support.ports import free_port
from tests.support.polling import until_deferred


def until(condition, timeout=8.0):
    return until_deferred(condition, timeout=timeout)


class Data:
    """RoboticsData's live-state calls, recorded (called from threads, like the real one)."""

    def __init__(self, provisioned=()):
        self.lock = threading.Lock()
        self.provisioned = set(provisioned)
        self.events = []
        self.lookups = []
        self.reads = 0               # reads of every provisioned robot (the master's cache fills from them)

    def platform_instance(self, name):
        with self.lock:
            self.lookups.append(name)
            if name not in self.provisioned:
                return None
            return {"pi_name": name, "service_logic": "logic", "connected": False, "paired": False,
                    "address": None}

    def platform_instances(self):
        with self.lock:
            self.reads += 1
            return [{"pi_name": name, "service_logic": "logic", "connected": False, "paired": False}
                    for name in sorted(self.provisioned)]

    def service_logic(self, name):
        return {"ss_side": "S", "sn_list": [{"sn_name": "r_node", "sn_side": "R"}], "sl_list": []}

    def _record(self, *event):
        with self.lock:
            self.events.append(event)

    def set_connected(self, name, address):
        self._record("connected", name, address)

    def set_paired(self, name, paired):
        self._record("paired", name, paired)

    def set_service_space(self, name, uri, port):
        self._record("space", name, uri, port)

    def set_disconnected(self, name):
        self._record("disconnected", name)

    def write_batch(self, calls):
        """RoboticsData.write_batch's answer, without a transaction: each call in order."""
        results = []
        for fn, args in calls:
            try:
                results.append((True, fn(*args)))
            except Exception as exc:
                results.append((False, exc))
        return results

    def names(self, name):
        with self.lock:
            return [e[0] for e in self.events if e[1] == name]


class Spaces:
    """A ServiceSpaceManager stand-in: asks the robot for its R items, reports paired, tears down."""

    def __init__(self):
        self.on_state = None
        self.created = []
        self.torn_down = []
        self.exited = []
        self.robots = {}

    @defer.inlineCallbacks
    def create(self, pi_name, logic, robot):
        self.created.append((pi_name, robot.name, robot.address))
        self.robots[pi_name] = robot
        answer = yield robot.start_items(pi_name, "http://127.0.0.1:11999/", logic["sn_list"], None)
        space = types.SimpleNamespace(ros_master_uri=answer["ros_master_uri"], inbound_port=None)
        self.on_state(pi_name, True, space)
        return space

    @defer.inlineCallbacks
    def teardown(self, pi_name):
        robot = self.robots.pop(pi_name, None)
        if robot is not None:
            try:
                yield robot.stop_items(pi_name)
            except Exception:
                pass
            self.on_state(pi_name, False, None)
        self.torn_down.append(pi_name)

    def teardown_all(self):
        return defer.gatherResults([self.teardown(n) for n in list(self.robots)])

    def item_exited(self, ss_name, report):
        self.exited.append((ss_name, report))


class Runner:
    """An ItemRunner stand-in."""

    def __init__(self):
        self.on_item_exited = None
        self.started = []
        self.stopped = []
        self.stop_all_calls = 0

    def start_items(self, ss_name, uri, items, port=None):
        self.started.append((ss_name, uri, len(items)))
        return defer.succeed({"ros_master_uri": uri, "items": [{"name": i["sn_name"], "state": "running"}
                                                               for i in items]})

    def stop_items(self, ss_name):
        self.stopped.append(ss_name)
        return defer.succeed(None)

    def stop_all(self):
        self.stop_all_calls += 1
        return defer.succeed(None)


def config(name, address, port, role="master", interval=0.2):
    return make_config(role, "/nonexistent", name=name, vpn_address=address, vpn_interface="lo",
                       ip_master="127.0.0.1", ic_port=port, heartbeat_interval=interval, heartbeat_misses=3)


class Logged(logging.Handler):
    def __init__(self):
        super().__init__(logging.DEBUG)
        self.lines = []
        self.levels = []

    def emit(self, record):
        self.lines.append(record.getMessage())
        self.levels.append(record.levelno)


class AgentTests(unittest.TestCase):

    @defer.inlineCallbacks
    def setUp(self):
        self.patch(rcmp_event, "AFTER_DISCONNECT", 0.5)
        self.port = free_port()
        self.data = Data(provisioned={"robot1"})
        self.spaces = Spaces()
        self.master = rcmp_event.MasterAgent(config("master", "127.0.0.1", self.port), self.data, None, reactor,
                                             "127.0.0.1", spaces=self.spaces)
        self.master.startService()
        yield until(lambda: self.master.listening is not None)
        self.addCleanup(self._stop, self.master)
        self.log = Logged()
        logging.getLogger("rcmp").addHandler(self.log)
        logging.getLogger("rcmp").setLevel(logging.DEBUG)
        self.addCleanup(logging.getLogger("rcmp").removeHandler, self.log)

    def _stop(self, svc):
        if svc.running:
            return svc.stopService()

    def robot(self, name="robot1", address="127.0.0.2"):
        runner = Runner()
        agent = rcmp_event.RobotAgent(config(name, address, self.port, role="robot"), None, reactor,
                                      runner=runner)
        agent.startService()
        self.addCleanup(self._stop, agent)
        return agent, runner

    @defer.inlineCallbacks
    def test_known_robot_connects_and_pairs(self):
        agent, runner = self.robot()
        yield until(lambda: "paired" in self.data.names("robot1"))
        self.assertEqual(self.data.events[0], ("connected", "robot1", "127.0.0.2"))
        self.assertEqual(self.spaces.created, [("robot1", "robot1", "127.0.0.2")])
        self.assertEqual(runner.started, [("robot1", "http://127.0.0.1:11999/", 1)])
        self.assertIn(("space", "robot1", "http://127.0.0.1:11999/", None), self.data.events)
        self.assertEqual(self.data.events[-1], ("paired", "robot1", True))
        self.assertEqual(sorted(self.master.sessions), ["robot1"])
        self.assertEqual(agent.peer.transport.getHost().host, "127.0.0.2")   # bound to its platform address

    @defer.inlineCallbacks
    def test_unknown_robot_is_refused_retries_and_connects_once_provisioned(self):
        agent, runner = self.robot(name="stranger", address="127.0.0.3")
        yield until(lambda: self.master.counters["refused_not_provisioned"] >= 2)
        self.assertEqual(self.data.names("stranger"), [])
        self.assertEqual(self.spaces.created, [])
        refusals = [line for line in self.log.lines if "refused hello" in line]
        self.assertTrue(any("'stranger' is not provisioned" in line for line in refusals), refusals)
        with self.data.lock:
            self.data.provisioned.add("stranger")
        yield until(lambda: "paired" in self.data.names("stranger"), timeout=10)
        self.assertEqual(self.data.names("stranger")[0], "connected")

    @defer.inlineCallbacks
    def test_robot_stopping_tears_its_space_down(self):
        agent, runner = self.robot()
        yield until(lambda: "paired" in self.data.names("robot1"))
        yield agent.stopService()
        yield until(lambda: "disconnected" in self.data.names("robot1"))
        self.assertEqual(self.spaces.torn_down, ["robot1"])
        self.assertEqual(self.data.names("robot1")[-1], "disconnected")
        self.assertEqual(sorted(self.master.sessions), [])
        self.assertEqual(runner.stop_all_calls, 1)

    @defer.inlineCallbacks
    def test_silent_peers_are_declared_gone_both_ways(self):
        agent, runner = self.robot()
        yield until(lambda: "paired" in self.data.names("robot1"))
        master_peer = self.master.sessions["robot1"].peer
        master_peer.transport.pauseProducing()      # the master reads nothing: every beat goes unanswered
        master_peer.transport.stopReading()
        robot_peer = agent.peer
        robot_peer.transport.stopReading()          # and the robot hears nothing from the master
        yield until(lambda: "disconnected" in self.data.names("robot1"), timeout=5)
        yield until(lambda: runner.stop_all_calls >= 1, timeout=5)
        self.assertTrue(any("silent" in line or "heartbeat" in line for line in self.log.lines))
        # the robot goes back to hello and pairs again
        yield until(lambda: self.data.names("robot1").count("paired") >= 2, timeout=10)
        self.assertEqual(self.data.names("robot1"),
                         ["connected", "space", "paired", "disconnected", "connected", "space", "paired"])

    @defer.inlineCallbacks
    def test_second_hello_replaces_the_old_session(self):
        handler = types.SimpleNamespace(
            request_received=lambda peer, op, body: {"ros_master_uri": body.get("ros_master_uri"), "items": []})
        first = yield ic.connect(reactor, "127.0.0.1", self.port, handler, bind_address="127.0.0.2")
        hello = {"name": "robot1", "address": "127.0.0.2", "robot": True, "version": rcmp_event.VERSION}
        answer = yield first.request("hello", hello)
        self.assertTrue(answer["accepted"])
        yield until(lambda: "paired" in self.data.names("robot1"))
        second = yield ic.connect(reactor, "127.0.0.1", self.port, handler, bind_address="127.0.0.2")
        self.addCleanup(second.abort, "test over")
        answer = yield second.request("hello", hello)
        self.assertTrue(answer["accepted"])
        yield until(lambda: first.closed)
        yield until(lambda: self.data.names("robot1").count("paired") >= 2)
        self.assertEqual(self.data.names("robot1"),
                         ["connected", "space", "paired", "disconnected", "connected", "space", "paired"])
        self.assertEqual(self.spaces.torn_down, ["robot1"])
        self.assertEqual(self.master.sessions["robot1"].peer.remote.split(":")[1],
                         str(second.transport.getHost().port))
        self.assertEqual(len(self.spaces.created), 2)

    @defer.inlineCallbacks
    def test_disconnect_tears_down_and_the_robot_is_told_why(self):
        agent, runner = self.robot()
        yield until(lambda: "paired" in self.data.names("robot1"))
        def remove():
            with self.data.lock:
                self.data.provisioned.discard("robot1")   # what r_provisioning's removal does
        yield self.master.remove("robot1", "robot1 was removed from the platform", remove)
        self.assertEqual(self.data.names("robot1")[-1], "disconnected")
        self.assertEqual(runner.stopped, ["robot1"])
        yield until(lambda: any("removed from the platform" in line for line in self.log.lines))
        yield until(lambda: runner.stop_all_calls >= 1)
        yield until(lambda: self.master.counters["refused_not_provisioned"] >= 1)   # back to hello: refused now
        self.assertEqual(sorted(self.master.sessions), [])

    @defer.inlineCallbacks
    def test_disconnect_of_an_unconnected_robot_is_a_no_op(self):
        yield self.master.disconnect("nobody", "test")
        self.assertEqual(self.data.events, [])

    @defer.inlineCallbacks
    def test_item_exit_is_forwarded_to_the_space_manager(self):
        agent, runner = self.robot()
        yield until(lambda: "paired" in self.data.names("robot1"))
        runner.on_item_exited("robot1", {"name": "r_node", "state": "failed", "error": "exit 3"})
        yield until(lambda: self.spaces.exited)
        self.assertEqual(self.spaces.exited, [("robot1", {"name": "r_node", "state": "failed", "error": "exit 3"})])

    @defer.inlineCallbacks
    def test_bad_hellos_and_requests_before_hello_are_refused(self):
        handler = types.SimpleNamespace(request_received=lambda peer, op, body: {})
        peer = yield ic.connect(reactor, "127.0.0.1", self.port, handler)
        self.addCleanup(peer.abort, "test over")
        cases = [("item_exited", {"ss_name": "robot1", "report": {}}, "no_session"),
                 ("hello", {"name": "robot1"}, "bad_request"),
                 ("hello", {"name": "robot1", "address": "x", "robot": "yes", "version": 1}, "bad_request"),
                 ("hello", {"name": "robot1", "address": "x", "robot": True, "version": True}, "bad_request"),
                 ("start_items", {"ss_name": "x", "items": []}, "unknown_op")]
        for op, body, code in cases:
            with self.assertRaises(ic.RemoteError, msg=(op, body)) as caught:
                yield peer.request(op, body, timeout=2)
            self.assertEqual(caught.exception.code, code, (op, body))
        with self.assertRaises(ic.RemoteError) as caught:
            yield peer.request("hello", {"name": "robot1", "address": "x", "robot": True, "version": 99})
        self.assertEqual(caught.exception.code, "unsupported_version")
        yield until(lambda: peer.closed)
        self.assertEqual(self.data.events, [])

    @defer.inlineCallbacks
    def test_master_stopping_disconnects_everyone(self):
        agent, runner = self.robot()
        yield until(lambda: "paired" in self.data.names("robot1"))
        yield self.master.stopService()
        self.assertEqual(self.data.names("robot1")[-1], "disconnected")
        yield until(lambda: runner.stop_all_calls >= 1)


class ValidateTests(unittest.TestCase):

    def test_optional_fields_are_filled(self):
        body = rcmp_event.validate("start_items", {"ss_name": "r", "items": []}, "robot")
        self.assertEqual((body["ros_master_uri"], body["start_ros_master_port"]), (None, None))

    def test_side_matters(self):
        with self.assertRaises(ic.Refused):
            rcmp_event.validate("hello", {}, "robot")
        rcmp_event.validate("heartbeat", {}, "robot")
        rcmp_event.validate("heartbeat", {}, "master")

    def test_every_op_is_documented(self):
        import os
        path = os.path.join(REPO, "docs", "PROTOCOL.md")
        with open(path) as f:
            text = f.read()
        for op in rcmp_event.OPS:
            self.assertIn(f"### `{op}`", text)


class AddressTests(unittest.TestCase):
    """A robot waits for its platform address, then connects (to .1 of its network when ip_master is unset)."""

    @defer.inlineCallbacks
    def test_robot_waits_for_its_address_then_connects(self):
        address = {"now": None}
        self.patch(rcmp_event, "ADDRESS_POLL", 0.05)
        port = free_port()
        data = Data(provisioned={"robot1"})
        master = rcmp_event.MasterAgent(config("master", "127.0.0.1", port), data, None, reactor, "127.0.0.1",
                                        spaces=Spaces())
        master.address = "127.0.0.1"                   # the master's own address is known
        master.startService()
        self.addCleanup(master.stopService)
        robot_config = config("robot1", None, port, role="robot")
        robot_config.ip_master = None                  # derived from the address once it exists
        log = Logged()
        logging.getLogger("rcmp").addHandler(log)
        self.addCleanup(logging.getLogger("rcmp").removeHandler, log)
        robot = rcmp_event.RobotAgent(robot_config, None, reactor, runner=Runner(), address=lambda: address["now"])
        robot.startService()
        self.addCleanup(robot.stopService)
        yield until(lambda: any("waiting for the platform address" in line for line in log.lines))
        self.assertEqual(master.counters["sessions_opened"], 0)
        address["now"] = "127.0.0.5"                   # the VPN comes up
        yield until(lambda: "paired" in data.names("robot1"))
        self.assertEqual(data.events[0], ("connected", "robot1", "127.0.0.5"))


class HelloTimeoutTests(unittest.TestCase):

    @defer.inlineCallbacks
    def test_a_silent_connection_is_closed(self):
        self.patch(rcmp_event, "HELLO_WAIT", 0.2)
        port = free_port()
        master = rcmp_event.MasterAgent(config("master", "127.0.0.1", port), Data(), None, reactor, "127.0.0.1",
                                        spaces=Spaces())
        master.address = "127.0.0.1"
        master.startService()
        self.addCleanup(master.stopService)
        handler = types.SimpleNamespace(request_received=lambda peer, op, body: {})
        peer = yield ic.connect(reactor, "127.0.0.1", port, handler)
        yield peer.request("heartbeat", {})           # answered, but it is no hello
        yield until(lambda: peer.closed, timeout=3)


class HelloRulesTests(unittest.TestCase):

    @defer.inlineCallbacks
    def setUp(self):
        self.port = free_port()
        self.data = Data(provisioned={"robot1", "master"})
        self.master = rcmp_event.MasterAgent(config("master", "127.0.0.1", self.port), self.data, None, reactor,
                                             "127.0.0.1", spaces=Spaces())
        self.master.address = "127.0.0.1"
        self.master.startService()
        self.addCleanup(lambda: self.master.running and self.master.stopService())
        handler = types.SimpleNamespace(
            request_received=lambda peer, op, body: {"ros_master_uri": body.get("ros_master_uri"), "items": []})
        self.peer = yield ic.connect(reactor, "127.0.0.1", self.port, handler)
        self.addCleanup(self.peer.abort, "test over")

    def hello(self, name):
        return self.peer.request("hello", {"name": name, "address": "127.0.0.1", "robot": True,
                                           "version": rcmp_event.VERSION}, timeout=3)

    @defer.inlineCallbacks
    def test_the_masters_own_name_is_refused(self):
        with self.assertRaises(ic.RemoteError) as caught:
            yield self.hello("master")
        self.assertIn("master's own name", caught.exception.reason)
        yield until(lambda: self.peer.closed)
        self.assertEqual(self.data.events, [])

    @defer.inlineCallbacks
    def test_two_hellos_on_one_connection(self):
        first, second = self.hello("robot1"), self.hello("robot1")
        with self.assertRaises(ic.RemoteError) as caught:
            yield second
        self.assertEqual(caught.exception.code, "bad_request")
        answer = yield first
        self.assertTrue(answer["accepted"])
        self.assertEqual(sorted(self.master.sessions), ["robot1"])
