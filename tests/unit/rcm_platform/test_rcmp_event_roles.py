"""Who may say hello as what (issue 18 row 6), with the real MasterAgent and real agents over loopback TCP.

Written as the attacker of row 6 ran it: the client file of a name that is not a provisioned robot (a retired
robot) says hello as a server VM. With a managed VPN the certificate's role decides (``certificate_of`` gives
what the VPN's register says, as ``rcmp_vpn.certificate_of`` does on a real master; the register itself is
tested in ``test_rcmp_vpn.py``, real OpenVPN in ``tests/system/test_vpn_roles.py``); without one the master's
``servers`` allow-list does. Also: what r_provisioning tells the operator about a removed robot's certificate.
"""

from twisted.internet import defer, reactor

from rcm_platform import rcmp_event, rcmp_vpn
from rcm_platform.rcmp_platform_command import PlatformCommands
from tests.unit.rcm_platform.test_rcmp_event import Runner, Spaces, config
from tests.unit.rcm_platform.test_rcmp_event_admission import MasterCase, hello_body, until


class ServerSpaces(Spaces):
    """The space manager stand-in, with the server VMs it was given (``add_server``) recorded."""

    def __init__(self):
        super().__init__()
        self.servers = {}
        self.builds = {}

    def add_server(self, name, session, capacity, address, builds=None):
        self.servers[name] = (session, capacity, address)
        self.builds[name] = builds

    def remove_server(self, name, why):
        self.servers.pop(name, None)
        return defer.succeed(None)

    def spaces_of(self, name):
        return []


def logged_refusals(log, start):
    """The lines of ``log`` at warning level or above starting with ``start`` (repeats go to debug)."""
    return [line for line, level in zip(log.lines, log.levels) if line.startswith(start) and level >= 30]


def server_hello(name, address):
    return dict(hello_body(name, address), robot=False)


class ServerCase(MasterCase):
    """A master whose space manager stand-in records the server VMs it is given."""

    def setUp(self):
        d = super().setUp()

        def swap(_):
            self.spaces = ServerSpaces()
            self.spaces.on_state = self.master._on_state
            self.master.spaces = self.spaces
        return d.addCallback(swap)


class RoleCase(ServerCase):
    """A master whose managed VPN issued ``retired`` a robot certificate (at 127.0.0.5), ``vm1`` a server one (at
    127.0.0.6), ``vm2`` a server one too (at 127.0.0.4) although ``vm2`` is also provisioned as a robot, ``old``
    one before roles (at 127.0.0.7), and ``gone`` a robot certificate since revoked."""

    provisioned = ("robot1", "vm2")
    issued = {"robot1": ("127.0.0.2", "robot", False), "retired": ("127.0.0.5", "robot", False),
              "vm1": ("127.0.0.6", "server", False), "vm2": ("127.0.0.4", "server", False),
              "old": ("127.0.0.7", "robot", False), "gone": ("127.0.0.8", "robot", True)}

    def setUp(self):
        def certificate_of(name):
            if name not in self.issued:
                return rcmp_vpn.Certificate(None, None, False, "no VPN certificate was issued to it")
            return rcmp_vpn.Certificate(*self.issued[name], None)
        self.certificate_of = certificate_of
        return super().setUp()

    def agent(self, name, address, role):
        agent = rcmp_event.RobotAgent(config(name, address, self.port, role=role), None, reactor,
                                      runner=Runner())
        agent.startService()
        self.addCleanup(lambda: agent.running and agent.stopService())
        return agent


