"""A herd of robots against one master on this machine (issue 10 item 1): no thrash.

60 real robot agents (``python3 -m rcm_platform``, each on its own loopback address) are started at once against
a real master; every one must pair and no session may be ended and made again on the way (counted from the
agents' logs: the master's "connected from" and "ending robot ... session" lines, the robots' "lost the
master"). Then the master is restarted under the paired fleet (more than the issue's 40): all pair again, each
with exactly one new session. The service logic is the lightest honest one, ``empty``: each space is still a real
``rosmaster`` plus ``rosout`` on the master, and the robots are real agents, but no node of ours runs, so the
test measures the agents' admission, not ROS node start-up (bench/bench_lifecycle.py --herd does that).
"""

import pytest

from tests.support.lifecycle import Platform

HERD = 60


@pytest.fixture
def herd_platform(procs, tmp_path):
    # a 2 s heartbeat as in production: the point is that a saturated machine does not make agents look gone
    plat = Platform(procs, tmp_path / "platform", heartbeat=2.0, inbound_ports=0, log_max_bytes=100 * 1024 * 1024)
    try:
        yield plat
    finally:
        plat.stop_all_and_check_nothing_left()


def test_sixty_robots_at_once_then_a_master_restart_pair_without_thrash(herd_platform):
    plat = herd_platform
    plat.master.start()
    names = [f"herd{n}" for n in range(1, HERD + 1)]
    for name in names:
        plat.provision_robot(name, "empty")

    marks = plat.log_marks()
    started = plat.start_herd(names, log_max_bytes=10 * 1024 * 1024)
    plat.wait_all_paired(names, timeout=150, started=started)
    arrival = plat.session_log(names, marks)
    assert arrival.ended == [], f"sessions ended on the way: {arrival.ended[:5]}"
    assert arrival.reopened() == [], f"sessions made twice: {arrival.reopened()}"
    assert sorted(arrival.opened) == sorted(names)
    assert arrival.robot_lost == [], arrival.robot_lost[:5]
    assert len(arrival.robot_hello) == HERD

    # the master goes away under the paired fleet and comes back: the herd returns, once each
    plat.master.stop(timeout=90)      # it tears 60 spaces down first; the machine may be busy
    marks = plat.log_marks()
    plat.master.start()
    plat.wait_all_paired(names, timeout=150)
    comeback = plat.session_log(names, marks)
    assert comeback.ended == [], f"sessions ended after the restart: {comeback.ended[:5]}"
    assert comeback.reopened() == [], f"sessions made twice after the restart: {comeback.reopened()}"
    assert sorted(comeback.opened) == sorted(names)
    assert len(comeback.robot_hello) == HERD
    plat.stop_robots(names)
