"""The commands behind the RDAPI and the RDAPI resource itself, in-process (twisted.trial: Deferreds run for real).

Real SQLite files in a temp dir; fake master runtimes record what the commands asked of them. The resource is
driven with Twisted's DummyRequest, as Twisted's own web tests do.
"""

import json
import os
import tempfile

from twisted.internet import defer, threads
from twisted.trial import unittest
from twisted.web.test.requesthelper import DummyRequest

from rcm_platform.rcmp_command import (BadRequest, Conflict, NotFound, ReadCache, split_params, validate_name,
                                       validate_service_logic)
from rcm_platform.rcmp_ext_connector import Rdapi
from rcm_platform.rcmp_platform_command import PlatformCommands
from rcm_platform.rcmp_robotics_data import RoboticsData
from rcm_platform.rcmp_service_command import ServiceCommands


class RecordingRobots:
    """A master runtime that records removals and checks the robot is still provisioned when asked."""

    def __init__(self, data):
        self.data = data
        self.calls = []

    def remove(self, pi_name, reason, remove):
        row = self.data.platform_instance(pi_name)
        self.calls.append((pi_name, reason, row is not None))
        if row is not None and row["connected"]:
            self.data.set_disconnected(pi_name)
        d = threads.deferToThread(remove)
        d.addCallback(lambda _: bool(row and row["connected"]))
        return d


class Spaces:
    def __init__(self, spaces):
        self.spaces = spaces

    def describe(self, ss_name):
        return self.spaces.get(ss_name)


class DataTestCase(unittest.TestCase):
    def setUp(self):
        self.dir = tempfile.mkdtemp()
        self.data = RoboticsData(os.path.join(self.dir, "robotics_data.db"))
        self.addCleanup(self.data.close)


class ValidationTests(unittest.TestCase):
    def test_names(self):
        for good in ("r", "robot1", "Robot_01", "a" * 64):
            self.assertEqual(validate_name(good, "pi_name"), good)
        for bad in ("", "a" * 65, "1r", "_r", "r-1", "r/1", "r 1", "r;1", "$(x)", "r\u00f6", 5, None, ["r"]):
            self.assertRaises(BadRequest, validate_name, bad, "pi_name")

    def test_params_split_like_a_shell_without_one(self):
        self.assertEqual(split_params("-a 'b c' \"d e\" f\\ g $(rm) ;ls"), ["-a", "b c", "d e", "f g", "$(rm)", ";ls"])
        self.assertEqual(split_params(""), [])
        for bad in ("'open", 'x "y', "trail\\", "nul\x00"):
            self.assertRaises(BadRequest, split_params, bad)

    def test_service_logic_normalised(self):
        name, nodes, launchers, side = validate_service_logic({
            "slg_name": "s", "sn_list": [{"sn_package": "p", "sn_type": "t", "sn_name": "n", "sn_side": "R"}]})
        self.assertEqual((name, launchers, side), ("s", [], "S"))
        self.assertEqual(nodes, [{"sn_package": "p", "sn_type": "t", "sn_name": "n", "sn_params": "",
                                  "sn_side": "R"}])
        with self.assertRaisesRegex(BadRequest, r"sn_list\[0\]\.sn_side"):
            validate_service_logic({"slg_name": "s", "sn_list": [
                {"sn_package": "p", "sn_type": "t", "sn_name": "n", "sn_side": "Q"}]})


