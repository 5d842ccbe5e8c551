"""The master's log keeps its evidence through a flood (issue 18, rows 1 and 2), tried as the attacker did against a
real master process (``python3 -m rcm_platform``): an evidence line is written to ``rcmp.log`` (a provisioning the
log records) before each flood, and after it the line is still in ``rcmp.log`` itself (nothing rotated), the log
grew by kilobytes, not megabytes, and no peer's string reached it whole.

Row 1: with RDAPI tokens in force, 200 requests without a token for a 16 KB unknown path (and unknown methods,
and, with a read token, unknown query keys) rotated ``rcmp.log`` and its 5 backups away in 0.2 s. Row 2: a robot
(here a raw agent-protocol client that said hello as a provisioned robot) answered ``start_items`` with a 1 MB
``reason`` and sent 7 ``item_exited`` reports whose item name was 1 MB: the master's log and backups were
overwritten.
"""

import http.client
import json
import os
import secrets
import socket
import struct
import time

import pytest

from tests.support.lifecycle import Platform
from tests.support.polling import wait_until
from tests.system.test_rdapi_security import add_token, call

MB = 1000 * 1000


@pytest.fixture
def platform(procs, tmp_path):
    # heartbeats of 5 s: the raw robot below answers requests only when it reads, and needs a window of 15 s
    plat = Platform(procs, tmp_path / "platform", heartbeat=5.0, inbound_ports=0)
    plat.master.start()
    try:
        yield plat
    finally:
        plat.stop_all_and_check_nothing_left()


def write_evidence(plat, token=None):
    """A provisioning the master logs ("RDAPI POST ...: OK: ... evidence_..."); the robot's name."""
    name = "evidence_" + secrets.token_hex(4)
    status, answer, _ = call(plat.master, "POST", "/platform_instance/provisioning",
                             {"pi_name": name, "pi_service_logic": "empty"}, token=token)
    assert status == 200, answer
    wait_until(lambda: name in plat.master.log_text(), message="the evidence line in rcmp.log")
    return name


def assert_evidence_kept(plat, evidence, size_before, grew_at_most):
    log_dir = os.path.dirname(plat.master.log_path)
    text = plat.master.log_text()
    assert evidence in text, "the evidence line is gone from rcmp.log"
    assert not os.path.exists(os.path.join(log_dir, "rcmp.log.1")), "rcmp.log was rotated"
    grew = len(text) - size_before
    assert grew < grew_at_most, f"rcmp.log grew by {grew} characters"
    longest = max(len(line) for line in text.splitlines())
    assert longest < 2000, f"a log line of {longest} characters"
    return text[size_before:]


def raw_get(plat, method, path, headers=None):
    conn = http.client.HTTPConnection(plat.master.host, plat.master.ext_port, timeout=10)
    try:
        conn.request(method, path, headers=headers or {})
        resp = conn.getresponse()
        return resp.status, resp.read()
    finally:
        conn.close()


