"""`./run demo-hosts` as a person uses it: both robots pair over the VPN, the printed curl commands answer from
the office machine, Ctrl-C removes every namespace and process."""

import json
import os
import re
import shlex
import signal
import subprocess

import pytest

from tests.support.hosts import netns_names
from tests.support.lifecycle import processes_mentioning
from tests.support.paths import REPO
from tests.support.polling import wait_until
from tests.support.processes import group_alive, ros_env

ROOT = REPO

pytestmark = pytest.mark.netns


def test_demo_hosts_pairs_two_robots_over_the_vpn_and_ctrl_c_removes_everything(procs, tmp_path):
    if os.geteuid() != 0:
        pytest.skip("the demo's machines are network namespaces (root only)")
    workdir = str(tmp_path / "demo-hosts")
    demo = procs.start(["/usr/bin/python3", "-m", "demo.run_demo_hosts", "--workdir", workdir],
                       env=ros_env(), cwd=ROOT, name="demo-hosts")
    text = wait_until(lambda: (lambda out: out if "Press Ctrl-C" in out else None)(procs.output(demo)),
                      timeout=180, interval=0.5, message="the demo to say it is running")
    assert "robot1: VPN address 198.51.100.2, paired" in text and "robot2: VPN address 198.51.100.3, paired" in text
    own = [n for n in netns_names() if n.startswith(f"rcmt-{demo.pid}-")]
    assert len(own) == 5, own   # the LAN, master, office, robot1, robot2

    # the printed command, as printed (split as a shell would, run without one)
    line = next(l.strip() for l in text.splitlines() if l.strip().endswith("/platform_instance/read"))
    argv = shlex.split(line)
    assert argv[:3] == ["ip", "netns", "exec"] and argv[4:] == ["curl", "http://203.0.113.10/platform_instance/read"]
    rows = json.loads(subprocess.run(argv, capture_output=True, text=True, timeout=20).stdout)["reason"]
    assert {(r["pi_name"], r["paired"]) for r in rows} == {("robot1", True), ("robot2", True)}
    vpn_line = next(l.strip() for l in text.splitlines() if l.strip().endswith("vpn list"))
    vpn_argv = shlex.split(vpn_line.split("&&", 1)[1])
    listing = subprocess.run(vpn_argv, capture_output=True, text=True, timeout=30, cwd=ROOT).stdout
    assert listing == "robot1 198.51.100.2 connected robot\nrobot2 198.51.100.3 connected robot\n"

    # the console, from this machine's browser: a loopback port forwarded into the master's machine; each robot's
    # printed link opens on its pose
    console = re.search(r"Console: (http://127\.0\.0\.1:(\d+))/console/\n", text)
    assert console, text
    assert f"robot1: {console.group(1)}/console/#/robot/robot1?topic=/pose" in text
    served = subprocess.run(["curl", "-s", "-S", console.group(1) + "/platform_instance/read"], capture_output=True,
                            text=True, timeout=20).stdout
    assert {(r["pi_name"], r["paired"]) for r in json.loads(served)["reason"]} == {("robot1", True), ("robot2", True)}

    os.killpg(demo.pid, signal.SIGINT)  # what Ctrl-C in the terminal does
    assert demo.wait(timeout=90) == 0
    assert "demo-hosts: stopped" in procs.output(demo)
    assert not [n for n in netns_names() if n.startswith(f"rcmt-{demo.pid}-")]
    wait_until(lambda: not processes_mentioning(workdir), timeout=10,
               message="every demo process (agents, OpenVPN, ROS) to be gone")
    assert not group_alive(demo.pid)
    assert subprocess.run(["curl", "-s", console.group(1)], capture_output=True, timeout=20).returncode != 0
    assert re.search(r"rcmp_n stopped", open(os.path.join(workdir, "master", "log", "rcmp.log")).read())
