"""The platform across hosts over its own VPN (issue 9): real OpenVPN run by the agents, real network namespaces.

One set of hosts serves the module (``tests/support/vpn_hosts.py``): a master, two robots and an office machine
(the administrator's curl, and the fourth host where the stand-in broker runs for FIROS) on the LAN ``203.0.113.0/24``, the VPN ``198.51.100.0/24`` made by ``rcmp_n vpn init``. Every agent has the
default configuration (``tun0``, ``eth0``, ports 80 and 9999, no address keys; short heartbeats only) and runs
OpenVPN itself. The tests run in file order and each leaves the platform as it found it (both robots paired),
except the last, which revokes robot2.
"""

import json
import os
import signal

import pytest

from tests.support.firos import write_config
from tests.support.processes import ros_env
from tests.support.polling import wait_until
from tests.support.vpn_hosts import HEARTBEAT, HELLO, MISSES, PYTHON, REPO, vpn_platform

pytestmark = pytest.mark.netns

MASTER_VPN = "198.51.100.1"
ROBOT_LOGIC = {"slg_name": "vpn_talk", "sn_list": [
    {"sn_package": "robotics_test", "sn_type": "talker.py", "sn_name": "r_talker", "sn_params": "", "sn_side": "R"},
], "sl_list": []}
BROKER_PORT = 1026
FIROS_PORT = 10100          # the master's first inbound open port (its default inbound_open_ports)


def firos_logic(config_dir):
    """robot2's service logic: FIROS on the master (S) and, on the robot (R), a talker publishing the seed's s1."""
    return {"slg_name": "vpn_firos", "sn_list": [
        {"sn_package": "robotics_test", "sn_type": "talker.py", "sn_name": "r_talker",
         "sn_params": "_topic:=/end_end_test/s1", "sn_side": "R"},
        {"sn_package": "firos", "sn_type": "core.py", "sn_name": "firos", "sn_params": f"--config {config_dir}",
         "sn_side": "S"},
    ], "sl_list": []}
# the space's ROS master, asked from the master host: the URI of a node (its host is the address it registered from)
LOOKUP = r"""
import sys, xmlrpc.client
code, message, uri = xmlrpc.client.ServerProxy(sys.argv[1]).lookupNode("/probe", sys.argv[2])
print(uri if code == 1 else "")
"""


@pytest.fixture(scope="module")
def platform(tmp_path_factory):
    with vpn_platform(tmp_path_factory, "vpn-hosts") as p:
        p.add_robot("robot1")
        p.add_robot("robot2")
        # the stand-in broker on the office host (the fourth host), FIROS's configuration pointing at it
        p.broker = p.office.start([PYTHON, "-m", "tests.ngsi_broker", "--host", p.office.address, "--port",
                                   str(BROKER_PORT)], cwd=REPO, name="ngsi-broker")
        config_dir = write_firos_config(os.path.join(p.root, "firos-config"), p.office.address)
        p.master.start()
        p.wait_rdapi()
        p.rdapi_ok("POST", "/service_logic/provisioning", ROBOT_LOGIC)
        p.rdapi_ok("POST", "/service_logic/provisioning", firos_logic(config_dir))
        for name, logic in (("robot1", "vpn_talk"), ("robot2", "vpn_firos")):
            p.rdapi_ok("POST", "/platform_instance/provisioning", {"pi_name": name, "pi_service_logic": logic})
            p.robots[name].start()
        yield p


def write_firos_config(config_dir, broker_address):
    """FIROS's configuration: the broker on another host; notifications to the address FIROS uses towards it."""
    write_config(config_dir, BROKER_PORT)
    path = os.path.join(config_dir, "config.json")
    with open(path) as f:
        config = json.load(f)
    block = config[config["environment"]]
    block["contextbroker"]["address"] = broker_address
    del block["endpoint"]            # interface "public": the master's eth0 address, as the broker sees it
    with open(path, "w") as f:
        json.dump(config, f, indent=2)
    return config_dir


def broker(p, method, path, body=None):
    """(status, JSON or text) of one call to the stand-in broker, from the office host."""
    argv = ["curl", "-s", "-S", "--max-time", "5", "-o", "-", "-w", "\n%{http_code}", "-X", method]
    if body is not None:
        argv += ["-H", "Content-Type: application/json", "--data-binary", json.dumps(body)]
    argv.append(f"http://{p.office.address}:{BROKER_PORT}{path}")
    result = p.office.run(argv, check=False, stderr=None)
    text, _, status = result.stdout.rpartition("\n")
    try:
        return int(status), json.loads(text) if text else None
    except ValueError:
        return (int(status) if status.isdigit() else None), text


def listening(host, port):
    """The local addresses listening on TCP ``port`` in ``host``."""
    out = host.run(["ss", "-H", "-l", "-n", "-t", f"sport = :{port}"]).stdout
    return sorted(line.split()[3].rsplit(":", 1)[0] for line in out.splitlines() if line.strip())


