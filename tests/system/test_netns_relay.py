"""demo/netns_relay.py: a loopback port of this machine forwarded into a test host's network namespace, bounded.

A test host (``tests/support/hosts.py``) runs Python's HTTP server on its ``eth0`` address, which this machine has
no route to; the relay runs as its own process here (``python3 -m demo.netns_relay``: Twisted's reactor runs once
per process) and the test talks to it on loopback.
"""

import os
import re
import signal
import socket
import urllib.request

import pytest

from tests.support.polling import wait_until
from tests.support.ports import port_accepts

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
HTTP_PORT = 8000

pytestmark = [pytest.mark.netns, pytest.mark.slow]


@pytest.fixture
def served(lan, tmp_path):
    """A host serving ``tmp_path/www`` over HTTP on its eth0 address; (host, its address)."""
    www = tmp_path / "www"
    www.mkdir()
    (www / "marker.txt").write_text("served inside the namespace\n")
    host = lan.add_host("srv")
    host.start(["/usr/bin/python3", "-m", "http.server", "--bind", host.address, "--directory", str(www),
                str(HTTP_PORT)], name="http-server")
    wait_until(lambda: host.run(["/usr/bin/python3", "-c", "import socket, sys; "
                                 "socket.create_connection((sys.argv[1], int(sys.argv[2])), 1)",
                                 host.address, str(HTTP_PORT)], check=False).returncode == 0,
               timeout=15, message="the HTTP server in the host")
    return host


def start_relay(procs, host, *options):
    relay = procs.start(["/usr/bin/python3", "-m", "demo.netns_relay", "--netns", host.netns,
                         "--to", f"{host.address}:{HTTP_PORT}", *options], cwd=ROOT, name="relay")
    line = wait_until(lambda: re.search(r"forwarding 127\.0\.0\.1:(\d+) to ", procs.output(relay)), timeout=20,
                      message="the relay to listen")
    return relay, int(line.group(1))


def closed_by_peer(sock, timeout=10.0):
    """True once the other end closed ``sock`` (what is left to read read, then b"" or a reset) within
    ``timeout``."""
    sock.settimeout(timeout)
    try:
        while sock.recv(4096):
            pass
        return True
    except ConnectionResetError:
        return True
    except socket.timeout:
        return False


def test_the_relay_reaches_the_server_inside_the_namespace_and_stops_cleanly(procs, served):
    relay, port = start_relay(procs, served)
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/marker.txt", timeout=10) as answer:
        assert answer.read() == b"served inside the namespace\n"
    held = socket.create_connection(("127.0.0.1", port), timeout=5)
    try:
        os.kill(relay.pid, signal.SIGTERM)
        assert relay.wait(timeout=20) == 0
        assert closed_by_peer(held)
        assert not port_accepts(port)
    finally:
        held.close()


def test_connections_are_bounded_in_number(procs, served):
    relay, port = start_relay(procs, served, "--max-connections", "2")
    first = socket.create_connection(("127.0.0.1", port), timeout=5)
    second = socket.create_connection(("127.0.0.1", port), timeout=5)
    try:
        # two held open (the server waits for their requests); a third is closed at once, before any byte
        third = socket.create_connection(("127.0.0.1", port), timeout=5)
        try:
            assert closed_by_peer(third, timeout=5)
        finally:
            third.close()
        # the held ones are relayed: a request on one is answered (and the server closes it, HTTP/1.0)
        first.sendall(b"GET /marker.txt HTTP/1.1\r\nHost: x\r\n\r\n")
        first.settimeout(10)
        assert first.recv(4096).startswith(b"HTTP/1.0 200")
        assert closed_by_peer(first)
        # which leaves room for a new one
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/marker.txt", timeout=10) as answer:
            assert answer.status == 200
    finally:
        first.close()
        second.close()
    procs.stop(relay)


def test_a_connection_quiet_for_longer_than_the_idle_limit_is_closed(procs, served):
    relay, port = start_relay(procs, served, "--idle-timeout", "1.5")
    quiet = socket.create_connection(("127.0.0.1", port), timeout=5)
    try:
        assert closed_by_peer(quiet, timeout=15)     # the HTTP server would wait for its request for ever
    finally:
        quiet.close()
    procs.stop(relay)
