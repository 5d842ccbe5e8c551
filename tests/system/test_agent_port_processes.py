"""The agent port of a real master process (``python3 -m rcm_platform``), probed as issue 12's attacker did.

Row 7: 200 connections, each from its own address, each sending most of a 1 MiB frame before hello: every one is
dropped and the master's resident memory stays where it was. Row 10: seven hellos with a 1,000,000-character
name: the log grows by a few lines, not megabytes. Row 13: deeply nested JSON: one warning line, no traceback, no
CRITICAL. Row 6 with real ROS: ``r_provisioning`` racing a hello, at varied offsets; whenever it answers 200
"removed", nothing of the robot is left running (no session, no ROS master) and a second call gets 404.
"""

import json
import random
import socket
import struct
import threading

import pytest

from tests.support.lifecycle import Platform
from tests.support.polling import wait_until


def frame(message):
    data = json.dumps(message).encode()
    return struct.pack("!I", len(data)) + data


def hello_frame(name):
    return frame({"v": 1, "id": 1, "kind": "req", "op": "hello",
                  "body": {"name": name, "address": "127.0.0.2", "robot": True, "version": 1}})


def rss_kib(pid):
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    raise AssertionError(f"no VmRSS for {pid}")


def closed_by_master(sock, timeout=10.0):
    """True once the master closed ``sock`` (EOF or reset)."""
    sock.settimeout(timeout)
    try:
        while sock.recv(65536):
            pass
        return True
    except (ConnectionResetError, BrokenPipeError):
        return True
    except socket.timeout:
        return False


@pytest.fixture
def master(procs, tmp_path):
    plat = Platform(procs, tmp_path / "platform", inbound_ports=0)
    plat.master.start()
    try:
        yield plat
    finally:
        plat.stop_all_and_check_nothing_left()


def test_half_sent_big_frames_nested_json_and_huge_names_cost_nothing(master):
    pid = master.master.process.pid
    port = master.master.ic_port
    log_before = len(master.master.log_text())
    before = rss_kib(pid)
    socks = []
    try:
        for n in range(200):   # row 7: most of a 1 MiB frame each, before hello
            sock = socket.create_connection(("127.0.0.1", port), timeout=5,
                                            source_address=(f"127.0.{2 + n // 250}.{n % 250 + 1}", 0))
            socks.append(sock)
            try:
                sock.sendall(struct.pack("!I", 1024 * 1024 - 16) + b'{"v":1,"id":1,"op":"hello","body":"'
                             + b"x" * (900 * 1024))
            except (ConnectionResetError, BrokenPipeError):
                pass                                 # the master hung up before we finished: fine
        assert all(closed_by_master(sock) for sock in socks)
        for _ in range(7):     # row 10: a 1,000,000-character name
            sock = socket.create_connection(("127.0.0.1", port), timeout=5, source_address=("127.0.5.1", 0))
            socks.append(sock)
            try:
                sock.sendall(hello_frame("n" * 1000000))
            except (ConnectionResetError, BrokenPipeError):
                pass
            assert closed_by_master(sock)
        # row 13: deeply nested JSON, small enough to pass the size limit
        sock = socket.create_connection(("127.0.0.1", port), timeout=5, source_address=("127.0.5.2", 0))
        socks.append(sock)
        sock.sendall(struct.pack("!I", 3900) + b"[" * 1950 + b"]" * 1950)
        assert closed_by_master(sock)
    finally:
        for sock in socks:
            sock.close()
    after = rss_kib(pid)
    assert after - before < 20 * 1024, f"master RSS {before} KiB before, {after} KiB after"
    log = master.master.log_text()[log_before:]
    assert len(log) < 20000, f"the log grew by {len(log)} characters"
    assert "n" * 100 not in log
    assert "CRITICAL" not in log and "Traceback" not in log and "RecursionError" not in log, log[-3000:]
    assert "over the 4096-byte limit before admission" in log
    # the master still serves: the RDAPI answers and a well-formed stranger gets a sentence
    assert master.master.get("/")[0] == 200
    sock = socket.create_connection(("127.0.0.1", port), timeout=5, source_address=("127.0.5.3", 0))
    try:
        sock.sendall(hello_frame("nobody"))
        length = struct.unpack("!I", sock.recv(4))[0]
        data = b""
        while len(data) < length:
            data += sock.recv(length - len(data))
        answer = json.loads(data)
        assert answer["kind"] == "err" and answer["body"]["code"] == "not_provisioned", answer
    finally:
        sock.close()


def test_r_provisioning_racing_a_hello_never_leaves_a_session_running(master):
    """Row 6: once in 4 tries the probe got 200 "removed" with the session and its ROS master still running."""
    plat = master
    master_pid = plat.master.process.pid
    port = plat.master.ic_port
    rng = random.Random(6)
    outcomes = []
    for attempt in range(10):
        plat.provision_robot("racer", "empty")
        sock = socket.create_connection(("127.0.0.1", port), timeout=5, source_address=("127.0.0.7", 0))
        try:
            # the removal from 30 ms before the hello (it holds the lock) to 300 ms after (the space is starting)
            delay = rng.uniform(-0.03, 0.3)
            answers = []
            remover = threading.Timer(max(0.0, delay), lambda: answers.append(plat.remove_robot("racer")))
            hello = threading.Timer(max(0.0, -delay), sock.sendall, (hello_frame("racer"),))
            remover.start()
            hello.start()
            remover.join()
            hello.join()
            status, body = answers[0]
            assert status == 200 and "removed" in body["reason"], (attempt, status, body)
            outcomes.append("hello first" if "after disconnecting" in body["reason"] else "removal first")
            # nothing of racer is left: no session (the connection is closed), no space process
            assert closed_by_master(sock), attempt
            wait_until(lambda: not [p for p in plat.leftovers() if p[0] != master_pid], timeout=20,
                       message=f"racer's processes to go (attempt {attempt}, r_provisioning after {delay:.2f} s)")
            assert "racer" not in plat.instances()
            assert plat.space("racer")[0] == 404
            assert plat.remove_robot("racer")[0] == 404
        finally:
            sock.close()
    assert plat.master.process.poll() is None
    print("race outcomes:", outcomes)
