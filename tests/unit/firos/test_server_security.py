"""FIROS's `include/server.py` on real sockets with a fake bridge: the worker pool, its shares (a per-address share,
the broker's larger one and the workers the others leave it) and its caps (503 at once), the request deadline and
a connection's lifetime, the administration socket (administrative calls there; over TCP only with the token),
JSON-only bodies, edits refused from web pages, strict JSON answers and what reaches the log. The attacks against a
real FIROS are in tests/system/test_firos_security.py."""

import http.client as client
import json
import logging
import os
import socket
import stat
import time

import pytest

from include import server as http
from tests.support.firos import UnixHTTPConnection
from tests.support.polling import wait_until


class FakeWhitelist:
    def __init__(self):
        self.data = {}

    def snapshot(self):
        return dict(self.data)


class FakeFiros:
    def __init__(self, robots=()):
        self.whitelist = FakeWhitelist()
        self.robots = list(robots)

    def list_robots(self):
        return self.robots

    def whitelist_write(self, data):
        self.whitelist.data.update(data)


def _serve(pool, admin_socket=None, firos=None, **options):
    servers = http.make_servers(firos or FakeFiros(), 0, ["127.0.0.1"], pool=pool, admin_socket=admin_socket,
                                **options)
    for server in servers:
        http.serve_in_thread(server)
    return servers


def _small_server(monkeypatch, deadline):
    """A real FIROS HTTP server on 127.0.0.1 with 2 workers, 1 waiting place, 1 connection per source and a
    ``deadline`` s request deadline; yields (port, pool)."""
    monkeypatch.setattr(http, "REQUEST_DEADLINE", deadline)
    pool = http.WorkerPool(workers=2, queue_limit=1, per_source=1)
    servers = _serve(pool)
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
    except (ConnectionResetError, TimeoutError, socket.timeout):
        return data


def _held(pool, count, waiting):
    """Wait until the pool holds ``count`` connections, ``waiting`` of them not yet at a worker."""
    wait_until(lambda: pool.held() == count and pool.waiting() == waiting, timeout=2,
               message=f"the pool to hold {count} connections, {waiting} waiting")


def test_per_source_share_and_pool_limit_answer_503_at_once(small_server_and_pool):
    port, pool = small_server_and_pool
    first = _connect(port, "127.0.0.2")
    first.sendall(b"GET /robots HTTP/1.1\r\n")        # holds its worker until the deadline
    _held(pool, 1, 0)
    second = _connect(port, "127.0.0.2")                 # same source: over its share of 1
    answer = _read_all(second)
    assert answer.startswith(b"HTTP/1.1 503 ") and b"Retry-After: 1" in answer, answer
    assert json.loads(answer.split(b"\r\n\r\n", 1)[1])["result"] == "ERROR"
    # 2 workers + 1 waiting place, filled one source at a time: the fourth slow client is refused at once
    others = []
    for i, state in ((3, (2, 0)), (4, (3, 1))):
        others.append(_connect(port, f"127.0.0.{i}"))
        others[-1].sendall(b"GET /robots HTTP/1.1\r\n")
        _held(pool, *state)
    refused = _connect(port, "127.0.0.5")
    assert _read_all(refused).startswith(b"HTTP/1.1 503 ")
    assert pool.refused == 2
    answers = [_read_all(sock) for sock in [first] + others]     # each served (cut at its deadline), none a 503
    assert not any(a.startswith(b"HTTP/1.1 503 ") for a in answers), answers
    others.append(refused)
    for sock in [first, second] + others:
        sock.close()


def test_the_brokers_address_has_a_larger_share_and_workers_the_others_leave_it(monkeypatch):
    monkeypatch.setattr(http, "REQUEST_DEADLINE", 3.0)
    pool = http.WorkerPool(workers=4, queue_limit=2, per_source=1, shares={"127.0.0.9": 2}, reserve=2)
    servers = _serve(pool)
    port = servers[0].server_address[1]
    held = []
    try:
        for source, state in (("127.0.0.2", 1), ("127.0.0.3", 2)):     # two other addresses: one each
            held.append(_connect(port, source))
            held[-1].sendall(b"GET /robots HTTP/1.1\r\n")
            _held(pool, state, 0)
        third = _connect(port, "127.0.0.4")        # the others hold the 2 workers not kept for the broker
        assert _read_all(third).startswith(b"HTTP/1.1 503 ")
        for state in (3, 4):                       # the broker's address: two connections, both at a worker
            held.append(_connect(port, "127.0.0.9"))
            held[-1].sendall(b"GET /robots HTTP/1.1\r\n")
            _held(pool, state, 0)
        over = _connect(port, "127.0.0.9")
        assert _read_all(over).startswith(b"HTTP/1.1 503 ")
    finally:
        for sock in held:
            sock.close()
        http.close_servers(servers)