def space_master_uri(p, name):
    status, space = p.rdapi("GET", f"/service_space/read?ss_name={name}")
    assert status == 200, (status, space)
    return space["reason"]["ros_master_uri"]


def test_robots_pair_over_the_vpn_with_default_interfaces(platform):
    p = platform
    for name in ("robot1", "robot2"):
        p.wait_state(name, True, True, timeout=60)
    assert p.master.vpn_address() == MASTER_VPN
    addresses = {name: robot.vpn_address() for name, robot in p.robots.items()}
    assert addresses == {"robot1": "198.51.100.2", "robot2": "198.51.100.3"}
    # the agent port on the VPN address only, the RDAPI on eth0 only
    assert listening(p.master_host, 9999) == [MASTER_VPN]
    assert listening(p.master_host, 80) == [p.master_address]
    # the R-side node registered with the space's ROS master (on the master host) from the robot's VPN address
    for name, address in addresses.items():
        uri = space_master_uri(p, name)
        assert uri.startswith(f"http://{p.master_address}:") or uri.startswith(f"http://{MASTER_VPN}:"), uri
        def node_uri():
            return p.master_host.run([PYTHON, "-c", LOOKUP, uri, "/r_talker"]).stdout.strip()
        wait_until(lambda: node_uri().startswith("http://"), timeout=30, interval=0.5,
                   message=f"{name}'s r_talker to register with its space's ROS master")
        assert node_uri().startswith(f"http://{address}:"), (name, node_uri())
    # vpn list on the master says who is connected
    assert p.vpn("list").stdout == "robot1 198.51.100.2 connected robot\nrobot2 198.51.100.3 connected robot\n"


def test_the_seeds_curl_commands_answer_on_the_masters_eth0(platform):
    p = platform
    status, page = p.rdapi("GET", "/")
    assert status == 200 and page == "<html><body>Welcome to the RCM platform node server!</body></html>"
    rows = {row["pi_name"]: row for row in p.rdapi_ok("GET", "/platform_instance/read")}
    assert {"robot1", "robot2"} <= set(rows)
    assert rows["robot1"]["paired"] and rows["robot2"]["paired"]


def test_firos_in_a_service_space_reaches_a_broker_on_another_host_and_its_notifications_come_back(platform):
    p = platform
    # robot2's talker (on the robot) -> its space's FIROS (on the master) -> the broker (on the office host)
    def s1():
        status, value = broker(p, "GET", "/v2/entities/end_end_test/attrs/s1?type=ROBOT")
        return value if status == 200 else None
    value = wait_until(s1, timeout=30, interval=0.5, message="s1 of end_end_test in the broker")
    assert value["type"] == "std_msgs.msg.String" and value["value"]["data"] == "hello from /r_talker"
    # FIROS subscribed with the master's eth0 address and its inbound port
    def subscription_urls():
        status, subs = broker(p, "GET", "/v2/subscriptions")
        return [s["notification"]["http"]["url"] for s in subs] if status == 200 else []
    urls = wait_until(subscription_urls, timeout=20, interval=0.5, message="FIROS's subscription in the broker")
    assert all(url.startswith(f"http://{p.master_address}:{FIROS_PORT}/") for url in urls), urls
    # the seed's command: an update in the broker, notified to FIROS through the inbound port, published in ROS
    status, _ = broker(p, "POST", "/v2/op/update", {"actionType": "append", "entities": [
        {"id": "end_end_test", "type": "ROBOT", "p1": {"type": "std_msgs.msg.String", "value": {"data": "4242"}},
         "COMMAND": {"type": "COMMAND", "value": ["p1"]}}]})
    assert status == 204
    env = ros_env({"ROS_IP": MASTER_VPN, "ROS_LOG_DIR": os.path.join(p.root, "echo-roslog")},
                  master_uri=space_master_uri(p, "robot2"))
    echo = p.master_host.run(["rostopic", "echo", "-n", "1", "/end_end_test/p1"], env=env, timeout=30, check=False)
    assert echo.returncode == 0 and "data: \"4242\"" in echo.stdout, echo.stdout


def test_a_hello_for_robot1_from_robot2s_address_is_refused_and_robot1_stays_paired(platform):
    p = platform
    robot2 = p.robots["robot2"]
    result = robot2.host.run([PYTHON, "-c", HELLO, "robot1", "198.51.100.2", MASTER_VPN, "9999"], check=False)
    assert result.returncode == 0, result.stdout
    answer = json.loads(result.stdout)
    assert answer["kind"] == "err" and answer["body"]["code"] == "wrong_address", answer
    assert "198.51.100.2" in answer["body"]["reason"] and "198.51.100.3" in answer["body"]["reason"]
    assert "refused hello for robot1 from 198.51.100.3" in p.master.log_text()
    assert p.state("robot1") == (True, True)
    assert "robot1 disconnected" not in p.robots["robot1"].log_text()


