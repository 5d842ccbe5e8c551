"""Server VMs host service spaces (issue 10 items 2 and 3, CONTRACTS §8): real agents on loopback addresses, real
ROS, provisioning through the RDAPI.

A master on 127.0.0.1, server VMs (``robot=no``) on 127.0.0.10 and .11 with their own ``ros_port_base``, robots on
127.0.0.2, .3, ... Each robot's service logic has a talker on each side, so a space is a ROS master, rosout, an S
node (on the chosen server) and an R node (on the robot). Every test ends with nothing of the platform left.
"""

import os
import signal
import time

import pytest

from tests.support.lifecycle import HEARTBEAT, Platform
from tests.support.polling import wait_until
from tests.support.firos import write_config
from tests.support.ports import port_accepts, ros_port_base, stable_free_ports

VM_ADDRESS = {"vm1": "127.0.0.10", "vm2": "127.0.0.11"}
START = 60   # seconds a space may take to start: a deadline for a machine loaded by other tests, not a target
LOGIC = {"sn_list": [
    {"sn_package": "robotics_test", "sn_type": "talker.py", "sn_name": "brain", "sn_params": "_topic:=brain_chatter",
     "sn_side": "S"},
    {"sn_package": "robotics_test", "sn_type": "talker.py", "sn_name": "body", "sn_params": "_topic:=body_chatter",
     "sn_side": "R"}]}


# -- real agents ------------------------------------------------------------------------------------------------

@pytest.fixture
def make_platform(procs, tmp_path):
    made = []

    def make(max_service_spaces):
        plat = Platform(procs, tmp_path, inbound_ports=0, max_service_spaces=max_service_spaces)
        made.append(plat)
        return plat
    try:
        yield make
    finally:
        for plat in made:
            plat.stop_all_and_check_nothing_left()


def start_server(plat, name, capacity):
    vm = plat.robot(name, VM_ADDRESS[name], role="server", max_service_spaces=capacity,
                    ros_port_base=ros_port_base(VM_ADDRESS[name]))
    vm.start()
    wait_until(lambda: name in servers(plat), timeout=30, message=f"server {name} to join")
    return vm


def servers(plat):
    """The connected servers of platform_instance/read?pi_type=S, by name."""
    return {name: row for name, row in all_servers(plat).items() if row["connected"]}


def all_servers(plat):
    status, answer = plat.master.get("/platform_instance/read?pi_type=S")
    assert status == 200, answer
    return {row["pi_name"]: row for row in answer["reason"]}


def start_robot(plat, name, index, wait=True):
    plat.provision_robot(name, "two_sides")
    robot = plat.robot(name, f"127.0.0.{index + 1}").start()
    if wait:
        plat.wait_state(name, True, True, timeout=START)
    return robot


def space(plat, name):
    status, answer = plat.space(name)
    assert status == 200, answer
    return answer


def check_placed_on(plat, name, server):
    """The space of ``name`` is on ``server``: said by service_space/read, its S node registered there with the
    server's address (ROS_IP) at its ROS master (ROS_MASTER_URI), and the R node at the same master."""
    address = "127.0.0.1" if server == "master" else VM_ADDRESS[server]
    described = space(plat, name)
    assert described["server"] == server, described
    assert described["public_ip"] == address
    assert described["ros_master_uri"].startswith(f"http://{address}:"), described
    where = {n["sn_name"]: n["i_name"] for n in described["r_nodes"]}
    assert where == {"brain": server, "body": name}
    master = plat.ros_master(name)
    wait_until(lambda: _registered(master, "/body"), timeout=START,
               message=f"{name}'s R node at its space's ROS master")
    brain = wait_until(lambda: _registered(master, "/brain"), timeout=START,
                       message=f"{name}'s S node at its space's ROS master")
    assert brain.startswith(f"http://{address}:"), brain
    assert plat.instances()[name]["server"] == server


def _registered(master, node):
    try:
        return master.lookupNode(node)
    except Exception:
        return None


