"""Space builds bounded per machine, with the real MasterAgent and real agents over loopback TCP: a server VM's hello
announces how many spaces it builds at once (``max_starting_spaces``, two per core unless its ``.init.cfg`` says),
a server that does not say (an older agent) gets ``SERVER_STARTING_SPACES``, an impossible count is refused; the
platform builds the master's count plus each connected server's at once, so a server joining lets more build."""

from twisted.internet import defer, reactor

from rcm_platform import rcmp_event
from rcm_platform.rcmp_config import SERVER_STARTING_SPACES, default_max_starting_spaces
from rcm_platform.rcmp_service_command import ServiceCommands
from tests.unit.rcm_platform.test_rcmp_event import Runner, config
from tests.unit.rcm_platform.test_rcmp_event_admission import BlockingSpaces, hello_body, until
from tests.unit.rcm_platform.test_rcmp_event_roles import ServerCase, ServerSpaces, server_hello


class AnnouncedBuildsTests(ServerCase):

    master_keys = {"max_starting_spaces": 3}

    def server_agent(self, name, address, **keys):
        cfg = config(name, address, self.port, role="server")
        for key, value in keys.items():
            setattr(cfg, key, value)
        agent = rcmp_event.RobotAgent(cfg, None, reactor, runner=Runner())
        agent.startService()
        self.addCleanup(lambda: agent.running and agent.stopService())
        return agent

    @defer.inlineCallbacks
    def test_a_server_announces_its_count_and_the_platform_adds_it(self):
        self.server_agent("vm1", "127.0.0.3", max_starting_spaces=7)
        self.server_agent("vm2", "127.0.0.4")
        yield until(lambda: {"vm1", "vm2"} <= set(self.spaces.servers))
        self.assertEqual(self.spaces.builds, {"vm1": 7, "vm2": default_max_starting_spaces()})
        self.assertEqual(self.master.build_limit(), 3 + 7 + default_max_starting_spaces())

    @defer.inlineCallbacks
    def test_a_server_that_does_not_say_gets_the_default(self):
        peer = yield self.connect("127.0.0.3")
        hello = server_hello("vm1", "127.0.0.3")           # as an older server agent sends it: no count
        self.assertNotIn("max_starting_spaces", hello)
        answer = yield peer.request("hello", hello, timeout=5)
        self.assertTrue(answer["accepted"])
        self.assertEqual(self.spaces.builds["vm1"], SERVER_STARTING_SPACES)
        self.assertEqual(self.master.build_limit(), 3 + SERVER_STARTING_SPACES)

    @defer.inlineCallbacks
    def test_an_impossible_count_is_refused(self):
        for count in (0, 1001):
            peer = yield self.connect("127.0.0.3")
            reason = yield self.refused(peer, dict(server_hello("vm1", "127.0.0.3"), max_starting_spaces=count),
                                        "bad_request")
            self.assertIn("max_starting_spaces must be between 1 and 1000", reason)
        self.assertEqual(self.master.servers, {})


class BlockingServerSpaces(BlockingSpaces, ServerSpaces):
    """Space creation held until the test releases it, with the server VMs recorded."""


class MoreBuildsWithServersTests(ServerCase):

    provisioned = tuple(f"robot{n}" for n in range(1, 6))
    master_keys = {"max_starting_spaces": 1}

    def setUp(self):
        d = super().setUp()

        def swap(_):
            self.spaces = BlockingServerSpaces()
            self.spaces.on_state = self.master._on_state
            self.master.spaces = self.spaces
        return d.addCallback(swap)

    @defer.inlineCallbacks
    def test_a_server_joining_lets_more_spaces_build_at_once(self):
        for n in range(1, 6):
            peer = yield self.connect(f"127.0.0.{n + 1}")
            yield peer.request("hello", hello_body(f"robot{n}"), timeout=5)
        yield until(lambda: self.spaces.running == 1)
        waiting = yield ServiceCommands(self.data, spaces=self.master).service_space("robot3")
        self.assertIn("number 2 in line", waiting["reason"])
        self.assertIn("at most 1 service spaces", waiting["reason"])
        server = yield self.connect("127.0.0.9")
        yield server.request("hello", dict(server_hello("vm1", "127.0.0.9"), max_starting_spaces=2), timeout=5)
        yield until(lambda: self.spaces.running == 3)      # the master's 1 and vm1's 2
        self.assertEqual(sorted(self.spaces.releases), ["robot1", "robot2", "robot3"])   # in arrival order
        for n in range(1, 6):
            yield until(lambda: f"robot{n}" in self.spaces.releases)
            self.spaces.releases[f"robot{n}"].callback(None)
        yield until(lambda: all("paired" in self.data.names(f"robot{n}") for n in range(1, 6)))
        self.assertEqual(self.spaces.most, 3)
