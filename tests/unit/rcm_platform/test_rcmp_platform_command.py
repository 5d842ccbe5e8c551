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


class StandInSpace:
    def __init__(self, server):
        self.server = server


class Placement:
    """What the robots' read needs of the master runtime: ``server_of`` and its space manager's ``spaces`` and
    ``observers`` (told of every change of a space, as ``rcmp_ms.ServiceSpaceManager`` tells them)."""

    def __init__(self, observed=True):
        self.spaces = type("Spaces", (), {})()
        self.spaces.spaces = {}
        if observed:
            self.spaces.observers = []

    def server_of(self, pi_name):
        return getattr(self.spaces.spaces.get(pi_name), "server", None)

    def place(self, pi_name, server, tell=True):
        if server is None:
            self.spaces.spaces.pop(pi_name, None)
        else:
            self.spaces.spaces[pi_name] = StandInSpace(server)
        if tell:
            self.tell(pi_name)

    def tell(self, ss_name):
        for observer in list(getattr(self.spaces, "observers", [])):
            observer(ss_name)


class RobotsReadTests(DataTestCase):
    """The robots' read (``platform_instance/read``) is one object while nothing it shows changed, so that the RDAPI
    encodes it once; a write or a robot's new server is seen at the next read."""

    def setUp(self):
        super().setUp()
        self.placement = Placement()
        self.commands = PlatformCommands(self.data, robots=self.placement)
        for name in ("r1", "r2", "r3"):
            self.data.provision_platform_instance(name, "empty")

    @defer.inlineCallbacks
    def test_the_same_answer_while_nothing_changed(self):
        self.placement.place("r2", "vm1")
        first = yield self.commands.read()
        again = yield self.commands.read()
        self.assertIs(first, again)
        self.assertEqual([r.get("server") for r in first], [None, "vm1", None])
        self.placement.tell("r2")            # an item of r2's space changed, not its server
        self.assertIs((yield self.commands.read()), first)

    @defer.inlineCallbacks
    def test_a_write_is_seen_at_once(self):
        self.placement.place("r1", "vm1")
        yield self.commands.read()
        self.data.set_connected("r1", "198.51.100.4")
        rows = yield self.commands.read()
        self.assertEqual((rows[0]["connected"], rows[0]["server"]), (True, "vm1"))
        self.data.remove_platform_instance("r3")
        self.assertEqual([r["pi_name"] for r in (yield self.commands.read())], ["r1", "r2"])

    @defer.inlineCallbacks
    def test_a_placement_is_seen_at_once(self):
        first = yield self.commands.read()
        self.placement.place("r1", "vm1")              # placed
        rows = yield self.commands.read()
        self.assertEqual(rows[0]["server"], "vm1")
        self.assertNotIn("server", first[0])           # the answer given before is left as it was
        self.placement.place("r1", "vm2")              # moved (a failover)
        self.assertEqual((yield self.commands.read())[0]["server"], "vm2")
        self.placement.place("r1", None)               # torn down
        self.assertNotIn("server", (yield self.commands.read())[0])
        self.placement.place("r3", "vm1")
        self.placement.tell(None)                      # a server joined or went: a new answer, the same rows
        self.assertEqual([r.get("server") for r in (yield self.commands.read())], [None, None, "vm1"])

    @defer.inlineCallbacks
    def test_without_observers_every_read_asks_for_the_servers(self):
        placement = Placement(observed=False)
        commands = PlatformCommands(self.data, robots=placement)
        yield commands.read()
        placement.place("r2", "vm1", tell=False)
        self.assertEqual((yield commands.read())[1]["server"], "vm1")

    @defer.inlineCallbacks
    def test_spaces_placed_before_the_commands_were_made_are_followed(self):
        placement = Placement()
        placement.place("r1", "vm1")
        commands = PlatformCommands(self.data, robots=placement)
        self.assertEqual((yield commands.read())[0]["server"], "vm1")
        placement.place("r1", None)
        self.assertNotIn("server", (yield commands.read())[0])
