"""rcmp_metrics: the master's /metrics from real parts (robotics data in SQLite, the MasterAgent, its space manager,
the RDAPI resource), read back with prometheus_client's own parser; labels stay bounded."""

import json
import os
import random
import string
import tempfile

from prometheus_client.parser import text_string_to_metric_families
from twisted.internet import defer, reactor
from twisted.web.test.requesthelper import DummyRequest

from rcm_platform import rcmp_metrics
from rcm_platform.rcmp_config import make_config
from rcm_platform.rcmp_event import MasterAgent
from rcm_platform.rcmp_ext_connector import UNKNOWN_ROUTE, make_site
from rcm_platform.rcmp_ms import SPACE_PAIRED, SPACE_UNPAIRED, ServiceSpace, ServiceSpaceManager
from rcm_platform.rcmp_platform_command import PlatformCommands
from rcm_platform.rcmp_process import ProcessTable
from rcm_platform.rcmp_service_command import ServiceCommands
from rcm_platform.rcmp_service_item import ITEM_FAILURES, ServiceItem
from tests.unit.rcm_platform.test_rcmp_command import DataTestCase

NODE = {"sn_package": "robotics_test", "sn_type": "talker.py", "sn_name": "talker", "sn_side": "R"}
LAUNCHER = {"sl_package": "robotics_test", "sl_file_launcher": "two_talkers.launch", "sl_name": "two",
            "sl_side": "S"}


class Request(DummyRequest):
    """Twisted's DummyRequest with the ``code`` a real request has (200 until set)."""

    @property
    def code(self):
        return self.responseCode or 200


def samples(text):
    """{(sample name, ((label, value), ...)): value} of a text exposition, parsed by prometheus_client."""
    found = {}
    for family in text_string_to_metric_families(text):
        for sample in family.samples:
            found[(sample[0], tuple(sorted(sample[1].items())))] = sample[2]
    return found


