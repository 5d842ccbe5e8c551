"""rcmp_ext_connector: ``GET /platform_instance/read`` is encoded once while nothing it shows changed, and a write or a
robot's new server is in the very next answer (DummyRequest, real SQLite)."""

import json

from twisted.internet import defer

from rcm_platform.rcmp_ext_connector import Rdapi
from rcm_platform.rcmp_platform_command import PlatformCommands
from rcm_platform.rcmp_service_command import ServiceCommands
from tests.unit.rcm_platform.test_rcmp_command import DataTestCase
from tests.unit.rcm_platform.test_rcmp_ext_connector import ResourceTests
from tests.unit.rcm_platform.test_rcmp_platform_command import Placement


class ReadEncodedOnceTests(DataTestCase):
    render = ResourceTests.render

    def setUp(self):
        super().setUp()
        self.placement = Placement()
        self.resource = Rdapi(PlatformCommands(self.data, robots=self.placement), ServiceCommands(self.data))
        self.encoded = []
        dumps = self.resource._dumps

        def counting(payload):
            if isinstance(payload.get("reason"), list):        # a robots' read (not a write's sentence)
                self.encoded.append(payload)
            return dumps(payload)
        self.resource._dumps = counting
        for name in ("r1", "r2"):
            self.data.provision_platform_instance(name, "empty")

    @defer.inlineCallbacks
    def read(self):
        code, body, _ = yield self.render("GET", "/platform_instance/read")
        self.assertEqual(code, 200)
        return json.loads(body)["reason"]

    @defer.inlineCallbacks
    def test_reads_while_nothing_changed_are_not_encoded_again(self):
        self.placement.place("r1", "vm1")
        first = yield self.read()
        for _ in range(5):
            self.assertEqual((yield self.read()), first)
        self.assertEqual(len(self.encoded), 1)

    @defer.inlineCallbacks
    def test_a_write_and_a_placement_are_in_the_next_answer(self):
        yield self.read()
        code, _, _ = yield self.render("POST", "/platform_instance/provisioning",
                                       b'{"pi_name": "r3", "pi_service_logic": "empty"}')
        self.assertEqual(code, 200)
        self.assertEqual([r["pi_name"] for r in (yield self.read())], ["r1", "r2", "r3"])
        self.data.set_connected("r2", "198.51.100.9")          # a write of the master runtime
        self.assertTrue((yield self.read())[1]["connected"])
        self.placement.place("r2", "vm3")
        self.assertEqual((yield self.read())[1].get("server"), "vm3")
        self.placement.place("r2", "vm4")                       # moved by a failover
        self.assertEqual((yield self.read())[1].get("server"), "vm4")
        self.assertEqual(len(self.encoded), 5)                  # once per change, no more
        yield self.read()
        self.assertEqual(len(self.encoded), 5)
