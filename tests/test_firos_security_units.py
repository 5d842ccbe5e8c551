"""FIROS's security pieces alone (no ROS): the regex shape check, the configured-literal rule, the new
configuration keys, the default listening addresses, and the HTTP server's pool, caps and request deadline on a
real loopback socket with a fake bridge. The attacks themselves, against a real FIROS, are in
tests/test_firos_security.py."""

import json
import os
import socket
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "firos", "scripts"))

import core  # noqa: E402
from include import config as cfg  # noqa: E402
from include import server as http  # noqa: E402
from include.whitelist import Whitelist, WhitelistError, costly_shape, sre_parse, validate  # noqa: E402
from tests.support.firos import write_config  # noqa: E402
from tests.support.polling import wait_until  # noqa: E402


@pytest.mark.parametrize("pattern, refused", [
    ("(a|a)*b", "alternation inside a repetition"),
    ("(?:a|ab)*c", "alternation inside a repetition"),
    ("(a+)+b", "repetition inside a repetition"),
    ("(a*)*", "repetition inside a repetition"),
    ("(ab{2,3})*", "repetition inside a repetition"),
    ("(x)\\1", "backreference"),
    (".*a.*b.*c", "too many repetitions"),
    (".{0,40}.{0,40}.{0,40}.{0,40}x", "too many repetitions"),
    ("turtle\\w+", None), (".*move_base/goal", None), ("cmd_vel.*teleop", None), (".*foo.*", None),
    ("(cmd|odom)/.*", None), ("(a|b)*", None), ("[ab]*c", None), ("a{1,5}b{1,5}.*", None), ("p1", None),
])
def test_costly_shapes(pattern, refused):
    problem = costly_shape(sre_parse.parse(pattern))
    if refused is None:
        assert problem is None
        validate({"r": {"publisher": [pattern]}})
    else:
        assert refused in problem
        with pytest.raises(WhitelistError):
            validate({"r": {"publisher": [pattern]}})


def test_long_patterns_and_names():
    with pytest.raises(WhitelistError, match="longer than 256"):
        validate({"a" * 257: {}})
    whitelist = Whitelist("unused", {"r\\w*": {"publisher": ["p\\w*"]}})
    assert whitelist.robot_allowed("r" * 256) and not whitelist.robot_allowed("r" * 257)
    assert whitelist.topic_kinds("r1", "p" * 256) == {"publisher"}
    assert whitelist.topic_kinds("r1", "p" * 257) == set()


def test_only_plain_names_of_the_configured_whitelist_may_be_commanded_outside_the_graph(tmp_path):
    config = write_config(str(tmp_path), 1026, whitelist={"end_end_test": {"publisher": ["p1", "q.*"]}})
    whitelist = Whitelist.load(config)
    assert whitelist.configured_literal("end_end_test", "p1")
    assert not whitelist.configured_literal("end_end_test", "q1")        # a regex entry
    assert not whitelist.configured_literal("other", "p1")
    whitelist.write({"end_end_test": {"publisher": ["p2"]}})
    assert "publisher" in whitelist.topic_kinds("end_end_test", "p2")
    assert not whitelist.configured_literal("end_end_test", "p2")        # an HTTP edit
    whitelist.restore()
    assert whitelist.configured_literal("end_end_test", "p1")


def _settings(tmp_path, **server):
    config = write_config(str(tmp_path), 1026, server=dict({"port": 10100}, **server))
    return cfg.load_settings(config)


def test_server_address_and_admin_token_keys(tmp_path):
    assert _settings(tmp_path).server_addresses is None and _settings(tmp_path).admin_token is None
    assert _settings(tmp_path, address="203.0.113.5").server_addresses == ["203.0.113.5"]
    assert _settings(tmp_path, address=["127.0.0.1", "::1", "127.0.0.1"]).server_addresses == ["127.0.0.1", "::1"]
    assert _settings(tmp_path, admin_token="x" * 16).admin_token == "x" * 16
    for bad in ({"address": "somehost"}, {"address": []}, {"address": 5}, {"admin_token": "short"},
                {"admin_token": "has a space in it!!"}):
        with pytest.raises(cfg.ConfigError) as info:
            _settings(tmp_path, **bad)
        assert "server." in str(info.value) and "\n" not in str(info.value)


def test_default_listening_addresses(tmp_path, monkeypatch):
    settings = _settings(tmp_path)
    monkeypatch.delenv("ROS_IP", raising=False)
    assert core.listen_addresses(settings, "127.0.0.1") == (["127.0.0.1"], [])
    monkeypatch.setenv("ROS_IP", "198.51.100.1")
    assert core.listen_addresses(settings, "203.0.113.10") == (["198.51.100.1"], ["203.0.113.10"])
    assert core.listen_addresses(settings, "198.51.100.1") == (["198.51.100.1"], [])
    configured = _settings(tmp_path, address=["0.0.0.0"])
    assert core.listen_addresses(configured, "203.0.113.10") == (["0.0.0.0"], [])


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