def test_a_cut_link_tears_the_robot_down_within_three_heartbeats_and_it_pairs_again(platform):
    p = platform
    robot1 = p.robots["robot1"]
    space_port = int(space_master_uri(p, "robot1").rstrip("/").rsplit(":", 1)[1])
    assert listening(p.master_host, space_port)
    robot1.host.link_down()
    try:
        wait_until(lambda: p.state("robot1") == (False, False), timeout=MISSES * HEARTBEAT + 1.0, interval=0.1,
                   message=f"robot1 torn down within {MISSES} heartbeats")
        # nothing left: robot1's service space (its ROS master) gone from the master, its R-side node from the robot
        wait_until(lambda: not listening(p.master_host, space_port), timeout=10,
                   message="robot1's service space ROS master to stop")
        wait_until(lambda: "talker.py" not in " ".join(_commands(robot1.host)), timeout=10,
                   message="robot1's R-side node to stop")
    finally:
        robot1.host.link_up()
    p.wait_state("robot1", True, True, timeout=60)
    assert p.state("robot2") == (True, True)


def _commands(host):
    return [_cmdline(pid) for pid in host.pids()]


def _openvpn_pids(host):
    return [pid for pid in host.pids() if _cmdline(pid).startswith("/usr/sbin/openvpn ")]


def _cmdline(pid):
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().replace(b"\0", b" ").decode("utf-8", "replace")
    except OSError:
        return ""


def test_the_agent_restarts_its_openvpn_when_it_dies(platform):
    p = platform
    robot1 = p.robots["robot1"]
    [pid] = _openvpn_pids(robot1.host)
    os.kill(pid, signal.SIGKILL)
    wait_until(lambda: "managed VPN: OpenVPN ended (killed by signal 9" in robot1.log_text(), timeout=10,
               message="the robot's agent to log that its OpenVPN died")
    wait_until(lambda: _openvpn_pids(robot1.host) not in ([], [pid]), timeout=20,
               message="the robot's agent to start OpenVPN again")
    p.wait_state("robot1", True, True, timeout=60)
    assert robot1.vpn_address() == "198.51.100.2"


def test_when_the_masters_openvpn_dies_it_is_restarted_and_both_robots_pair_again(platform):
    p = platform
    [pid] = _openvpn_pids(p.master_host)
    mark = len(p.master.log_text())
    os.kill(pid, signal.SIGKILL)
    wait_until(lambda: "managed VPN: OpenVPN ended (killed by signal 9" in p.master.log_text()[mark:], timeout=10,
               message="the master's agent to log that its OpenVPN died")
    # the tunnel is gone for a while: both sessions end (heartbeats), then the robots' OpenVPN notice the new
    # server (keepalive) and both robots pair again, on the same listener
    for name in ("robot1", "robot2"):
        wait_until(lambda: f"lost robot {name}" in p.master.log_text()[mark:], timeout=10,
                   message=f"{name}'s session to end")
    for name in ("robot1", "robot2"):
        wait_until(lambda: f"robot {name} paired" in p.master.log_text()[mark:], timeout=60, interval=0.2,
                   message=f"{name} to pair again")
        p.wait_state(name, True, True, timeout=10)
    assert listening(p.master_host, 9999) == [MASTER_VPN]
    assert p.master.process.poll() is None


def test_a_restarted_master_pairs_both_robots_again(platform):
    p = platform
    assert p.master.stop() == 0
    # the agent stopped its OpenVPN last: nothing of the master is left in its host
    assert not [c for c in _commands(p.master_host) if "openvpn" in c or "rcm_platform" in c]
    p.master.start()
    p.wait_rdapi()
    for name in ("robot1", "robot2"):
        p.wait_state(name, True, True, timeout=90)
    assert p.master.log_text().count("managed VPN: up, tun0 has address 198.51.100.1") >= 2


def test_a_revoked_robot_is_cut_off_and_stays_off(platform):
    p = platform
    result = p.vpn("revoke", "robot2")
    assert result.returncode == 0 and "robot2: revoked; its connection was cut" in result.stdout, result.stdout
    wait_until(lambda: p.state("robot2") == (True, False) or p.state("robot2") == (False, False),
               timeout=MISSES * HEARTBEAT + 1.0, interval=0.1, message="robot2 unpaired within 3 heartbeats")
    p.wait_state("robot2", False, False, timeout=10)
    # its OpenVPN tries again and the master's refuses its certificate
    openvpn_log = os.path.join(p.master.home, "log", "openvpn.log")
    wait_until(lambda: "certificate revoked: OU=robot, CN=robot2" in _read(openvpn_log), timeout=60, interval=0.5,
               message="robot2's OpenVPN to be refused for its revoked certificate")
    assert p.state("robot2") == (False, False)
    assert p.robots["robot2"].vpn_address() is None or "robot2 connected" not in p.master.log_text()[-2000:]
    assert p.vpn("list").stdout == "robot1 198.51.100.2 connected robot\nrobot2 198.51.100.3 revoked robot\n"
    assert p.state("robot1") == (True, True)


def _read(path):
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            return f.read()
    except OSError:
        return ""
