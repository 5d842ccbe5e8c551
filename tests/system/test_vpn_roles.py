"""Certificate roles on real OpenVPN in test hosts (issue 18 row 6), as the attacker of that row ran it.

A master that hosts no service space itself (``max_service_spaces = 0``: every robot's space must go to a server
VM), a robot, and two would-be server VMs, each a host of its own over the platform's own VPN
(``tests/support/vpn_hosts.py``; agents with their default configuration running OpenVPN themselves):
``retired`` is the agent of a server VM given the client file of a robot (``rcmp_n vpn client retired``, never
provisioned: a retired robot's file), ``vm1`` one with a server certificate (``--server``). The tests run in file
order: the attacker is refused and no space goes to it, the real server VM takes the robot's space and cannot say
hello as a robot, and removing the robot tells the operator to revoke its certificate.
"""

import json

import pytest

from tests.support.polling import wait_until
from tests.support.vpn_hosts import HELLO, PYTHON, vpn_platform

pytestmark = pytest.mark.netns

MASTER_VPN = "198.51.100.1"


@pytest.fixture(scope="module")
def platform(tmp_path_factory):
    with vpn_platform(tmp_path_factory, "vpn-roles", master_keys={"max_service_spaces": 0}) as p:
        p.add_robot("robot1")                                   # 198.51.100.2
        p.add_server("retired", certificate="robot")            # 198.51.100.3: a robot's file on a server VM
        p.add_server("vm1")                                     # 198.51.100.4: a server certificate
        p.master.start()
        p.wait_rdapi()
        p.rdapi_ok("POST", "/platform_instance/provisioning", {"pi_name": "robot1", "pi_service_logic": "empty"})
        yield p


def servers(p):
    """The connected server VMs (the master, listed first, left out)."""
    return [row["pi_name"] for row in p.rdapi_ok("GET", "/platform_instance/read?pi_type=S")[1:]]


def robot_row(p, name):
    return next((row for row in p.rdapi_ok("GET", "/platform_instance/read") if row["pi_name"] == name), None)


def test_a_robot_certificate_saying_hello_as_a_server_is_refused_and_no_space_is_placed_on_it(platform):
    p = platform
    attacker = p.robots["retired"].start()
    p.robots["robot1"].start()
    p.wait_state("robot1", True, False, timeout=60)             # connected; its space has nowhere to go
    # (the attacker logs its refusal once and keeps saying hello: docs/PROTOCOL.md's retry)
    # (the refusal's sentence is the master's, quoted in the attacker's log as any peer's text is)
    wait_until(lambda: "refused hello: " in attacker.log_text()
               and "'retired' holds a robot certificate" in attacker.log_text(),
               timeout=60, interval=0.3, message="the attacker to be refused")
    reason = attacker.log_text()
    assert "rcmp_n vpn client retired --server" in reason
    assert servers(p) == []
    status, space = p.rdapi("GET", "/service_space/read?ss_name=robot1")
    assert status == 200 and space["reason"]["paired"] is False, space
    assert "server" not in robot_row(p, "robot1")                # placed nowhere, certainly not on the attacker
    # the master logged it once, with the attacker's VPN address, although it keeps saying hello
    lines = [line for line in p.master.log_text().splitlines() if "refused hello as a server for retired" in line]
    assert len(lines) == 1 and "from 198.51.100.3:" in lines[0] and "robot certificate" in lines[0], lines
    assert p.vpn("list").stdout.splitlines() == ["retired 198.51.100.3 connected robot",
                                                 "robot1 198.51.100.2 connected robot",
                                                 "vm1 198.51.100.4 disconnected server"]


def test_a_server_certificate_works_as_a_server_and_cannot_say_hello_as_a_robot(platform):
    p = platform
    server = p.robots["vm1"].start()
    wait_until(lambda: servers(p) == ["vm1"], timeout=60, interval=0.3, message="vm1 to join as a server")
    p.wait_state("robot1", True, True, timeout=60)             # robot1's waiting space went to vm1
    assert robot_row(p, "robot1")["server"] == "vm1"
    assert "ROS master answers" in server.log_text() or "service space robot1" in server.log_text()
    # vm1's certificate says hello as a robot (its own name, from its own address): refused, its session stays
    result = server.host.run([PYTHON, "-c", HELLO, "vm1", "198.51.100.4", MASTER_VPN, "9999", "robot"],
                             check=False)
    assert result.returncode == 0, result.stdout
    answer = json.loads(result.stdout)
    assert answer["kind"] == "err" and answer["body"]["code"] == "wrong_role", answer
    assert "'vm1' holds a server certificate" in answer["body"]["reason"]
    assert servers(p) == ["vm1"] and p.state("robot1") == (True, True)
    assert "retired" not in servers(p)


def test_removing_a_robot_tells_the_operator_to_revoke_its_certificate(platform):
    p = platform
    answer = p.rdapi_ok("POST", "/platform_instance/r_provisioning", {"pi_name": "robot1"})
    assert answer == ("platform instance 'robot1' removed after disconnecting it; its VPN certificate still lets it "
                      "join the platform's VPN as a robot: run 'rcmp_n vpn revoke robot1' on the master to cut it "
                      "off")
    assert "run 'rcmp_n vpn revoke robot1' on the master" in p.master.log_text()
    # the removed robot can neither come back as a robot nor become a server with its certificate
    robot1 = p.robots["robot1"]
    wait_until(lambda: "is not provisioned on this platform" in robot1.log_text(), timeout=30, interval=0.3,
               message="the removed robot's hello to be refused")
    result = robot1.host.run([PYTHON, "-c", HELLO, "robot1", "198.51.100.2", MASTER_VPN, "9999", "server"],
                             check=False)
    assert json.loads(result.stdout)["body"]["code"] == "wrong_role", result.stdout
    assert servers(p) == ["vm1"]
