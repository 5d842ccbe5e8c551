"""rcmp_platform_command: the platform instance commands behind the RDAPI, on real SQLite (twisted.trial: Deferreds
run for real); a fake master runtime records what the commands asked of it."""

from twisted.internet import defer, threads

from rcm_platform.rcmp_command import BadRequest, NotFound
from rcm_platform.rcmp_platform_command import PlatformCommands
from tests.unit.rcm_platform.test_rcmp_command import DataTestCase


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


class PlatformCommandTests(DataTestCase):
    @defer.inlineCallbacks
    def test_r_provisioning_disconnects_a_connected_robot_first(self):
        robots = RecordingRobots(self.data)
        commands = PlatformCommands(self.data, robots=robots)
        yield commands.provisioning({"pi_name": "r1", "pi_service_logic": "empty"})
        self.data.set_connected("r1", "198.51.100.6")
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
        self.data.set_connected("r1", "198.51.100.6")  # a write by the master runtime, not through the commands
        live = yield commands.read()
        self.assertTrue(live[0]["connected"])
