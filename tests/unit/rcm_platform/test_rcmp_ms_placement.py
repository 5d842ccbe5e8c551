"""The master's ServiceSpaceManager placing spaces on server VMs, with remote agents that answer ``start_items`` as
a server VM does (nothing runs on the master: its ``max_service_spaces`` is 0):

- each server builds at most its own count of spaces at once (``builds``), all servers at the same time;
- the placement counts (``hosted()``, ``spaces_of()``), kept per server as spaces come and go, equal a recount
  over every space after creates, teardowns, a failover and a server leaving.
"""

import collections
import os
import tempfile
import types

from twisted.internet import defer, reactor
from twisted.trial import unittest

from rcm_platform.rcmp_config import SERVER_STARTING_SPACES, make_config
from rcm_platform.rcmp_ms import ServiceSpaceManager
from rcm_platform.rcmp_process import ProcessTable
from tests.unit.rcm_platform.test_rcmp_event import until

LOGIC = {"ss_side": "S", "sn_list": [{"sn_package": "robotics_test", "sn_type": "talker.py", "sn_name": "talker",
                                      "sn_side": "S"}], "sl_list": []}


class ServerVM:
    """A server VM's agent as the master sees it: starts a space's ROS master and S items when asked (each
    answer held back while ``gated``), and counts how many it builds at once."""

    def __init__(self, name, address, gated=False):
        self.name = name
        self.address = address
        self.gated = gated
        self.held = []               # Deferreds of start_items answers held back
        self.building = 0
        self.most = 0
        self.ports = iter(range(11311, 20000))

    def start_items(self, ss_name, ros_master_uri, items, start_ros_master_port=None):
        self.building += 1
        self.most = max(self.most, self.building)
        answer = {"ros_master_uri": f"http://{self.address}:{next(self.ports)}/", "reason": None,
                  "inbound_port": None,
                  "items": [{"kind": "node", "name": i["sn_name"], "package": i["sn_package"],
                             "type_or_file": i["sn_type"], "side": "S", "i_name": self.name, "state": "running",
                             "error": None, "nodes": [f"/{i['sn_name']}"]} for i in items]}
        d = defer.Deferred()
        d.addBoth(self._built)
        if self.gated:
            self.held.append((d, answer))
        else:
            reactor.callLater(0, d.callback, answer)
        return d

    def _built(self, result):
        self.building -= 1
        return result

    def release(self):
        held, self.held = self.held, []
        for d, answer in held:
            d.callback(answer)
        return len(held)

    def stop_items(self, ss_name):
        return defer.succeed({})


class PlacementCase(unittest.TestCase):

    def setUp(self):
        home = tempfile.mkdtemp()
        config = make_config("master", home, vpn_address="127.0.0.1", max_service_spaces=0, max_starting_spaces=2)
        table = ProcessTable(reactor, os.path.join(home, "log"))
        self.manager = ServiceSpaceManager(reactor, table, config, "127.0.0.1", address="127.0.0.1")
        self.robots = {}

    def robot(self, name):
        return self.robots.setdefault(name, types.SimpleNamespace(name=name, address="127.0.0.2", ended=False))

    def recount(self):
        hosted, of_server = collections.Counter(), collections.defaultdict(list)
        for space in self.manager.spaces.values():
            of_server[space.server].append(space.name)
            if space.ss_side == "S":
                hosted[space.server] += 1
        return hosted, dict(of_server)

    def assert_counts(self):
        hosted, of_server = self.recount()
        self.assertEqual(self.manager.hosted(), hosted)
        names = set(self.manager.servers) | set(self.manager.gone) | set(of_server)
        for name in names:
            self.assertEqual(self.manager.spaces_of(name), of_server.get(name, []), name)