class ManagedVpnRoleTests(RoleCase):

    @defer.inlineCallbacks
    def test_a_retired_robots_certificate_saying_hello_as_a_server_is_refused_and_gets_no_space(self):
        # the attack: the real agent of a server VM, run with the client file of a robot that is not provisioned
        attacker = self.agent("retired", "127.0.0.5", "server")
        yield until(lambda: self.master.counters["refused_wrong_role"] >= 3, timeout=15)
        self.assertEqual(self.master.servers, {})
        self.assertEqual(self.spaces.servers, {})                 # never a place for a service space
        self.assertFalse(attacker.accepted)
        # a robot that arrives meanwhile gets its space from the space manager as usual, nothing on the attacker
        robot = self.agent("robot1", "127.0.0.2", "robot")
        yield until(lambda: "paired" in self.data.names("robot1"))
        self.assertTrue(robot.accepted)
        self.assertEqual(self.spaces.created, [("robot1", "robot1", "127.0.0.2")])
        # the attacker retries every few seconds: its refusal is logged once, and says what to do
        refusals = logged_refusals(self.log, "refused hello as a server for retired")
        self.assertEqual(len(refusals), 1, refusals)
        self.assertIn("is a robot certificate", refusals[0])
        self.assertIn("from 127.0.0.5", refusals[0])

    @defer.inlineCallbacks
    def test_the_refusal_names_the_role_and_how_to_issue_a_server_certificate(self):
        peer = yield self.connect("127.0.0.5")
        reason = yield self.refused(peer, server_hello("retired", "127.0.0.5"), "wrong_role")
        self.assertIn("'retired' holds a robot certificate", reason)
        self.assertIn("rcmp_n vpn client retired --server", reason)
        self.assertLess(len(reason), 300)

    @defer.inlineCallbacks
    def test_a_certificate_issued_before_roles_is_a_robots(self):
        peer = yield self.connect("127.0.0.7")
        yield self.refused(peer, server_hello("old", "127.0.0.7"), "wrong_role")
        self.assertEqual(self.master.servers, {})

    @defer.inlineCallbacks
    def test_a_server_certificate_joins_as_a_server_and_cannot_say_hello_as_a_robot(self):
        server = self.agent("vm1", "127.0.0.6", "server")
        # the master counts vm1 a server before its answer reaches vm1: wait for both
        yield until(lambda: "vm1" in self.master.servers and server.accepted)
        self.assertEqual(self.spaces.servers["vm1"][2], "127.0.0.6")
        peer = yield self.connect("127.0.0.6")
        reason = yield self.refused(peer, hello_body("vm1", "127.0.0.6"), "wrong_role")
        self.assertIn("'vm1' holds a server certificate", reason)
        self.assertIn("only as a server VM", reason)
        self.assertFalse(self.master.servers["vm1"].ended)  # the server's own session is untouched
        # vm2 is also provisioned as a robot (the RDAPI allows it while no server of that name is connected): its
        # server certificate still cannot bring up a robot's session and the robot-side items of a service logic
        lookups = list(self.data.lookups)
        peer = yield self.connect("127.0.0.4")
        reason = yield self.refused(peer, hello_body("vm2", "127.0.0.4"), "wrong_role")
        self.assertIn("'vm2' holds a server certificate", reason)
        self.assertEqual(self.master.sessions, {})
        self.assertEqual(self.spaces.created, [])
        self.assertEqual(self.data.lookups, lookups)     # refused before provisioning was looked up

    @defer.inlineCallbacks
    def test_the_address_rule_still_comes_first(self):
        # a server certificate's holder naming another server from its own address: wrong_address, not a role
        peer = yield self.connect("127.0.0.6")
        yield self.refused(peer, server_hello("retired", "127.0.0.6"), "wrong_address")
        peer = yield self.connect("127.0.0.9")
        yield self.refused(peer, server_hello("nobody", "127.0.0.9"), "wrong_address")


class AllowListCase(ServerCase):
    """No managed VPN; the master's ``servers`` key: vm1 from anywhere, vm2 only from 127.0.0.8."""

    provisioned = ("robot1",)
    master_keys = {"servers": {"vm1": None, "vm2": "127.0.0.8"}}


class AllowListTests(AllowListCase):

    @defer.inlineCallbacks
    def test_a_name_not_in_the_list_cannot_join_as_a_server(self):
        peer = yield self.connect("127.0.0.5")
        reason = yield self.refused(peer, server_hello("intruder", "127.0.0.5"), "wrong_role")
        self.assertIn("'intruder' is not one of this master's server VMs", reason)
        self.assertIn("servers", reason)
        self.assertEqual(self.spaces.servers, {})

    @defer.inlineCallbacks
    def test_listed_names_join_and_a_pinned_address_is_checked(self):
        peer = yield self.connect("127.0.0.6")
        answer = yield peer.request("hello", server_hello("vm1", "127.0.0.6"))
        self.assertTrue(answer["accepted"])
        elsewhere = yield self.connect("127.0.0.7")
        reason = yield self.refused(elsewhere, server_hello("vm2", "127.0.0.8"), "wrong_address")
        self.assertIn("127.0.0.8", reason)
        self.assertIn("127.0.0.7", reason)
        own = yield self.connect("127.0.0.8")
        answer = yield own.request("hello", server_hello("vm2", "127.0.0.8"))
        self.assertTrue(answer["accepted"])
        self.assertEqual(sorted(self.spaces.servers), ["vm1", "vm2"])

    @defer.inlineCallbacks
    def test_robots_are_not_affected(self):
        peer = yield self.connect("127.0.0.2")
        answer = yield peer.request("hello", hello_body("robot1"))
        self.assertTrue(answer["accepted"])