class MetricsTests(DataTestCase):
    def setUp(self):
        super().setUp()
        home = tempfile.mkdtemp()
        self.config = make_config("master", home, vpn_address="127.0.0.1", ext_address="127.0.0.1")
        table = ProcessTable(reactor, os.path.join(home, "log"))
        self.spaces = ServiceSpaceManager(reactor, table, self.config, "127.0.0.1", address="127.0.0.1")
        self.agent = MasterAgent(self.config, self.data, table, reactor, "127.0.0.1", spaces=self.spaces)
        self.platform = PlatformCommands(self.data, robots=self.agent)
        self.metrics = rcmp_metrics.make_metrics(self.agent, self.spaces, self.platform)
        self.site = make_site(self.platform, ServiceCommands(self.data, spaces=self.agent), metrics=self.metrics)
        self.metrics.watch_site(self.site)
        self.metrics.startService()
        self.addCleanup(self.metrics.stopService)

    @defer.inlineCallbacks
    def render(self, method, path):
        request = Request(path.strip("/").split("/"))
        request.method = method.encode()
        request.path = path.encode()
        request.too_large = False
        result = self.site.resource.render(request)
        if isinstance(result, bytes):
            request.write(result)
            request.finish()
        elif not request.finished:
            yield request.notifyFinish()
        return request.responseCode or 200, b"".join(request.written), request

    @defer.inlineCallbacks
    def scrape(self):
        code, body, request = yield self.render("GET", "/metrics")
        self.assertEqual(code, 200, body)
        self.assertTrue(request.responseHeaders.getRawHeaders(b"content-type")[0].startswith(b"text/plain"))
        return samples(body.decode("utf-8"))

    def space(self, name, state, items, server="master"):
        space = ServiceSpace(name, "S", "ss", "127.0.0.1", "master")
        space.items, space.server = items, server
        if state != "creating":
            space.transition(state, "test")
        self.spaces.spaces[name] = space
        return space

    @defer.inlineCallbacks
    def test_robot_counts_are_what_platform_instance_read_says(self):
        found = yield self.scrape()
        self.assertEqual([found[(n, ())] for n in ("rcm_robots_provisioned", "rcm_robots_connected",
                                                     "rcm_robots_paired")], [0, 0, 0])
        for name in ("r1", "r2"):
            yield self.platform.provisioning({"pi_name": name, "pi_service_logic": "empty"})
        yield defer.maybeDeferred(self.data.set_connected, "r1", "127.0.0.2")
        yield defer.maybeDeferred(self.data.set_paired, "r1", True)
        found = yield self.scrape()
        self.assertEqual([found[(n, ())] for n in ("rcm_robots_provisioned", "rcm_robots_connected",
                                                     "rcm_robots_paired")], [2, 1, 1])
        self.assertFalse([key for key in found if "r1" in str(key[1]) or "r2" in str(key[1])])  # no robot label

    @defer.inlineCallbacks
    def test_service_spaces_per_server_and_state_read_at_scrape_time(self):
        self.space("a", SPACE_PAIRED, [])
        self.space("b", SPACE_UNPAIRED, [])
        self.spaces.add_server("vm1", object(), 7, "127.0.0.9")
        self.space("c", SPACE_PAIRED, [], server="vm1")
        found = yield self.scrape()
        self.assertEqual(found[("rcm_servers_connected", ())], 2)
        spaces = {dict(labels)["server"] + "/" + dict(labels)["state"]: value for (name, labels), value
                  in found.items() if name == "rcm_service_spaces"}
        self.assertEqual(spaces, {"master/creating": 0, "master/paired": 1, "master/unpaired": 1,
                                  "master/stopping": 0, "vm1/creating": 0, "vm1/paired": 1, "vm1/unpaired": 0,
                                  "vm1/stopping": 0})
        self.assertEqual(found[("rcm_service_spaces_limit", (("server", "vm1"),))], 7)
        self.assertEqual(found[("rcm_service_spaces_limit", (("server", "master"),))], 100)
        del self.spaces.spaces["c"]
        yield self.spaces.remove_server("vm1", "test")
        found = yield self.scrape()   # a server gone is no series any more
        self.assertFalse([key for key in found if ("server", "vm1") in key[1]])

    @defer.inlineCallbacks
    def test_each_failed_item_counts_once_by_its_reason(self):
        local = ServiceItem.from_entry(LAUNCHER, "master")
        remote = ServiceItem.from_entry(NODE, "r1")
        remote.remote = {**remote.report(), "state": "running"}
        stranger = ServiceItem.from_entry(dict(NODE, sn_name="other"), "r1")
        stranger.remote = {**stranger.report(), "state": "failed", "failure": "a word of its own " * 20}
        self.space("r1", SPACE_PAIRED, [local, remote, stranger])
        local.fail("roslaunch cannot load robotics_test/two_talkers.launch: no such file", "launch_file")
        report = {**remote.report(), "state": "failed", "error": "exited with status 3", "failure": "exited"}
        for _ in range(3):    # told again and again: still one failure each
            self.spaces.item_exited("r1", report)
        found = yield self.scrape()
        failures = {dict(labels)["reason"]: value for (name, labels), value in found.items()
                    if name == "rcm_item_failures_total"}
        self.assertEqual(set(failures), set(ITEM_FAILURES))      # every reason, at 0 too: no series appears later
        self.assertEqual({r: v for r, v in failures.items() if v}, {"launch_file": 1, "exited": 1, "other": 1})

    @defer.inlineCallbacks
    def test_hello_and_pairing_durations(self):
        for observer in self.agent.timing_observers:
            observer("hello", 0.02)
            observer("pairing", 4.0)
        found = yield self.scrape()
        self.assertEqual(found[("rcm_hello_duration_seconds_count", ())], 1)
        self.assertEqual(found[("rcm_hello_duration_seconds_bucket", (("le", "0.025"),))], 1)
        self.assertEqual(found[("rcm_pairing_duration_seconds_bucket", (("le", "3.0"),))], 0)
        self.assertEqual(found[("rcm_pairing_duration_seconds_bucket", (("le", "5.0"),))], 1)

    @defer.inlineCallbacks
    def test_agent_counters_are_read_at_scrape_time(self):
        self.agent.counters.update({"refused_not_provisioned": 4, "heartbeat_misses_robot": 2,
                                    "heartbeat_timeouts_server": 1, "sessions_opened": 5, "sessions_ended": 3})
        found = yield self.scrape()
        self.assertEqual(found[("rcm_hellos_refused_total", (("code", "not_provisioned"),))], 4)
        self.assertEqual(found[("rcm_heartbeat_misses_total", (("peer", "robot"),))], 2)
        self.assertEqual(found[("rcm_heartbeat_misses_total", (("peer", "server"),))], 0)
        self.assertEqual(found[("rcm_heartbeat_timeouts_total", (("peer", "server"),))], 1)
        self.assertEqual((found[("rcm_robot_connections_total", ())], found[("rcm_robot_disconnections_total", ())]),
                         (5, 3))
        self.assertIn(("process_resident_memory_bytes", ()), found)

    @defer.inlineCallbacks
    def test_requests_to_any_path_with_any_method_make_a_bounded_set_of_series(self):
        yield self.render("GET", "/platform_instance/read")
        before = yield self.scrape()
        for _ in range(200):
            path = "/" + "".join(random.choice(string.ascii_letters + "/_.%") for _ in range(random.randint(1, 40)))
            method = random.choice(["GET", "POST", "PUT", "DELETE", "BREW", "X" * random.randint(1, 30)])
            yield self.render(method, path)
        after = yield self.scrape()
        routes = {dict(labels)["route"] for (name, labels) in after if name == "rcm_rdapi_requests_total"}
        self.assertLessEqual(routes, set(self.site.resource.routes) | {UNKNOWN_ROUTE})
        new = {key for key in after if key not in before and not key[0].startswith(("process_", "python_"))}
        labels = {dict(key[1]).get("route") for key in new}
        self.assertLessEqual(labels, {UNKNOWN_ROUTE, "/metrics"})
        self.assertLessEqual(len([k for k in new if k[0] == "rcm_rdapi_requests_total"]), 6)  # 3 methods x 404/405
        self.assertEqual(after[("rcm_rdapi_requests_total", (("code", "200"), ("method", "GET"),
                                                              ("route", "/platform_instance/read")))], 1)

    @defer.inlineCallbacks
    def test_metrics_take_get_only(self):
        code, body, _ = yield self.render("POST", "/metrics")
        self.assertEqual(code, 405)
        self.assertEqual(json.loads(body)["result"], "ERROR")