class BuildsPerServerTests(PlacementCase):

    @defer.inlineCallbacks
    def test_each_server_builds_its_own_count_at_once(self):
        vm1, vm2 = ServerVM("vm1", "127.0.0.3", gated=True), ServerVM("vm2", "127.0.0.4", gated=True)
        self.manager.add_server("vm1", vm1, 100, vm1.address, builds=2)
        self.manager.add_server("vm2", vm2, 100, vm2.address, builds=3)
        created = [self.manager.create(f"robot{n}", LOGIC, self.robot(f"robot{n}")) for n in range(12)]
        yield until(lambda: vm1.building == 2 and vm2.building == 3)   # both at once, each up to its count
        self.assertEqual(self.manager.hosted(), {"vm1": 6, "vm2": 6})  # placed by load, building or waiting
        while vm1.held or vm2.held:
            vm1.release()
            vm2.release()
            yield until(lambda: vm1.held or vm2.held or all(d.called for d in created))
        spaces = yield defer.gatherResults(created)
        self.assertTrue(all(space.paired for space in spaces), [s.why_unpaired() for s in spaces])
        self.assertEqual((vm1.most, vm2.most), (2, 3))

    @defer.inlineCallbacks
    def test_a_space_torn_down_while_it_waits_for_its_turn_is_never_built(self):
        vm1 = ServerVM("vm1", "127.0.0.3", gated=True)
        self.manager.add_server("vm1", vm1, 100, vm1.address, builds=1)
        first = self.manager.create("robot1", LOGIC, self.robot("robot1"))
        second = self.manager.create("robot2", LOGIC, self.robot("robot2"))
        yield until(lambda: vm1.held)
        yield self.manager.teardown("robot2")
        vm1.release()
        yield first
        space = yield second
        self.assertTrue(space.cancelled)
        self.assertEqual(vm1.most, 1)
        self.assertEqual(vm1.release(), 0)                 # robot2's items were never asked for
        self.assertEqual(self.manager.spaces_of("vm1"), ["robot1"])

    def test_a_server_that_does_not_say_gets_the_default(self):
        self.manager.add_server("old", ServerVM("old", "127.0.0.5"), 100, "127.0.0.5")
        self.assertEqual(self.manager.servers["old"].builds, SERVER_STARTING_SPACES)
        self.assertEqual(self.manager.servers[self.manager.name].builds, 2)   # the master's max_starting_spaces


class CountsTests(PlacementCase):

    @defer.inlineCallbacks
    def test_counts_equal_a_recount_through_create_teardown_failover_and_leaving(self):
        vms = {name: ServerVM(name, f"127.0.0.{n + 3}") for n, name in enumerate(("vm1", "vm2", "vm3"))}
        for vm in vms.values():
            self.manager.add_server(vm.name, vm, 100, vm.address, builds=4)
        yield defer.gatherResults([self.manager.create(f"robot{n}", LOGIC, self.robot(f"robot{n}"))
                                   for n in range(30)])
        self.assert_counts()
        self.assertEqual(self.manager.hosted(), {"vm1": 10, "vm2": 10, "vm3": 10})
        yield defer.gatherResults([self.manager.teardown(f"robot{n}") for n in range(0, 30, 3)])
        self.assert_counts()
        self.assertEqual(sum(self.manager.hosted().values()), 20)
        moved = self.manager.spaces_of("vm2")
        yield self.manager.remove_server("vm2", "its connection was lost")        # failover
        self.assert_counts()
        self.assertEqual(self.manager.spaces_of("vm2"), [])
        self.assertEqual(set(moved) <= set(self.manager.spaces_of("vm1") + self.manager.spaces_of("vm3")), True)
        self.manager.add_server("vm2", vms["vm2"], 100, "127.0.0.4", builds=4)    # it comes back
        yield defer.gatherResults([self.manager.create(f"robot{n}", LOGIC, self.robot(f"robot{n}"))
                                   for n in range(30, 36)])
        self.assert_counts()
        self.assertEqual(self.manager.hosted()["vm2"], 6)
        yield self.manager.create("robot31", LOGIC, self.robot("robot31"))       # the same robot again
        self.assert_counts()
        yield self.manager.remove_server("vm3", "it said bye")                   # leaving
        self.assert_counts()
        yield self.manager.teardown_all()
        self.assert_counts()
        self.assertEqual(self.manager.hosted(), {})
        self.assertEqual(self.manager.spaces_of("vm1"), [])

    @defer.inlineCallbacks
    def test_spaces_wait_for_room_and_are_counted_once_placed(self):
        vm1 = ServerVM("vm1", "127.0.0.3")
        self.manager.add_server("vm1", vm1, 2, vm1.address)
        results = yield defer.gatherResults([self.manager.create(f"robot{n}", LOGIC, self.robot(f"robot{n}"))
                                             for n in range(3)])
        self.assertIsNone(results[2])                      # no room: waiting
        self.assertIn("vm1 2/2", self.manager.waiting_reason("robot2"))
        self.assert_counts()
        yield self.manager.teardown("robot0")
        yield until(lambda: "robot2" in self.manager.spaces and self.manager.spaces["robot2"].paired)
        self.assert_counts()
        self.assertEqual(self.manager.spaces_of("vm1"), ["robot1", "robot2"])
