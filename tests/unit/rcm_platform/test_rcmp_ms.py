"""rcmp_ms without processes: a service space's closed set of states, where a new space is placed, and which ROS
master URI the master accepts from the remote agent that started a space's ROS master."""

import pytest

from rcm_platform import rcmp_ms
from rcm_platform.rcmp_ms import Server, choose_server
from rcm_platform.rcmp_process import InvalidTransition


def test_a_space_changes_state_only_as_its_closed_set_allows():
    space = rcmp_ms.ServiceSpace("robot1", "S", "ss", None, "master")
    assert (space.state, space.creating, space.paired, space.cancelled) == ("creating", True, False, False)
    with pytest.raises(InvalidTransition):
        space.transition(rcmp_ms.SPACE_GONE, "a space is stopped before it is gone")
    space.transition(rcmp_ms.SPACE_UNPAIRED, "created")
    space.transition(rcmp_ms.SPACE_PAIRED, "its items run")
    assert space.paired and not space.creating
    with pytest.raises(InvalidTransition):
        space.transition(rcmp_ms.SPACE_CREATING, "never again")
    space.transition(rcmp_ms.SPACE_STOPPING, "teardown")
    assert space.cancelled and not space.paired
    with pytest.raises(InvalidTransition):
        space.transition(rcmp_ms.SPACE_PAIRED, "a stopping space never pairs again")
    space.transition(rcmp_ms.SPACE_GONE, "torn down")
    assert space.cancelled
    with pytest.raises(InvalidTransition):
        space.transition("lost", "not a state")


def test_placement_goes_to_the_lowest_load_ties_to_the_master_then_by_name():
    master, vm1, vm2 = Server("master", 1, "a"), Server("vm1", 2, "b", host=object()), Server("vm2", 1, "c", host=1)
    servers = [vm2, vm1, master]
    assert choose_server(servers, {}) is master                          # all at 0: the master
    assert choose_server(servers, {"master": 1}) is vm1                  # master full; vm1 and vm2 at 0: by name
    assert choose_server(servers, {"master": 1, "vm1": 1}) is vm2        # vm1 at 1/2, vm2 at 0/1
    assert choose_server(servers, {"master": 1, "vm1": 1, "vm2": 1}) is vm1
    assert choose_server(servers, {"master": 1, "vm1": 2, "vm2": 1}) is None   # no room anywhere
    assert choose_server([Server("master", 0, "a")], {}) is None         # 0: a pure coordinator


ROBOT = "198.51.100.7"


@pytest.mark.parametrize("answer, accepted", [
    ("http://198.51.100.7:11311/", "http://198.51.100.7:11311/"),
    ("http://198.51.100.7:11311", "http://198.51.100.7:11311/"),
    ("http://198.51.100.7:01131/", "http://198.51.100.7:1131/"),
    ("http://198.51.100.7:65535/", "http://198.51.100.7:65535/"),
])
def test_a_remote_ros_master_uri_on_the_agents_own_address_is_accepted(answer, accepted):
    assert rcmp_ms.remote_master_uri(answer, ROBOT) == accepted


@pytest.mark.parametrize("answer", [
    "http://198.51.100.8:11311/",                 # another host
    "http://127.0.0.1:11311/",                    # the master's own loopback
    "http://localhost:11311/",
    "http://198.51.100.70:11311/",                # a prefix of the address is not the address
    "http://198.51.100.07:11311/",                # the same address written otherwise
    "http://198.51.100.7.evil.example:11311/",
    "https://198.51.100.7:11311/",                # another scheme
    "HTTP://198.51.100.7:11311/",
    "file:///etc/passwd",
    "http://198.51.100.7/",                       # no port
    "http://198.51.100.7:0/",
    "http://198.51.100.7:011311/",
    "http://198.51.100.7:70000/",
    "http://198.51.100.7:11311:80/",
    "http://198.51.100.7:１１３１１/",              # digits of another script
    "http://198.51.100.7:11311/RPC2",             # a path
    "http://198.51.100.7:11311/../",
    "http://198.51.100.7:11311/?x=1",             # a query, a fragment
    "http://198.51.100.7:11311/#x",
    "http://user@198.51.100.7:11311/",            # a user
    "http://198.51.100.7@198.51.100.8:11311/",
    "http://198.51.100.7:11311/\n",               # trailing and leading bytes
    " http://198.51.100.7:11311/",
    "http://198.51.100.7:11311/\x00",
    "http://[::1]:11311/",
    "",
    None,
    11311,
    ["http://198.51.100.7:11311/"],
])
def test_any_other_remote_ros_master_uri_is_refused(answer):
    assert rcmp_ms.remote_master_uri(answer, ROBOT) is None


def test_without_a_known_address_nothing_is_accepted():
    assert rcmp_ms.remote_master_uri("http://198.51.100.7:11311/", None) is None


def test_a_peers_item_report_is_kept_bounded_and_never_whole():
    report = {"kind": "node", "name": "n" * 1000000, "state": float("nan"), "error": "e" * 100000,
              "nodes": ["a"] * 5000 + [7, None], "node_types": {"a": ["pkg", "type"], "b": "not a pair"},
              "extra": "x" * 100000, "i_name": ["not", "text"]}
    kept = rcmp_ms.received_report(report)
    assert set(kept) == {"kind", "name", "package", "type_or_file", "side", "i_name", "state", "error", "nodes",
                         "node_types"}
    assert len(kept["name"]) == rcmp_ms.REPORTED_NAME and len(kept["error"]) == rcmp_ms.REPORTED_TEXT
    assert kept["state"] == "failed" and kept["i_name"] is None
    assert len(kept["nodes"]) == rcmp_ms.REPORTED_NODES
    assert kept["node_types"] == {"a": ["pkg", "type"]}
    assert rcmp_ms.received_report({"kind": "node", "name": "x", "state": "running"})["state"] == "running"
