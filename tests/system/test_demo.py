"""`./run demo` as a person uses it: it pairs, the robot moves, the seed's curl commands answer, Ctrl-C stops all."""

import json
import os
import re
import signal
import subprocess
import urllib.request

from tests.support.paths import REPO
from tests.support.polling import wait_until
from tests.support.ports import free_port
from tests.support.processes import group_alive, ros_env

ROOT = REPO


def _curl(url):
    return subprocess.run(["curl", "-s", "-S", url], capture_output=True, text=True, timeout=10).stdout


def _processes_mentioning(needle):
    """PIDs of processes whose command line or environment mentions ``needle``."""
    pids = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            for part in ("cmdline", "environ"):
                try:
                    with open(f"/proc/{entry}/{part}", "rb") as f:
                        if needle.encode() in f.read():
                            pids.append(int(entry))
                            break
                except OSError:
                    pass
    return pids


def _console_pose_moves(base):
    """Two samples of /pose from the console's topic stream (Server-Sent Events) at different places."""
    url = f"{base}/console/api/topic?ss_name=demo_robot&topic=/pose"
    points = []
    with urllib.request.urlopen(url, timeout=30) as stream:
        event = None
        for raw in stream:
            line = raw.decode().rstrip("\n")
            if line.startswith("event: "):
                event = line[len("event: "):]
            elif line.startswith("data: ") and event in ("sample", "samples"):
                data = json.loads(line[len("data: "):])
                for sample in data.get("samples", [data.get("sample")]):
                    if sample and "x" in sample:
                        points.append((sample["x"], sample["y"]))
                if len(set(points)) >= 2:
                    return True
    return False


def test_demo_pairs_shows_the_seed_commands_and_stops_cleanly_on_ctrl_c(procs, tmp_path):
    workdir = str(tmp_path / "demo")
    port = free_port()
    demo = procs.start(["/usr/bin/python3", "-m", "demo.run_demo", "--port", str(port), "--workdir", workdir],
                       env=ros_env(), cwd=ROOT, name="demo")
    text = wait_until(lambda: (lambda out: out if "Press Ctrl-C" in out else None)(procs.output(demo)),
                      timeout=120, message="the demo to say it is running")
    assert f"curl http://127.0.0.1:{port}/platform_instance/read" in text

    assert "Welcome to the RCM platform node server!" in _curl(f"http://127.0.0.1:{port}")
    rows = json.loads(_curl(f"http://127.0.0.1:{port}/platform_instance/read"))["reason"]
    assert rows == [{"pi_name": "demo_robot", "service_logic": "demo_patrol", "connected": True, "paired": True,
                     "server": "master"}]     # (ext) the server hosting its space (CONTRACTS section 8)
    space = json.loads(_curl(f"http://127.0.0.1:{port}/service_space/read?ss_name=demo_robot"))["reason"]
    where = {n["sn_name"]: n["i_name"] for n in space["r_nodes"]}
    assert where == {"sim_robot": "demo_robot", "patrol_brain": "master"}

    # the robot (robot side) circles because the brain (server side) drives it, across the two agents
    uri = re.search(r"ROS_MASTER_URI=(http://\S+)", text).group(1)

    def moved():
        out = subprocess.run(["/usr/bin/rostopic", "echo", "-n", "1", "/pose"], env=ros_env(master_uri=uri),
                             capture_output=True, text=True, timeout=20).stdout
        x = re.search(r"^x: (\S+)", out, re.M)
        return x and float(x.group(1)) > 0.05
    wait_until(moved, timeout=30, message="the demo robot to move")

    # the console shows it: its page, and the live pose the page plots (the browser itself: test_console_browser)
    console = re.search(r"Console: (http://\S+)", text).group(1)
    assert console == f"http://127.0.0.1:{port}/console/#/robot/demo_robot?topic=/pose"   # opens on the plot
    assert "<title>RCM platform console</title>" in _curl(console.split("#")[0])
    # the settings that let the docs' examples run as written (tests/system/test_doc_examples.py runs them)
    assert f"export MASTER=127.0.0.1:{port} RCMP_HOME={workdir}/master ROS_MASTER_URI={uri} PATH={ROOT}:/usr/bin:$PATH" \
        in text
    assert _console_pose_moves(f"http://127.0.0.1:{port}")

    assert _processes_mentioning(workdir)
    assert _processes_mentioning(uri)  # the service space's nodes run against its ROS master
    os.killpg(demo.pid, signal.SIGINT)  # what Ctrl-C in the terminal does
    assert demo.wait(timeout=60) == 0
    assert "demo: stopped" in procs.output(demo)
    wait_until(lambda: not _processes_mentioning(workdir) and not _processes_mentioning(uri), timeout=10,
               message="every demo process (agents, ROS master, nodes) to be gone")
    assert not group_alive(demo.pid)
