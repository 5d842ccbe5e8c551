"""Every shared pool of a real master (``python3 -m rcm_platform``) has a share per source address: while one
address holds its whole share, a legitimate client from another address is served (issue 18 item 2). Tried as
the attacker did: connections that are opened and then never read or never used.

Row 3 of issue 18: 64 console event streams from two addresses, never read, made every operator get 503. Here the
same 64 leave each attacking address its share (``MAX_PER_ADDRESS``) and an operator from a third address gets
the whole snapshot. The same for the RDAPI (32 idle connections from one address) and the agent port (8
connections from one address that never say hello, while a robot from another address pairs). The watchers'
socket is in ``test_console_watchers.py``.
"""

import json
import socket

import pytest

from rcm_platform import rcmp_console, rcmp_ext_connector
from rcm_platform import rcmp_inter_communication as ic
from tests.support.lifecycle import Platform
from tests.support.polling import wait_until


@pytest.fixture
def platform(procs, tmp_path):
    plat = Platform(procs, tmp_path / "platform", inbound_ports=0)
    plat.master.start()
    try:
        yield plat
    finally:
        plat.stop_all_and_check_nothing_left()


def connect(plat, source, port=None, timeout=10):
    return socket.create_connection((plat.master.host, port or plat.master.ext_port), timeout=timeout,
                                    source_address=(source, 0))


class EventStream:
    """A console event stream read by hand from ``source`` (a page's fetch of /console/api/events, or an attacker
    who never reads it)."""

    def __init__(self, plat, source, path="/console/api/events"):
        self.sock = connect(plat, source)
        self.sock.sendall(f"GET {path} HTTP/1.1\r\nHost: {plat.master.host}\r\n\r\n".encode())
        self.buffer = b""
        self.pending = []           # events read but not yet asked for

    def status(self):
        while b"\r\n\r\n" not in self.buffer:
            self._more()
        head, self.buffer = self.buffer.split(b"\r\n\r\n", 1)
        return int(head.split(b" ", 2)[1])

    def _more(self):
        chunk = self.sock.recv(65536)
        assert chunk, "the master closed the stream"
        self.buffer += chunk

    def events(self):
        """The events complete so far, ``[(name, data text)]``, consumed; reads once more when there are none. The
        chunked transfer's size lines fall between events (each event is one write), never inside a data line."""
        if b"\n\n" not in self.buffer:
            self._more()
        found = []
        *blocks, self.buffer = self.buffer.split(b"\n\n")
        for block in blocks:
            lines = block.split(b"\n")
            name = next((line[len(b"event: "):] for line in lines if line.startswith(b"event: ")), None)
            data = next((line[len(b"data: "):] for line in lines if line.startswith(b"data: ")), None)
            if name is not None and data is not None:
                found.append((name.decode(), data.decode()))
        return found

    def event(self, name):
        """The data of the next event ``name``, parsed (the events before it are read and dropped)."""
        while True:
            self.pending = self.pending or self.events()
            while self.pending:
                found, data = self.pending.pop(0)
                if found == name:
                    return json.loads(data)

    def close(self):
        self.sock.close()


def test_row3_streams_never_read_from_two_addresses_leave_every_other_operator_served(platform):
    share = rcmp_console.MAX_PER_ADDRESS
    held, statuses = [], {"127.0.0.2": [], "127.0.0.3": []}
    try:
        for n in range(64):                                    # the probe: 64 streams from two addresses, never read
            source = "127.0.0.2" if n % 2 else "127.0.0.3"
            stream = EventStream(platform, source)
            statuses[source].append(stream.status())
            held.append(stream)
        for source, got in statuses.items():
            assert got.count(200) == share and got.count(503) == 32 - share, (source, got)
        operator = EventStream(platform, "127.0.0.4")
        assert operator.status() == 200
        snapshot = operator.event("snapshot")
        assert "robots" in snapshot and "logics" in snapshot
        operator.close()
    finally:
        for stream in held:
            stream.close()


def test_the_rdapi_serves_another_address_while_one_holds_its_whole_share(platform):
    share = rcmp_ext_connector.MAX_PER_ADDRESS
    held = [connect(platform, "127.0.0.2") for _ in range(share)]          # opened, never used
    try:
        wait_until(lambda: (lambda s: s == 503)(_get_status(platform, "127.0.0.2")), timeout=10,
                   message="the holder's next connection to get 503")
        assert _get_status(platform, "127.0.0.3") == 200
    finally:
        for sock in held:
            sock.close()


def _get_status(plat, source):
    sock = connect(plat, source)
    try:
        sock.sendall(f"GET /platform_instance/read HTTP/1.1\r\nHost: {plat.master.host}\r\n"
                     f"Connection: close\r\n\r\n".encode())
        data = b""
        while b"\r\n" not in data:
            chunk = sock.recv(4096)
            if not chunk:
                break
            data += chunk
        return int(data.split(b" ", 2)[1])
    finally:
        sock.close()


def test_the_agent_port_serves_a_robot_from_another_address_while_one_holds_its_whole_share(platform):
    port = platform.master.ic_port
    share = ic.MAX_PER_ADDRESS
    held = [connect(platform, "127.0.0.5", port) for _ in range(share)]      # connected, never say hello
    try:
        extra = connect(platform, "127.0.0.5", port)
        extra.settimeout(10)
        assert extra.recv(1) == b""                            # over the share: closed before anything is read
        extra.close()
        platform.provision_robot("robot1", "empty")
        robot = platform.robot("robot1", "127.0.0.3")
        robot.start()
        platform.wait_state("robot1", True, True, timeout=30)
        for sock in held:                                      # and the held ones go at the hello deadline
            sock.settimeout(20)
            try:
                assert sock.recv(1) == b""
            except ConnectionResetError:
                pass
    finally:
        for sock in held:
            sock.close()