def test_row1_a_flood_of_tokenless_requests_for_huge_unknown_paths_leaves_the_evidence(platform):
    admin = add_token(platform.master, "ops", "admin")
    reader = add_token(platform.master, "viewer", "read")
    wait_until(lambda: call(platform.master, "GET", "/platform_instance/read")[0] == 401,   # re-read each second
               message="tokens to be in force")
    evidence = write_evidence(platform, token=admin)
    size_before = len(platform.master.log_text())

    huge = "/" + "a" * 16000
    statuses = set()
    started = time.monotonic()
    for n in range(200):                                       # the probe's flood: no token, a 16 KB unknown path
        status, body = raw_get(platform, "GET", f"{huge}{n}")
        statuses.add(status)
        assert len(body) < 1000
    for n in range(50):                                        # unknown methods, as long as a request line takes
        statuses.add(raw_get(platform, "M" * 8000 + str(n), "/platform_instance/read")[0])
    for n in range(50):                                        # unknown query keys (these need a token to reach)
        statuses.add(raw_get(platform, "GET", f"/platform_instance/read?{'k' * 15000}{n}=1",
                             {"Authorization": f"Bearer {reader}"})[0])
    assert statuses == {404, 405, 400}, statuses

    flood_log = assert_evidence_kept(platform, evidence, size_before, grew_at_most=20000)
    assert "a" * 300 not in flood_log and "M" * 300 not in flood_log and "k" * 300 not in flood_log
    assert "unknown path '/aaaa" in flood_log and "characters)" in flood_log     # what came is still said, cut
    error_lines = sum(flood_log.count(f": {status} ") for status in (400, 404, 405))
    windows = 1 + int((time.monotonic() - started) // 10)
    assert 1 <= error_lines <= 10 * windows, (error_lines, windows)     # the budget's burst per window
    # the RDAPI still answers its users
    assert call(platform.master, "GET", "/platform_instance/read", token=reader)[0] == 200


# -- row 2: a robot's reports -------------------------------------------------------------------------------------

class RawRobot:
    """The agent protocol spoken by hand (4-byte length + JSON), as a robot that said hello would."""

    def __init__(self, plat, name, address):
        self.sock = socket.create_connection(("127.0.0.1", plat.master.ic_port), timeout=20,
                                             source_address=(address, 0))
        self.next_id = 1
        answer = self.request("hello", {"name": name, "address": address, "robot": True, "version": 1})
        assert answer["kind"] == "res" and answer["body"]["accepted"], answer

    def send(self, message):
        data = json.dumps(message).encode()
        self.sock.sendall(struct.pack("!I", len(data)) + data)

    def read(self):
        length = struct.unpack("!I", self._exactly(4))[0]
        return json.loads(self._exactly(length))

    def _exactly(self, count):
        data = b""
        while len(data) < count:
            chunk = self.sock.recv(count - len(data))
            assert chunk, "the master closed the connection"
            data += chunk
        return data

    def request(self, op, body):
        msg_id = self.next_id
        self.next_id += 1
        self.send({"v": 1, "id": msg_id, "kind": "req", "op": op, "body": body})
        while True:
            message = self.read()
            if message["kind"] != "req" and message["id"] == msg_id:
                return message
            self.answer(message, {})

    def answer(self, request, body):
        self.send({"v": 1, "id": request["id"], "kind": "res", "op": request["op"], "body": body})

    def next_request(self, op):
        """Read until the master asks ``op`` (heartbeats answered meanwhile); that request."""
        while True:
            message = self.read()
            if message["kind"] == "req" and message["op"] == op:
                return message
            if message["kind"] == "req":
                self.answer(message, {})

    def close(self):
        self.sock.close()


def test_row2_a_robots_huge_reason_and_reports_leave_the_evidence(platform):
    platform.provision_logic("remote_talk", sn_list=[{
        "sn_package": "robotics_test", "sn_type": "talker.py", "sn_name": "talker", "sn_params": "",
        "sn_side": "R"}])
    platform.provision_robot("intruder", "remote_talk")
    robot = RawRobot(platform, "intruder", "127.0.0.2")
    try:
        evidence = write_evidence(platform)
        size_before = len(platform.master.log_text())
        # the master asks the robot to start its R item; the robot answers with a 1 MB reason
        start = robot.next_request("start_items")
        robot.answer(start, {"ros_master_uri": None, "items": [], "reason": "r" * MB, "inbound_port": None})
        wait_until(lambda: (platform.space("intruder")[1] or {}).get("reason"),
                   message="the space to say why it is not paired")
        reason = platform.space("intruder")[1]["reason"]
        assert len(reason) < 1000 and "rrrr" in reason and f"({MB} characters)" in reason
        # seven item_exited reports whose item name is 1 MB (the probe's row 2)
        for _ in range(7):
            answer = robot.request("item_exited", {"ss_name": "intruder", "report": {
                "kind": "node", "name": "n" * MB, "state": "failed", "error": "e" * 1000}})
            assert answer["kind"] == "res", answer
        wait_until(lambda: platform.master.log_text().count("an unknown item was reported") >= 7,
                   message="the reports in the log")
    finally:
        robot.close()
    flood_log = assert_evidence_kept(platform, evidence, size_before, grew_at_most=20000)
    assert "r" * 300 not in flood_log and "n" * 300 not in flood_log
    assert platform.master.get("/")[0] == 200