def test_a_connection_trickling_requests_is_closed_at_its_lifetime(monkeypatch):
    monkeypatch.setattr(http, "REQUEST_DEADLINE", 1.0)
    monkeypatch.setattr(http, "LIFETIME", 2.0)
    servers = _serve(http.WorkerPool(workers=2, queue_limit=1, per_source=2))
    conn = client.HTTPConnection("127.0.0.1", servers[0].server_address[1], timeout=5)
    try:
        started, answers = time.monotonic(), []
        while True:                                 # one small request every 0.2 s, never idle long
            conn.request("GET", "/robots")
            response = conn.getresponse()
            assert response.status == 200 and json.loads(response.read()) == []
            answers.append(response.getheader("Connection"))
            if response.getheader("Connection") == "close":
                break
            time.sleep(0.2)                        # the attacker's pace (a request now and then), not a wait
            assert time.monotonic() - started < 10, "the connection outlived its lifetime"
        # closed after the first answer once LIFETIME - REQUEST_DEADLINE old (the next request's deadline would
        # end past the lifetime), never before
        assert time.monotonic() - started >= 1.0 and len(answers) >= 2 and set(answers[:-1]) == {None}, answers
        assert conn.sock is None or conn.sock.recv(1) == b""
    finally:
        conn.close()
        http.close_servers(servers)


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
        except (TimeoutError, socket.timeout):
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


def _call(conn, method, path, body=None, headers=None):
    data = None if body is None else json.dumps(body).encode()
    conn.request(method, path, body=data, headers=dict({"Content-Type": "application/json"}, **(headers or {})))
    response = conn.getresponse()
    return response.status, json.loads(response.read())


def test_administration_goes_through_the_socket_or_the_token_never_through_being_local(tmp_path):
    path = str(tmp_path / "admin" / "firos.sock")
    firos = FakeFiros()
    servers = _serve(http.WorkerPool(workers=2, queue_limit=2), admin_socket=path, firos=firos)
    port = servers[0].server_address[1]
    try:
        assert stat.S_ISSOCK(os.stat(path).st_mode) and stat.S_IMODE(os.stat(path).st_mode) == 0o600
        assert stat.S_IMODE(os.stat(os.path.dirname(path)).st_mode) == 0o700
        # from this very machine over TCP (what a broker here can be subscribed to send): refused, naming the way
        status, body = _call(client.HTTPConnection("127.0.0.1", port, timeout=5), "POST", "/whitelist/write",
                             {"bot": {}})
        assert status == 403 and f"curl --unix-socket {path} http://firos/whitelist/write" in body["reason"], body
        assert firos.whitelist.data == {}
        # the operator on the socket; reads there too
        assert _call(UnixHTTPConnection(path), "POST", "/whitelist/write", {"bot": {}}) == (
            200, {"result": "OK", "reason": {"bot": {}}})
        assert _call(UnixHTTPConnection(path), "GET", "/robots") == (200, [])
        # never from a web page, even there
        assert _call(UnixHTTPConnection(path), "POST", "/whitelist/write", {"x": {}}, {"Origin": "http://evil"})[0] == 403
        # another FIROS on the same socket cannot start; a socket left by a killed one is taken over
        with pytest.raises(OSError, match="another FIROS answers"):
            http.make_servers(FakeFiros(), 0, [], admin_socket=path, pool=http.WorkerPool(workers=1))
    finally:
        http.close_servers(servers)
    assert not os.path.exists(path)                       # removed at the end
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stale.bind(path)
    stale.close()                                          # a socket file nobody answers on
    servers = _serve(http.WorkerPool(workers=1), admin_socket=path)
    try:
        assert _call(UnixHTTPConnection(path), "GET", "/robots") == (200, [])
    finally:
        http.close_servers(servers)
    shared = tmp_path / "shared"
    shared.mkdir(mode=0o777)
    os.chmod(shared, 0o777)
    with pytest.raises(OSError, match="others may write"):
        http.make_servers(FakeFiros(), 0, [], admin_socket=str(shared / "s.sock"), pool=http.WorkerPool(workers=1))