class UnavailableTests(DataTestCase):
    @defer.inlineCallbacks
    def test_a_master_without_prometheus_client_answers_503_naming_the_package(self):
        unavailable = rcmp_metrics.Unavailable("prometheus_client (Python module 'prometheus_client') is missing "
                                               "(for the RDAPI's /metrics): install it with 'sudo apt-get install "
                                               "python3-prometheus-client' (Debian GNU/Linux 12 (bookworm))")
        site = make_site(PlatformCommands(self.data), ServiceCommands(self.data), metrics=unavailable)
        request = Request([b"metrics"])
        request.method, request.path, request.too_large = b"GET", b"/metrics", False
        result = site.resource.render(request)
        if not request.finished:
            yield request.notifyFinish()
        self.assertIsNotNone(result)
        self.assertEqual(request.responseCode, 503)
        answer = json.loads(b"".join(request.written))
        self.assertEqual(answer["result"], "ERROR")
        self.assertIn("this master serves no metrics", answer["reason"])
        self.assertIn("python3-prometheus-client", answer["reason"])

    def test_make_metrics_without_the_library_names_it(self):
        saved = rcmp_metrics.prometheus_client, rcmp_metrics._MISSING
        rcmp_metrics.prometheus_client = None
        rcmp_metrics._MISSING = ModuleNotFoundError("No module named 'prometheus_client'", name="prometheus_client")
        try:
            made = rcmp_metrics.make_metrics(None, None, None)
        finally:
            rcmp_metrics.prometheus_client, rcmp_metrics._MISSING = saved
        self.assertIsInstance(made, rcmp_metrics.Unavailable)
        self.assertIn("python3-prometheus-client", made.reason)
        self.assertIn("for the RDAPI's /metrics", made.reason)