class CommandTests(DataTestCase):
    @defer.inlineCallbacks
    def test_r_provisioning_disconnects_a_connected_robot_first(self):
        robots = RecordingRobots(self.data)
        commands = PlatformCommands(self.data, robots=robots)
        yield commands.provisioning({"pi_name": "r1", "pi_service_logic": "empty"})
        self.data.set_connected("r1", "10.8.0.6")
        reason = yield commands.r_provisioning({"pi_name": "r1"})
        self.assertIn("after disconnecting it", reason)
        self.assertEqual(robots.calls, [("r1", "its provisioning was removed", True)])
        self.assertIsNone(self.data.platform_instance("r1"))

    @defer.inlineCallbacks
    def test_r_provisioning_errors_come_as_failures(self):
        commands = PlatformCommands(self.data, robots=RecordingRobots(self.data))
        yield self.assertFailure(commands.r_provisioning({"pi_name": "ghost"}), NotFound)
        yield self.assertFailure(commands.r_provisioning({"pi_name": "a/b"}), BadRequest)
        yield self.assertFailure(commands.provisioning({"pi_name": "r"}), BadRequest)
        yield self.assertFailure(commands.provisioning({"pi_name": "r", "pi_service_logic": "x"}), NotFound)

    @defer.inlineCallbacks
    def test_reads_are_cached_until_a_write(self):
        commands = PlatformCommands(self.data)
        first = yield commands.read()
        again = yield commands.read()
        self.assertIs(first, again)  # served from the cache: no SQLite, no thread
        yield commands.provisioning({"pi_name": "r1", "pi_service_logic": "empty"})
        after = yield commands.read()
        self.assertEqual([r["pi_name"] for r in after], ["r1"])
        self.data.set_connected("r1", "10.8.0.6")  # a write by the master runtime, not through the commands
        live = yield commands.read()
        self.assertTrue(live[0]["connected"])

    @defer.inlineCallbacks
    def test_service_logic_reads_follow_writes(self):
        commands = ServiceCommands(self.data)
        names = yield commands.read()
        self.assertEqual(names, [{"slg_name": "empty"}, {"slg_name": "fiware_base"}])
        yield commands.provisioning({"slg_name": "s1"})
        names = yield commands.read()
        self.assertIn({"slg_name": "s1"}, names)
        yield commands.r_provisioning({"slg_name": "s1"})
        yield self.assertFailure(commands.read("s1"), NotFound)
        yield self.assertFailure(commands.provisioning({"slg_name": "fiware_base"}), Conflict)

    @defer.inlineCallbacks
    def test_service_space_read(self):
        yield self.assertFailure(ServiceCommands(self.data).service_space("r1"), NotFound)
        yield self.assertFailure(ServiceCommands(self.data, spaces=Spaces({})).service_space("r1"), NotFound)
        described = {"r_nodes": [], "r_launchers": [], "public_ip": "1.2.3.4", "inbound_port": None}
        got = yield ServiceCommands(self.data, spaces=Spaces({"r1": described})).service_space("r1")
        self.assertEqual(got, described)
        yield self.assertFailure(ServiceCommands(self.data).service_space("r/1"), BadRequest)

    def test_read_cache_is_bounded(self):
        cache = ReadCache(self.data, max_entries=3)
        for i in range(5):
            cache.put(i, self.data.generation, [i])
        self.assertLessEqual(len(cache._entries), 3)


class ResourceTests(DataTestCase):
    def setUp(self):
        super().setUp()
        self.resource = Rdapi(PlatformCommands(self.data), ServiceCommands(self.data))

    @defer.inlineCallbacks
    def render(self, method, path, body=None, args=None):
        request = DummyRequest(path.strip("/").split("/"))
        request.method = method.encode()
        request.path = path.encode()
        request.args = args or {}
        request.too_large = False
        request.max_body = 65536
        if body is not None:
            from io import BytesIO
            request.content = BytesIO(body)
            request.requestHeaders.setRawHeaders(b"content-type", [b"application/json"])
        result = self.resource.render(request)
        if isinstance(result, bytes):
            request.write(result)
            request.finish()
        elif not request.finished:
            yield request.notifyFinish()
        return request.responseCode or 200, b"".join(request.written), request

    @defer.inlineCallbacks
    def test_ok_and_error_answers(self):
        code, body, _ = yield self.render("GET", "/platform_instance/read")
        self.assertEqual((code, json.loads(body)), (200, {"result": "OK", "reason": []}))
        code, body, _ = yield self.render("POST", "/service_logic/provisioning", b'{"slg_name": "s"}')
        self.assertEqual(code, 200)
        code, body, _ = yield self.render("POST", "/service_logic/provisioning", b'{"slg_name": "s"}')
        self.assertEqual((code, json.loads(body)["result"]), (409, "ERROR"))
        code, body, request = yield self.render("GET", "/service_logic/provisioning")
        self.assertEqual(code, 405)
        self.assertEqual(request.responseHeaders.getRawHeaders(b"allow")[-1], b"POST, OPTIONS")
        code, body, _ = yield self.render("GET", "/service_logic/read", args={b"slg_name": [b"s"]})
        self.assertEqual(json.loads(body)["reason"], {"ss_side": "S", "sn_list": [], "sl_list": []})

    @defer.inlineCallbacks
    def test_unexpected_error_is_500_and_logged(self):
        class Broken:
            def read(self):
                return defer.fail(RuntimeError("boom"))
        self.resource = Rdapi(Broken(), ServiceCommands(self.data))
        code, body, _ = yield self.render("GET", "/platform_instance/read")
        self.assertEqual(code, 500)
        self.assertIn("rcmp.log", json.loads(body)["reason"])
        self.flushLoggedErrors(RuntimeError)
