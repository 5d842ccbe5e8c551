"""The fleet simulator of ``bench/fleet_sim.py`` against a real master, so that ``bench/bench_fleet.py`` cannot
silently measure nothing: a small fleet (20 simulated robots, 2 simulated server VMs) pairs through the real agent
protocol, the spaces of a server VM that crashes move to the other one and pair again with no robot session lost,
and at the end every process (master, simulator workers) is gone.
"""

import pytest

from bench.fleet_sim import Fleet
from tests.support.lifecycle import Platform
from tests.support.polling import wait_until

ROBOTS = 20
HEARTBEAT = 1.0
LOGIC = [{"sn_package": "robotics_test", "sn_type": "talker.py", "sn_name": "brain", "sn_params": "",
          "sn_side": "S"},
         {"sn_package": "robotics_test", "sn_type": "talker.py", "sn_name": "body", "sn_params": "",
          "sn_side": "R"}]


@pytest.fixture
def platform(procs, tmp_path):
    plat = Platform(procs, tmp_path / "platform", heartbeat=HEARTBEAT, inbound_ports=0, max_service_spaces=0)
    try:
        yield plat
    finally:
        plat.stop_all_and_check_nothing_left()


def robots_on(plat, names):
    """{name: server} of the robots of ``names`` that platform_instance/read shows connected and paired."""
    rows = plat.instances()
    return {n: rows[n].get("server") for n in names if rows[n]["connected"] and rows[n]["paired"]}


def test_a_simulated_fleet_pairs_and_a_crashed_servers_spaces_move(platform, procs):
    plat = platform
    plat.master.start()
    plat.provision_logic("fleet_logic", sn_list=LOGIC)
    names = [f"simbot{n}" for n in range(ROBOTS)]
    for name in names:
        plat.provision_robot(name, "fleet_logic")

    fleet = Fleet(procs, "127.0.0.1", plat.master.ic_port, heartbeat=HEARTBEAT)
    workers = list(fleet.workers)
    try:
        fleet.add_servers(["vm1", "vm2"], capacity=100)
        fleet.start(["vm1", "vm2"])
        wait_until(lambda: all(a["accepted"] for a in fleet.agents(["vm1", "vm2"]).values()), timeout=15,
                   message="both simulated servers to be accepted")
        fleet.add_robots(names)
        fleet.start(names)
        placed = wait_until(lambda: (lambda r: r if len(r) == ROBOTS else None)(robots_on(plat, names)),
                            timeout=30, message="every simulated robot to pair")
        assert sorted(set(placed.values())) == ["vm1", "vm2"], placed     # the master hosts none (0 spaces)
        agents = fleet.agents()
        assert all(agents[n]["items_at"] and agents[n]["ros_master_uri"] for n in names)
        on_vm1 = sorted(agents["vm1"]["spaces"])
        assert on_vm1 == sorted(n for n, server in placed.items() if server == "vm1")
        assert len(on_vm1) == ROBOTS // 2    # least loaded first: an even spread

        fleet.crash(["vm1"])
        wait_until(lambda: robots_on(plat, names) == {n: "vm2" for n in names}, timeout=30,
                   message="vm1's robots to pair again on vm2")
        agents = fleet.agents()
        assert sorted(agents["vm2"]["spaces"]) == sorted(names)
        for name in on_vm1:       # their R side was restarted against vm2's ROS master
            assert agents[name]["ros_master_uri"].startswith(f"http://{agents['vm2']['address']}:")
        # the robots' own heartbeats are answered (every HEARTBEAT seconds)
        stats = wait_until(lambda: (lambda s: s if s["samples"]["heartbeat"] else None)(fleet.stats()),
                           timeout=3 * HEARTBEAT, message="a robot's heartbeat to be answered")
        assert stats["counters"].get("sessions_lost", 0) == 0, stats["losses"]
        assert len(stats["samples"]["hello"]) == ROBOTS + 2
        rows = {r["pi_name"]: r for r in plat.master.get("/platform_instance/read?pi_type=S")[1]["reason"]}
        assert rows["vm1"]["connected"] is False and sorted(rows["vm2"]["service_spaces"]) == sorted(names)
    finally:
        fleet.close()
    assert all(proc.poll() is not None for proc in workers)
    assert plat.master.stop(timeout=30) == 0
