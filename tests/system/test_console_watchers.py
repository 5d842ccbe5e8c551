"""The console's live topics on a real platform (a master and a robot agent, paired, with the space's ROS master),
tried as issue 18's attacker did.

Row 8: a local user opened 16 connections to the watchers' loopback port and sent bad keys: no real watcher could
connect, and the log got one warning per attempt. Now the watchers' socket is a Unix socket that another user
cannot open at all (tried as ``nobody``), and a process of the agent's own user that is not a watcher is closed
before anything is read; the real watcher links meanwhile and the page gets its topics; the warnings are budgeted.
Row 5: a watched topic carrying NaN made the stream send a bare ``NaN`` that the page's ``JSON.parse`` refused
(and reconnected into the same error). Now every event is strict JSON and such numbers are strings.
"""

import json
import os
import socket
import subprocess
import threading
import time

import pytest

from tests.support.lifecycle import Platform, processes_mentioning
from tests.support.polling import wait_until
from tests.support.processes import ros_env
from tests.system.test_shared_pools import EventStream

PROBE = ["/usr/bin/python3", "-m", "tests.support.ros_probe"]


@pytest.fixture
def platform(procs, tmp_path):
    plat = Platform(procs, tmp_path / "platform", inbound_ports=0)
    plat.master.start()
    try:
        plat.provision_robot("robot1", "empty")
        plat.robot("robot1", "127.0.0.2").start()
        plat.wait_state("robot1", True, True, timeout=30)
        yield plat
    finally:
        plat.stop_all_and_check_nothing_left()


def strict(text):
    def refuse(constant):
        raise ValueError(f"{constant} is not JSON: a browser's JSON.parse refuses it")
    return json.loads(text, parse_constant=refuse)