def test_spaces_are_placed_by_load_on_the_master_and_two_server_vms(make_platform):
    plat = make_platform(1)
    plat.master.start()
    plat.provision_logic("two_sides", **LOGIC)
    start_server(plat, "vm1", 2)
    start_server(plat, "vm2", 1)
    expected = {"r1": "master", "r2": "vm1", "r3": "vm2", "r4": "vm1"}   # CONTRACTS §8's load and tie rules
    for index, name in enumerate(expected, start=1):
        start_robot(plat, name, index)
        check_placed_on(plat, name, expected[name])
    status, answer = plat.master.post("/platform_instance/provisioning",
                                      {"pi_name": "vm1", "pi_service_logic": "two_sides"})
    assert (status, answer["reason"]) == (409, "'vm1' is the name of a connected server VM; give the robot another "
                                               "name")
    rows = servers(plat)
    assert list(rows) == ["master", "vm1", "vm2"]                              # the master first
    assert rows["master"] == {"pi_name": "master", "pi_type": "S", "connected": True, "address": "127.0.0.1",
                              "max_service_spaces": 1, "service_spaces": ["r1"]}
    assert sorted(rows["vm1"]["service_spaces"]) == ["r2", "r4"]
    assert (rows["vm2"]["address"], rows["vm2"]["max_service_spaces"]) == ("127.0.0.11", 1)

    # no room anywhere: connected, not paired, a readable reason; room appears when a robot leaves
    start_robot(plat, "r5", 5, wait=False)
    plat.wait_state("r5", True, False)
    wait_until(lambda: "waiting for room" in (space(plat, "r5").get("reason") or ""), timeout=30,
               message="r5 to wait for room")
    assert "master 1/1, vm1 2/2, vm2 1/1" in space(plat, "r5")["reason"]
    plat.robots["r3"].stop()
    plat.wait_state("r5", True, True, timeout=START)
    check_placed_on(plat, "r5", "vm2")


def test_a_master_at_its_cap_queues_new_spaces_instead_of_growing(make_platform):
    """Issue 12 row 9: max_service_spaces bounds what one master builds; the rest wait and nothing is started
    for them; a pure coordinator (0) builds none and places on a server VM as soon as one joins."""
    plat = make_platform(0)
    plat.master.start()
    plat.provision_logic("two_sides", **LOGIC)
    start_robot(plat, "r1", 1, wait=False)
    start_robot(plat, "r2", 2, wait=False)
    plat.wait_state("r1", True, False)
    plat.wait_state("r2", True, False)
    wait_until(lambda: "number 2 in line" in (space(plat, "r2").get("reason") or ""), timeout=30,
               message="r2 second in line")
    assert space(plat, "r1")["reason"].startswith("waiting for room")
    home = plat.master.home
    assert not [p for p in plat.leftovers() if "rosmaster" in p[1]], "a ROS master started for a waiting space"
    assert not [p for p in plat.leftovers() if home in p[1] and p[0] != plat.master.process.pid]
    start_server(plat, "vm1", 1)
    plat.wait_state("r1", True, True, timeout=START)                       # first in line, first placed
    check_placed_on(plat, "r1", "vm1")
    assert "waiting for room" in space(plat, "r2")["reason"]
    plat.robots["r1"].stop()
    plat.wait_state("r2", True, True, timeout=START)
    check_placed_on(plat, "r2", "vm1")


def leftovers_of(plat, name):
    home = os.path.join(plat.root, name)
    return [p for p in plat.leftovers() if home in p[1] or _environ_mentions(p[0], home)]


def _environ_mentions(pid, text):
    try:
        with open(f"/proc/{pid}/environ", "rb") as f:
            return text.encode() in f.read()
    except OSError:
        return False


def test_a_killed_server_vms_spaces_are_rebuilt_elsewhere_and_it_comes_back_for_new_ones(make_platform):
    plat = make_platform(0)                                             # a pure coordinator
    plat.master.start()
    plat.provision_logic("two_sides", **LOGIC)
    vm1 = start_server(plat, "vm1", 5)
    start_server(plat, "vm2", 5)
    for index, (name, where) in enumerate([("r1", "vm1"), ("r2", "vm2"), ("r3", "vm1")], start=1):
        start_robot(plat, name, index)
        check_placed_on(plat, name, where)
    marks = plat.log_marks()
    vm1.kill()                                                          # SIGKILL
    killed = time.monotonic()
    # re-paired within 3 heartbeats (the master notices) plus their start time, without any action of theirs
    for name in ("r1", "r3"):
        wait_until(lambda name=name: (plat.instances()[name]["paired"] and
                                      plat.instances()[name].get("server") == "vm2"),
                   timeout=3 * HEARTBEAT + START, message=f"{name} paired again on vm2")
        check_placed_on(plat, name, "vm2")
    repaired = time.monotonic() - killed
    assert plat.session_log(["r1", "r3"], marks).ended == [], "a robot's session was ended by the move"
    assert leftovers_of(plat, "vm1") == [], "processes of the killed server's spaces are still running"
    assert sorted(servers(plat)) == ["master", "vm2"]
    assert all_servers(plat)["vm1"] == {"pi_name": "vm1", "pi_type": "S", "connected": False,
                                        "address": "127.0.0.10", "max_service_spaces": 5, "service_spaces": []}
    assert sorted(servers(plat)["vm2"]["service_spaces"]) == ["r1", "r2", "r3"]
    # it comes back: it takes new spaces only, nothing moves back
    vm1.start()
    wait_until(lambda: "vm1" in servers(plat), timeout=30, message="vm1 to join again")
    start_robot(plat, "r4", 4)
    check_placed_on(plat, "r4", "vm1")
    assert servers(plat)["vm1"]["service_spaces"] == ["r4"]
    print(f"re-paired the killed server's 2 robots in {repaired:.1f} s")


