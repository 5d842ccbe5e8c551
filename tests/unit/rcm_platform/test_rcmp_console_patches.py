"""The console's patches at fleet scale (rcmp_console.Console, ``rows_patch``): robots and servers by changed row, a
rebuild that describes only the spaces that changed and reads the robots in a fixed number of queries, and a page
that applies the patches ending with the state a new page gets. Real RoboticsData (SQLite), the RDAPI's own
PlatformCommands, a stand-in space manager (``test_rcmp_console.StandInSpaces``)."""

import json

from twisted.internet import defer
from twisted.trial import unittest

from rcm_platform import rcmp_console
from tests.unit.rcm_platform.test_rcmp_console import ConsoleCase, FakeItem, FakeSpace


def apply_rows(rows, patch):
    """What the page's ``applyRows`` (console.js) does with a patch's ``robots`` or ``servers``."""
    if isinstance(patch, list):
        return patch
    by_name = {row["pi_name"]: row for row in rows}
    for name in patch["gone"]:
        by_name.pop(name, None)
    for name, row in patch["changed"].items():
        by_name[name] = row
    if "order" in patch:
        return [by_name[name] for name in patch["order"] if name in by_name]
    return list(by_name.values())


class RowsPatchTests(unittest.TestCase):
    def rows(self, *names, **changed):
        return [{"pi_name": n, "connected": n in changed} for n in names]

    def test_only_what_changed(self):
        old = self.rows("a", "b", "c")
        self.assertIsNone(rcmp_console.rows_patch(old, old))
        self.assertIsNone(rcmp_console.rows_patch(old, [dict(r) for r in old]))
        new = self.rows("a", "b", "c", b=True)
        self.assertEqual(rcmp_console.rows_patch(old, new),
                         {"changed": {"b": {"pi_name": "b", "connected": True}}, "gone": []})
        self.assertEqual(rcmp_console.rows_patch(old, self.rows("a", "c")), {"changed": {}, "gone": ["b"]})

    def test_order_only_when_the_readers_rule_would_not_give_it(self):
        old = self.rows("b", "a")
        new = self.rows("b", "a", "c", "d")              # new rows come last, by name: no "order"
        self.assertNotIn("order", rcmp_console.rows_patch(old, new))
        for new in (self.rows("b", "a", "d", "c"), self.rows("a", "b")):
            patch = rcmp_console.rows_patch(old, new)
            self.assertEqual(patch["order"], [r["pi_name"] for r in new])
            self.assertEqual(apply_rows(old, json.loads(json.dumps(patch, sort_keys=True))), new)


class FakeProcess:
    def __init__(self):
        self.state, self.error = "running", None


