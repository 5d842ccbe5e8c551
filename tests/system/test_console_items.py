"""The console's event stream with real child processes as service items: an item that exits is pushed with its
error, a space's log tails are pushed to the page that shows it (``tests/unit/rcm_platform/test_rcmp_console.py``
has the rest of the stream, with the same stand-ins)."""

import os

from twisted.internet import defer

from tests.unit.rcm_platform.test_rcmp_console import ConsoleCase, FakeItem, FakeSpace


class ConsoleItemsTest(ConsoleCase):

    @defer.inlineCallbacks
    def test_an_item_that_exits_is_pushed_with_its_error_and_the_teardown_removes_the_space(self):
        yield self.console.next_snapshot()
        request, _ = self.open()
        process = self.table.spawn("ss/robot1/node/crash", ["/bin/sh", "-c", "echo cannot open the lidar >&2; "
                                                            "exit 3"], dict(os.environ), "robot1-crash")
        self.spaces.add(FakeSpace("robot1", [FakeItem("node", "crash", process)]))

        def crashed(name, data):
            if name != "patch":
                return False
            nodes = (data.get("spaces") or {}).get("changed", {}).get("robot1", {}).get("r_nodes", [])
            return name == "patch" and nodes and nodes[0]["state"] == "failed"
        yield self.wait_event(request, crashed, "the item's failure to be pushed")
        node = request.last("patch")["spaces"]["changed"]["robot1"]["r_nodes"][0]
        self.assertIn("cannot open the lidar", node["error"])
        self.assertIn("status 3", node["error"])
        self.spaces.remove("robot1")
        yield self.wait_event(request, lambda n, d: n == "patch" and (d.get("spaces") or {}).get("gone") == [
            "robot1"], "the teardown to be pushed")

    @defer.inlineCallbacks
    def test_a_stream_with_ss_name_gets_the_items_log_tails(self):
        process = self.table.spawn("ss/robot2/node/talk", ["/bin/sh", "-c", "echo hello from the talker; "
                                                           "sleep 30"], dict(os.environ), "robot2-talk")
        self.spaces.add(FakeSpace("robot2", [FakeItem("node", "talk", process)]))
        request, _ = self.open(args={b"ss_name": [b"robot2"]})

        def tail_seen(name, data):
            if name != "detail":
                return False
            items = (data.get("detail") or {}).get("items", [])
            return items and "hello from the talker" in items[0].get("tail", "")
        yield self.wait_event(request, tail_seen, "the log tail to be pushed")
        yield self.table.stop("ss/robot2/node/talk")