class EmptyAllowListTests(AllowListCase):

    master_keys = {"servers": {}}

    @defer.inlineCallbacks
    def test_an_empty_list_lets_no_server_join(self):
        peer = yield self.connect("127.0.0.6")
        yield self.refused(peer, server_hello("vm1", "127.0.0.6"), "wrong_role")


class NoAllowListTests(AllowListCase):

    master_keys = {"servers": None}

    @defer.inlineCallbacks
    def test_without_a_list_and_a_managed_vpn_any_name_that_is_not_a_robots_may_join(self):
        peer = yield self.connect("127.0.0.5")
        answer = yield peer.request("hello", server_hello("anyname", "127.0.0.5"))
        self.assertTrue(answer["accepted"])
        robot_name = yield self.connect("127.0.0.6")
        yield self.refused(robot_name, server_hello("robot1", "127.0.0.6"), "name_taken")


class BothRulesTests(RoleCase):
    """With a managed VPN and a list, both must hold."""

    master_keys = {"servers": {"vm2": None}}

    @defer.inlineCallbacks
    def test_a_server_certificate_not_in_the_list_is_refused(self):
        peer = yield self.connect("127.0.0.6")
        reason = yield self.refused(peer, server_hello("vm1", "127.0.0.6"), "wrong_role")
        self.assertIn("not one of this master's server VMs", reason)


class RemovalAdviceTests(RoleCase):

    @defer.inlineCallbacks
    def test_removing_a_robot_with_a_valid_certificate_says_how_to_revoke_it(self):
        commands = PlatformCommands(self.data, robots=self.master)
        self.data.remove_platform_instance = lambda name: self.data.provisioned.discard(name)
        robot = self.agent("robot1", "127.0.0.2", "robot")
        yield until(lambda: "paired" in self.data.names("robot1"))
        reason = yield commands.r_provisioning({"pi_name": "robot1"})
        self.assertEqual(reason, "platform instance 'robot1' removed after disconnecting it; its VPN certificate "
                                 "still lets it join the platform's VPN as a robot: run 'rcmp_n vpn revoke robot1' "
                                 "on the master to cut it off")
        self.assertTrue(any("rcmp_n vpn revoke robot1" in line for line in self.log.lines))
        # the removed robot keeps saying hello: refused, as a robot and (its certificate's role) as a server
        yield until(lambda: self.master.counters["refused_not_provisioned"] >= 1, timeout=15)
        self.assertFalse(robot.accepted)
        peer = yield self.connect("127.0.0.2")
        yield self.refused(peer, server_hello("robot1", "127.0.0.2"), "wrong_role")

    @defer.inlineCallbacks
    def test_no_advice_for_a_revoked_certificate_or_without_a_managed_vpn(self):
        self.assertIsNone(self.master.certificate_advice("gone"))
        self.assertIsNone(self.master.certificate_advice("never_issued"))
        self.master.certificate_of = lambda name: None
        self.assertIsNone(self.master.certificate_advice("robot1"))
        commands = PlatformCommands(self.data, robots=self.master)
        self.data.remove_platform_instance = lambda name: self.data.provisioned.discard(name)
        reason = yield commands.r_provisioning({"pi_name": "robot1"})
        self.assertEqual(reason, "platform instance 'robot1' removed")


class RefusalLogTests(RoleCase):

    @defer.inlineCallbacks
    def test_each_agent_and_reason_is_logged_once_and_the_memory_is_bounded(self):
        self.patch(rcmp_event, "MAX_REFUSALS_REMEMBERED", 3)
        for _ in range(4):
            peer = yield self.connect("127.0.0.5")
            yield self.refused(peer, server_hello("retired", "127.0.0.5"), "wrong_role")
        peer = yield self.connect("127.0.0.7")
        yield self.refused(peer, server_hello("old", "127.0.0.7"), "wrong_role")
        lines = logged_refusals(self.log, "refused hello as a server")
        self.assertEqual(len(lines), 2, lines)
        self.assertEqual(self.master.counters["refused_wrong_role"], 5)
        self.assertLessEqual(len(self.master._refusals_logged), 3)
        # after the quiet time the same refusal is logged again
        self.patch(rcmp_event, "REFUSAL_QUIET", 0.0)
        peer = yield self.connect("127.0.0.5")
        yield self.refused(peer, server_hello("retired", "127.0.0.5"), "wrong_role")
        lines = logged_refusals(self.log, "refused hello as a server")
        self.assertEqual(len(lines), 3, lines)