class ConsolePatchTest(ConsoleCase):
    limits = {"max_clients": 8}

    def setUp(self):
        super().setUp()
        self.described = []
        describe = self.spaces.describe

        def counting(ss_name):
            self.described.append(ss_name)
            return describe(ss_name)
        self.console.describe = counting

    def wait_for(self, request, predicate, message):
        return self.wait_event(request, lambda n, d: n == "patch" and predicate(d), message)

    @defer.inlineCallbacks
    def test_a_patch_carries_only_the_robot_rows_that_changed(self):
        for i in range(40):
            self.data.provision_platform_instance(f"robot{i}", "empty")
        request, _ = self.open()
        yield self.wait_event(request, lambda n, d: n == "snapshot" and len(d["robots"]) == 40, "the snapshot")
        before = len(b"".join(request.written))
        self.data.set_connected("robot7", "203.0.113.7")
        yield self.wait_for(request, lambda d: "robot7" in d.get("robots", {}).get("changed", {}), "robot7's row")
        patch = request.last("patch")
        self.assertEqual(patch["robots"], {"changed": {"robot7": {
            "pi_name": "robot7", "service_logic": "empty", "connected": True, "paired": False,
            "address": "203.0.113.7"}}, "gone": []})
        self.assertLess(len(b"".join(request.written)) - before, 400)    # one row, not forty
        self.data.remove_platform_instance("robot3")
        yield self.wait_for(request, lambda d: d.get("robots", {}).get("gone") == ["robot3"], "robot3 gone")
        self.assertEqual(request.last("patch")["robots"]["changed"], {})

    @defer.inlineCallbacks
    def test_a_page_applying_the_patches_has_what_a_new_page_gets(self):
        for i in range(6):
            self.data.provision_platform_instance(f"robot{i}", "empty")
        request, _ = self.open()
        yield self.wait_event(request, lambda n, d: n == "snapshot", "the snapshot")
        steps = [lambda: self.data.set_connected("robot2", "203.0.113.2"),
                 lambda: self.data.provision_platform_instance("zed", "empty"),
                 lambda: self.data.provision_platform_instance("alpha", "empty"),
                 lambda: (self.data.remove_platform_instance("robot1"),       # provisioned again in the same
                          self.data.provision_platform_instance("robot1", "empty")),   # rebuild: last now
                 lambda: self.data.set_paired("robot2", True),
                 lambda: self.data.remove_platform_instance("robot4")]
        for step in steps:
            step()
            yield self.console.next_snapshot()
        robots = None
        for name, data in request.events():
            if name == "snapshot":
                robots = data["robots"]
            elif name == "patch" and "robots" in data:
                robots = apply_rows(robots, data["robots"])
        self.assertTrue(any("order" in d.get("robots", {}) for n, d in request.events() if n == "patch"))
        fresh, _ = self.open()                                   # a page connecting (again) gets the whole state
        yield self.wait_event(fresh, lambda n, d: n == "snapshot", "the new page's snapshot")
        self.assertEqual(robots, fresh.last("snapshot")["robots"])
        self.assertEqual([r["pi_name"] for r in robots], ["robot0", "robot2", "robot3", "robot5", "zed", "alpha",
                                                          "robot1"])

    @defer.inlineCallbacks
    def test_a_rebuild_describes_only_the_spaces_that_changed(self):
        processes = {}
        for i in range(12):
            processes[i] = FakeProcess()
            self.spaces.add(FakeSpace(f"space{i}", [FakeItem("node", "n", processes[i])]))
        request, _ = self.open()
        yield self.wait_event(request, lambda n, d: n == "snapshot" and len(d["spaces"]) == 12, "the snapshot")
        del self.described[:]
        processes[5].state = "failed"
        self.spaces._tell("space5")                              # the manager says space5 changed
        yield self.wait_for(request, lambda d: "space5" in d.get("spaces", {}).get("changed", {}), "space5")
        self.assertEqual(self.described, ["space5"])
        self.assertEqual(list(request.last("patch")["spaces"]["changed"]), ["space5"])
        del self.described[:]
        processes[8].state = "exited"                            # a process of space8 (key ss/space8/...)
        self.console._process_changed(type("Managed", (), {"key": "ss/space8/node/n"})(), "running", "exited")
        yield self.wait_for(request, lambda d: "space8" in d.get("spaces", {}).get("changed", {}), "space8")
        self.assertEqual(self.described, ["space8"])
        del self.described[:]
        self.data.provision_platform_instance("robot1", "empty")  # a write: no space described again
        yield self.console.next_snapshot()
        self.assertEqual(self.described, [])
        processes[1].state = "exited"
        self.spaces._tell(None)                                  # a server joined or went: every space
        yield self.wait_for(request, lambda d: "space1" in d.get("spaces", {}).get("changed", {}), "space1")
        self.assertEqual(sorted(self.described), sorted(f"space{i}" for i in range(12)))
        self.spaces.remove("space3")
        yield self.wait_for(request, lambda d: d.get("spaces", {}).get("gone") == ["space3"], "space3 gone")
        fresh, _ = self.open()
        yield self.wait_event(fresh, lambda n, d: n == "snapshot", "the new page's snapshot")
        self.assertEqual(fresh.last("snapshot")["spaces"], {n: self.spaces.describe(n) for n in self.spaces.spaces})

    @defer.inlineCallbacks
    def test_a_rebuild_reads_the_robots_in_a_number_of_queries_that_does_not_grow_with_them(self):
        request, _ = self.open()
        yield self.wait_event(request, lambda n, d: n == "snapshot", "the snapshot")

        @defer.inlineCallbacks
        def queries_of_one_rebuild(robots):
            for i in range(robots):
                self.data.provision_platform_instance(f"r{robots}_{i}", "empty")
            yield self.console.next_snapshot()
            statements = []
            self.data._db.set_trace_callback(statements.append)
            try:
                self.data.set_connected(f"r{robots}_0", "203.0.113.1")
                yield self.console.next_snapshot()
            finally:
                self.data._db.set_trace_callback(None)
            return len([s for s in statements if s.lstrip().upper().startswith("SELECT")])
        few = yield queries_of_one_rebuild(3)
        many = yield queries_of_one_rebuild(60)
        self.assertEqual(few, many)