def test_with_a_token_administration_over_tcp_needs_it(tmp_path):
    token = "a-token-of-sixteen-or-more"
    servers = _serve(http.WorkerPool(workers=2, queue_limit=2), admin_token=token)
    port = servers[0].server_address[1]
    try:
        tcp = client.HTTPConnection("127.0.0.1", port, timeout=5)
        assert _call(tcp, "POST", "/robot/disconnect/bot")[0] == 401
        tcp = client.HTTPConnection("127.0.0.1", port, timeout=5)
        assert _call(tcp, "POST", "/whitelist/write", {"bot": {}}, {"Authorization": f"Bearer {token}"})[0] == 200
    finally:
        http.close_servers(servers)


def test_answers_are_strict_json_with_nonfinite_numbers_as_strings():
    servers_firos = FakeFiros([{"name": "bot", "x": float("nan"), "y": [float("inf"), -float("inf"), 1.5]}])
    servers = _serve(http.WorkerPool(workers=3), firos=servers_firos)
    try:
        conn = client.HTTPConnection("127.0.0.1", servers[0].server_address[1], timeout=5)
        conn.request("GET", "/robots")
        text = conn.getresponse().read().decode()
        conn.close()

        def refuse(constant):
            raise ValueError(f"bare {constant}")
        assert json.loads(text, parse_constant=refuse) == [{"name": "bot", "x": "NaN",
                                                           "y": ["Infinity", "-Infinity", 1.5]}]
        # http.server's own refusals (a request it cannot parse) are JSON too
        sock = _connect(servers[0].server_address[1], "127.0.0.11")
        sock.sendall(b"GET /robots HTTP/1.1\r\n" + b"X: y\r\n" * 101 + b"\r\n")
        answer = _read_all(sock)
        assert answer.startswith(b"HTTP/1.1 431 ") and b"application/json" in answer, answer
        assert json.loads(answer.split(b"\r\n\r\n", 1)[1])["result"] == "ERROR"
        # no metrics wired: a 503 with a sentence, not a traceback
        status, body = _call(client.HTTPConnection("127.0.0.1", servers[0].server_address[1], timeout=5),
                             "GET", "/metrics")
        assert status == 503 and body["result"] == "ERROR"
    finally:
        http.close_servers(servers)


def test_a_flood_of_refused_requests_writes_a_few_short_lines(firos_log):
    servers = _serve(http.WorkerPool(workers=2, queue_limit=2, per_source=50))
    port = servers[0].server_address[1]
    logging.getLogger("firos.server").info("evidence before the flood")
    try:
        conn = client.HTTPConnection("127.0.0.1", port, timeout=5)
        for i in range(150):
            conn.request("POST", "/whitelist/restore?" if i % 2 else "/" + "x" * 16000, body=b"",
                         headers={"Content-Length": "0"})
            conn.getresponse().read()
            conn.close()
    finally:
        http.close_servers(servers)
    records = [r for r in firos_log.records if r.name == "firos.server"]
    lines = [r.getMessage() for r in records if r.levelno >= logging.INFO and "request lines" not in r.getMessage()]
    assert lines[0] == "evidence before the flood"
    assert len(lines) <= 1 + 10 + 1, lines            # the budget's 10, and the line counting the rest
    assert "more lines about refused or failed requests were left out" in lines[-1], lines[-1]
    requests = [r.getMessage() for r in records if r.levelno == logging.DEBUG or "request lines" in r.getMessage()]
    assert len(requests) <= 10 + 1 and "more request lines were left out" in requests[-1], requests   # DEBUG too
    assert all(len(r.getMessage()) < 700 for r in records), max(len(r.getMessage()) for r in records)
