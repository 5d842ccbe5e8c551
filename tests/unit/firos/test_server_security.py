"""FIROS's `include/server.py` on a real loopback socket with a fake bridge: the worker pool and its caps (503 at
once), the request deadline, JSON-only bodies and edits refused from web pages. The attacks against a real FIROS
are in tests/system/test_firos_security.py."""

import json
import socket

import pytest

from include import server as http
from tests.support.polling import wait_until


class FakeFiros:
    def list_robots(self):
        return []


def _small_server(monkeypatch, deadline):
    """A real FIROS HTTP server on 127.0.0.1 with 2 workers, 1 waiting place, 1 connection per client and a
    ``deadline`` s request deadline; yields (port, pool)."""
    monkeypatch.setattr(http, "REQUEST_DEADLINE", deadline)
    pool = http.WorkerPool(workers=2, queue_limit=1, per_client=1)
    servers = http.make_servers(FakeFiros(), 0, ["127.0.0.1"], pool=pool)
    http.serve_in_thread(servers[0])
    try:
        yield servers[0].server_address[1], pool
    finally:
        http.close_servers(servers)


@pytest.fixture
def small_server(monkeypatch):
    for port, _pool in _small_server(monkeypatch, 1.0):
        yield port


@pytest.fixture
def small_server_and_pool(monkeypatch):
    """As small_server, with a deadline long enough for the test to fill the pool step by step (3 s)."""
    yield from _small_server(monkeypatch, 3.0)


def _connect(port, source):
    sock = socket.create_connection(("127.0.0.1", port), timeout=5, source_address=(source, 0))
    return sock


def _read_all(sock):
    data = b""
    try:
        while True:
            chunk = sock.recv(4096)
            if not chunk:
                return data
            data += chunk
    except (ConnectionResetError, TimeoutError):
        return data


def test_per_client_cap_and_pool_limit_answer_503_at_once(small_server_and_pool):
    port, pool = small_server_and_pool

    def held(count, waiting):    # the pool holds ``count`` connections, ``waiting`` of them not yet at a worker
        wait_until(lambda: pool.held() == count and pool.waiting() == waiting, timeout=2,
                   message=f"the pool to hold {count} connections, {waiting} waiting")

    first = _connect(port, "127.0.0.2")
    first.sendall(b"GET /robots HTTP/1.1\r\n")        # holds its worker until the deadline
    held(1, 0)
    second = _connect(port, "127.0.0.2")                 # same client: over its cap of 1
    answer = _read_all(second)
    assert answer.startswith(b"HTTP/1.1 503 ") and b"Retry-After: 1" in answer, answer
    assert json.loads(answer.split(b"\r\n\r\n", 1)[1])["result"] == "ERROR"
    # 2 workers + 1 waiting place, filled one client at a time: the fourth slow client is refused at once
    others = []
    for i, state in ((3, (2, 0)), (4, (3, 1))):
        others.append(_connect(port, f"127.0.0.{i}"))
        others[-1].sendall(b"GET /robots HTTP/1.1\r\n")
        held(*state)
    refused = _connect(port, "127.0.0.5")
    assert _read_all(refused).startswith(b"HTTP/1.1 503 ")
    answers = [_read_all(sock) for sock in [first] + others]     # each served (cut at its deadline), none a 503
    assert not any(a.startswith(b"HTTP/1.1 503 ") for a in answers), answers
    others.append(refused)
    for sock in [first, second] + others:
        sock.close()


def test_a_byte_now_and_then_does_not_extend_the_request_deadline(small_server):
    sock = _connect(small_server, "127.0.0.6")
    closed = []

    def dribble():
        try:
            sock.sendall(b"G")
        except OSError:
            closed.append(True)
            return True
        sock.settimeout(0.15)
        try:
            if sock.recv(1) == b"":
                closed.append(True)
                return True
        except TimeoutError:
            return False
        except OSError:
            closed.append(True)
            return True
        return False
    wait_until(dribble, timeout=5, interval=0.05, message="FIROS to cut a client sending one byte at a time")
    sock.close()
    assert closed


def test_bodies_must_be_json_and_edits_from_web_pages_are_refused(small_server):
    sock = _connect(small_server, "127.0.0.7")
    sock.sendall(b"POST /firos HTTP/1.1\r\nHost: x\r\nContent-Type: text/plain\r\nContent-Length: 2\r\n\r\n{}")
    answer = _read_all(sock)
    assert answer.startswith(b"HTTP/1.1 415 ") and b"access-control" not in answer.lower(), answer
    sock = _connect(small_server, "127.0.0.8")   # another client: 127.0.0.7's slot may not be free yet
    sock.sendall(b"POST /whitelist/write HTTP/1.1\r\nHost: x\r\nOrigin: http://evil\r\n"
                 b"Content-Type: application/json\r\nContent-Length: 2\r\n\r\n{}")
    assert _read_all(sock).startswith(b"HTTP/1.1 403 ")
