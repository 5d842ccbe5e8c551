"""rcmp_service_command: the service logic commands and service_space/read behind the RDAPI, on real SQLite
(twisted.trial)."""

from twisted.internet import defer

from rcm_platform.rcmp_command import BadRequest, Conflict, NotFound
from rcm_platform.rcmp_service_command import ServiceCommands
from tests.unit.rcm_platform.test_rcmp_command import DataTestCase


class Spaces:
    def __init__(self, spaces):
        self.spaces = spaces

    def describe(self, ss_name):
        return self.spaces.get(ss_name)


class ServiceCommandTests(DataTestCase):
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