def watchers_socket(master_pid):
    """The path of the master's console socket, found as a local user with ``/proc`` would (its open sockets'
    inodes in ``/proc/net/unix``)."""
    inodes = set()
    for fd in os.listdir(f"/proc/{master_pid}/fd"):
        try:
            target = os.readlink(f"/proc/{master_pid}/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[len("socket:["):-1])
    with open("/proc/net/unix") as f:
        for line in f.readlines()[1:]:
            parts = line.split()
            if len(parts) >= 8 and parts[6] in inodes and "rcmp-console-" in parts[7]:
                return parts[7]
    raise AssertionError("the master has no console socket")


def connect_as(user, group, path):
    """Try to open the socket at ``path`` as another local user: "connected" or the error's name."""
    attempt = subprocess.run(
        ["/usr/bin/setpriv", f"--reuid={user}", f"--regid={group}", "--clear-groups", "/usr/bin/python3", "-c",
         "import socket, sys\ns = socket.socket(socket.AF_UNIX)\n"
         "try:\n    s.connect(sys.argv[1]); print('connected')\n"
         "except OSError as e:\n    print(type(e).__name__)\n", path],
        capture_output=True, text=True, timeout=30)
    return attempt.stdout.strip() or attempt.stderr.strip()


def knock(path, line=b'{"name": "robot1", "key": "guessed"}\n'):
    """Connect to the watchers' socket, send a bad hello, and say whether the master closed it at once."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(10)
        sock.connect(path)
        try:
            sock.sendall(line)
            return sock.recv(1) == b""
        except (BrokenPipeError, ConnectionResetError):
            return True


def test_row8_other_users_cannot_connect_and_impostors_cannot_keep_the_watcher_out(platform):
    master = platform.master
    path = watchers_socket(master.process.pid)
    # another local user: the socket cannot even be opened
    assert connect_as("nobody", "nogroup", path) == "PermissionError"
    # the agent's own user, but not a watcher: each connection is closed at once, before the watcher exists ...
    log_before = len(master.log_text())
    started = time.monotonic()
    assert all(knock(path) for _ in range(32))
    # ... and while it starts and links, the attacker goes on
    stop = threading.Event()
    closed = []

    def attack():
        while not stop.is_set():
            closed.append(knock(path))
    attacker = threading.Thread(target=attack)
    attacker.start()
    try:
        page = EventStream(platform, "127.0.0.1", "/console/api/topic?ss_name=robot1")
        assert page.status() == 200
        topics = wait_until(lambda: (lambda t: t if t["topics"] else None)(page.event("topics")), timeout=30,
                            message="the watcher's topics on the page")
        assert ["/rosout", "rosgraph_msgs/Log"] in topics["topics"]
        page.close()
    finally:
        stop.set()
        attacker.join()
    assert closed and all(closed)
    log = master.log_text()[log_before:]
    warnings = log.count("closed a connection to the watchers' socket")
    windows = 1 + int((time.monotonic() - started) // 10)
    assert 1 <= warnings <= 10 * windows, (warnings, len(closed))   # the budget's burst per window, however many
    assert warnings < len(closed)
    assert "Traceback" not in log


def test_row5_a_topic_carrying_nan_reaches_the_page_as_strict_json(platform, procs):
    status, space = platform.space("robot1")
    assert status == 200
    env = ros_env(master_uri=space["ros_master_uri"])
    env["ROS_IP"] = "127.0.0.1"
    pub = procs.start(PROBE + ["pub", "/pose", "geometry_msgs/Pose2D",
                               '{"x": NaN, "y": 1.5, "theta": Infinity}'], env=env, name="nan-publisher")
    wait_until(lambda: '"published": true' in procs.output(pub), timeout=20, message="the NaN pose to be published")
    page = EventStream(platform, "127.0.0.1", "/console/api/topic?ss_name=robot1&topic=/pose")
    try:
        assert page.status() == 200

        def sample():
            for _, data in page.events():
                event = strict(data)                     # every event parses strictly, not only the sample
                found = [event.get("sample")] + list(event.get("samples") or [])
                point = next((s for s in found if s and "x" in s), None)
                if point is not None:
                    return point
            return None
        point = wait_until(sample, timeout=30, message="a sample of /pose")
    finally:
        page.close()
    assert (point["x"], point["y"], point["theta"]) == ("NaN", 1.5, "Infinity")


def test_with_run_as_the_watcher_runs_as_that_user_and_only_it_may_open_the_socket(procs, tmp_path):
    """``run_as=nobody``: the watcher node runs as nobody, so the socket is nobody's (0600) in a folder others may
    pass through but not list (0711); another user (``daemon``) still cannot open it, and the page gets its topics."""
    if os.geteuid() != 0:
        pytest.skip("switching users needs a root agent")
    import pwd
    nobody = pwd.getpwnam("nobody")
    plat = Platform(procs, tmp_path / "platform", inbound_ports=0, run_as="nobody")
    plat.master.start()
    try:
        plat.provision_robot("robot1", "empty")
        plat.robot("robot1", "127.0.0.2").start()
        plat.wait_state("robot1", True, True, timeout=30)
        path = watchers_socket(plat.master.process.pid)
        info, folder = os.stat(path), os.stat(os.path.dirname(path))
        assert (info.st_uid, info.st_mode & 0o777) == (nobody.pw_uid, 0o600)
        assert (folder.st_uid, folder.st_mode & 0o777) == (0, 0o711)
        assert connect_as("daemon", "daemon", path) == "PermissionError"
        page = EventStream(plat, "127.0.0.1", "/console/api/topic?ss_name=robot1")
        try:
            assert page.status() == 200
            wait_until(lambda: (lambda t: t if t["topics"] else None)(page.event("topics")), timeout=30,
                       message="the topics of a watcher running as nobody")
        finally:
            page.close()
        watchers = [pid for pid, line in processes_mentioning(path) if "rcmp_console watch" in line]
        assert watchers and all(os.stat(f"/proc/{pid}").st_uid == nobody.pw_uid for pid in watchers)
    finally:
        plat.stop_all_and_check_nothing_left()