def test_sigterm_on_a_server_vm_hands_its_spaces_over(make_platform):
    plat = make_platform(1)
    plat.master.start()
    plat.provision_logic("two_sides", **LOGIC)
    start_robot(plat, "r1", 1)
    check_placed_on(plat, "r1", "master")
    vm1 = start_server(plat, "vm1", 2)
    start_robot(plat, "r2", 2)
    check_placed_on(plat, "r2", "vm1")
    plat.robots["r1"].stop()                                            # room on the master for the handover
    wait_until(lambda: servers(plat)["master"]["service_spaces"] == [], timeout=30, message="r1's space gone")
    assert vm1.stop() == 0                                              # SIGTERM
    plat.wait_state("r2", True, True, timeout=START)
    wait_until(lambda: plat.instances()["r2"].get("server") == "master", timeout=30,
               message="r2 moved to the master")
    check_placed_on(plat, "r2", "master")
    assert leftovers_of(plat, "vm1") == []


def test_a_server_vm_cut_off_loses_its_spaces_and_stops_what_it_ran_for_them(make_platform):
    """Heartbeats, not a closed connection: the server's agent is frozen (SIGSTOP), so its ROS processes live on
    and nothing closes its connection. The master declares it lost after 3 heartbeats and moves its space; the
    server, once it runs again, finds the master gone and stops every process of that space."""
    plat = make_platform(2)
    plat.master.start()
    plat.provision_logic("two_sides", **LOGIC)
    vm1 = start_server(plat, "vm1", 2)
    start_robot(plat, "r1", 1)
    check_placed_on(plat, "r1", "master")
    start_robot(plat, "r2", 2)
    check_placed_on(plat, "r2", "vm1")
    agent = vm1.process.pid
    os.kill(agent, signal.SIGSTOP)
    try:
        wait_until(lambda: plat.instances()["r2"].get("server") == "master" and plat.instances()["r2"]["paired"],
                   timeout=3 * HEARTBEAT + START, message="r2 paired again on the master")
        assert "vm1" not in servers(plat)
        assert [p for p in leftovers_of(plat, "vm1") if p[0] != agent], "the frozen server's processes"
    finally:
        os.kill(agent, signal.SIGCONT)
    wait_until(lambda: not [p for p in leftovers_of(plat, "vm1") if p[0] != agent], timeout=30,
               message="the server to stop the processes of the space it lost")
    check_placed_on(plat, "r2", "master")
    wait_until(lambda: "vm1" in servers(plat), timeout=30, message="vm1 to join again")
    assert servers(plat)["vm1"]["service_spaces"] == []


def test_firos_on_a_server_vm_takes_the_servers_inbound_open_port(make_platform, tmp_path):
    """FIROS in a space placed on a server VM gets one of that server's inbound_open_ports and listens there at
    the server's address; service_space/read gives that port and address."""
    port = stable_free_ports(1, VM_ADDRESS["vm1"])[0]
    plat = make_platform(0)
    plat.master.start()
    config_dir = write_config(str(tmp_path / "firos-config"), broker_port=stable_free_ports(1)[0])
    plat.provision_logic("two_sides", sn_list=[
        {"sn_package": "firos", "sn_type": "core.py", "sn_name": "firos", "sn_params": f"--config {config_dir}",
         "sn_side": "S"}])
    vm = plat.robot("vm1", VM_ADDRESS["vm1"], role="server", max_service_spaces=1, inbound_open_ports=port,
                    ros_port_base=ros_port_base(VM_ADDRESS["vm1"]))
    vm.start()
    wait_until(lambda: "vm1" in servers(plat), timeout=30, message="vm1 to join")
    start_robot(plat, "r1", 1)
    described = space(plat, "r1")
    assert (described["server"], described["public_ip"], described["inbound_port"]) == ("vm1", "127.0.0.10", port)
    assert plat.instances()["r1"]["server"] == "vm1"
    wait_until(lambda: port_accepts(port, VM_ADDRESS["vm1"]), timeout=START,
               message="FIROS listening on the server's inbound port")
