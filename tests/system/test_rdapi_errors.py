"""The RDAPI's error corpus: every bad request gets the right 4xx, ``ERROR`` with a reason, and changes nothing.

All requests go through real HTTP (raw sockets for the malformed ones) to a real master on loopback; the
database file must be byte-for-byte the same after the whole corpus as before it.
"""

import hashlib
import json
import socket

import pytest

from tests.support.rcmp_agent import RcmpAgent

NODE = {"sn_package": "pkg", "sn_type": "node.py", "sn_name": "n1", "sn_params": "", "sn_side": "S"}
LAUNCHER = {"sl_package": "pkg", "sl_file_launcher": "x.launch", "sl_name": "l1", "sl_params": "",
            "sl_side": "R"}
PI = "/platform_instance/provisioning"
PIR = "/platform_instance/r_provisioning"
SL = "/service_logic/provisioning"
SLR = "/service_logic/r_provisioning"


def sl(**fields):
    body = {"slg_name": "bad_one", "sn_list": [NODE], "sl_list": [LAUNCHER]}
    body.update(fields)
    return body


def node(**fields):
    item = dict(NODE)
    item.update(fields)
    return {"slg_name": "bad_one", "sn_list": [item]}


def launcher(**fields):
    item = dict(LAUNCHER)
    item.update(fields)
    return {"slg_name": "bad_one", "sl_list": [item]}


def without(item, key):
    item = dict(item)
    del item[key]
    return item


BIG = b'{"slg_name": "big", "pad": "' + b"x" * (70 * 1024) + b'"}'

# (method, path, body: dict -> JSON, bytes -> as is, None -> no body, expected status, a word the reason has)
CORPUS = [
    # malformed bodies
    ("POST", SL, b"{not json", 400, "JSON"),
    ("POST", SL, b"", 400, "empty"),
    ("POST", SL, b"   \n", 400, "empty"),
    ("POST", SL, b'["slg_name"]', 400, "object"),
    ("POST", SL, b'"slg_name"', 400, "object"),
    ("POST", SL, b"null", 400, "object"),
    ("POST", SL, b"42", 400, "object"),
    ("POST", SL, b'{"slg_name": "a"', 400, "JSON"),
    ("POST", SL, b'{"slg_name": "\xff\xfe"}', 400, "UTF-8"),
    ("POST", PI, b"{'pi_name': 'r'}", 400, "JSON"),
    # missing fields
    ("POST", SL, {}, 400, "slg_name"),
    ("POST", PI, {"pi_name": "r1"}, 400, "pi_service_logic"),
    ("POST", PI, {"pi_service_logic": "fiware_base"}, 400, "pi_name"),
    ("POST", PIR, {}, 400, "pi_name"),
    ("POST", SLR, {}, 400, "slg_name"),
    ("POST", SL, {"slg_name": "bad_one", "sn_list": [without(NODE, "sn_side")]}, 400, "sn_side"),
    ("POST", SL, {"slg_name": "bad_one", "sn_list": [without(NODE, "sn_package")]}, 400, "sn_package"),
    ("POST", SL, {"slg_name": "bad_one", "sl_list": [without(LAUNCHER, "sl_file_launcher")]}, 400,
     "sl_file_launcher"),
    # unknown fields
    ("POST", PI, {"pi_name": "r1", "pi_service_logic": "fiware_base", "extra": 1}, 400, "extra"),
    ("POST", SL, node(sn_colour="red"), 400, "sn_colour"),
    # wrong types
    ("POST", SL, {"slg_name": 42}, 400, "string"),
    ("POST", SL, {"slg_name": None}, 400, "slg_name"),
    ("POST", SL, {"slg_name": ["a"]}, 400, "string"),
    ("POST", SL, sl(sn_list={"a": 1}), 400, "list"),
    ("POST", SL, sl(sn_list="n1"), 400, "list"),
    ("POST", SL, sl(sn_list=["n1"]), 400, "object"),
    ("POST", SL, node(sn_params=["-a"]), 400, "sn_params"),
    ("POST", SL, node(sn_package=7), 400, "sn_package"),
    ("POST", PI, {"pi_name": True, "pi_service_logic": "fiware_base"}, 400, "pi_name"),
    ("POST", PI, {"pi_name": "r1", "pi_service_logic": {"slg_name": "x"}}, 400, "pi_service_logic"),
    # bad names
    ("POST", PI, {"pi_name": "", "pi_service_logic": "fiware_base"}, 400, "empty"),
    ("POST", PI, {"pi_name": "r" * 65, "pi_service_logic": "fiware_base"}, 400, "64"),
    ("POST", PI, {"pi_name": "robots/r1", "pi_service_logic": "fiware_base"}, 400, "valid name"),
    ("POST", PI, {"pi_name": "/r1", "pi_service_logic": "fiware_base"}, 400, "valid name"),
    ("POST", PI, {"pi_name": "my robot", "pi_service_logic": "fiware_base"}, 400, "valid name"),
    ("POST", PI, {"pi_name": "r1;rm -rf /", "pi_service_logic": "fiware_base"}, 400, "valid name"),
    ("POST", PI, {"pi_name": "$(reboot)", "pi_service_logic": "fiware_base"}, 400, "valid name"),
    ("POST", PI, {"pi_name": "`id`", "pi_service_logic": "fiware_base"}, 400, "valid name"),
    ("POST", PI, {"pi_name": "r\u00f6bot", "pi_service_logic": "fiware_base"}, 400, "valid name"),
    ("POST", PI, {"pi_name": "\u673a\u5668\u4eba", "pi_service_logic": "fiware_base"}, 400, "valid name"),
    ("POST", PI, {"pi_name": "1robot", "pi_service_logic": "fiware_base"}, 400, "valid name"),
    ("POST", PI, {"pi_name": "_robot", "pi_service_logic": "fiware_base"}, 400, "valid name"),
    ("POST", PI, {"pi_name": "r1\n", "pi_service_logic": "fiware_base"}, 400, "valid name"),
    ("POST", PI, {"pi_name": "r-1", "pi_service_logic": "fiware_base"}, 400, "valid name"),
    ("POST", SL, {"slg_name": "a.b"}, 400, "valid name"),
    ("POST", SL, node(sn_name="talker/1"), 400, "sn_name"),
    ("POST", SL, launcher(sl_name="my launcher"), 400, "sl_name"),
    ("POST", SL, node(sn_package="pkg;ls"), 400, "sn_package"),
    ("POST", SL, node(sn_type="../../bin/sh"), 400, "sn_type"),
    ("POST", SL, launcher(sl_file_launcher="$(x).launch"), 400, "sl_file_launcher"),
    ("POST", SL, node(sn_type=""), 400, "empty"),
    # sides
    ("POST", SL, node(sn_side="X"), 400, "sn_side"),
    ("POST", SL, node(sn_side="s"), 400, "sn_side"),
    ("POST", SL, launcher(sl_side=""), 400, "sl_side"),
    ("POST", SL, launcher(sl_side=1), 400, "sl_side"),
    ("POST", SL, sl(ss_side="robot"), 400, "ss_side"),
    # params a shell could not split
    ("POST", SL, node(sn_params="'unbalanced"), 400, "sn_params"),
    ("POST", SL, launcher(sl_params='say "hi'), 400, "sl_params"),
    ("POST", SL, node(sn_params="a\\"), 400, "sn_params"),
    # duplicate item names inside one service logic
    ("POST", SL, {"slg_name": "bad_one", "sn_list": [NODE, NODE]}, 400, "twice"),
    # unknown names, conflicts
    ("POST", PI, {"pi_name": "r9", "pi_service_logic": "no_such_logic"}, 404, "no_such_logic"),
    ("POST", PIR, {"pi_name": "ghost"}, 404, "ghost"),
    ("POST", SLR, {"slg_name": "ghost"}, 404, "ghost"),
    ("POST", SL, {"slg_name": "fiware_base"}, 409, "fiware_base"),
    ("POST", SL, {"slg_name": "used"}, 409, "used"),
    ("POST", PI, {"pi_name": "existing", "pi_service_logic": "fiware_base"}, 409, "existing"),
    ("POST", PI, {"pi_name": "master", "pi_service_logic": "fiware_base"}, 409, "master"),
    ("POST", SLR, {"slg_name": "used"}, 409, "existing"),
    ("POST", PIR, {"pi_name": "master"}, 404, "master"),
    # reads
    ("GET", "/service_logic/read?slg_name=ghost", None, 404, "ghost"),
    ("GET", "/service_logic/read?slg_name=a/b", None, 400, "valid name"),
    ("GET", "/service_logic/read?slg_name=", None, 400, "empty"),
    ("GET", "/service_logic/read?slg_name=a&slg_name=b", None, 400, "2 times"),
    ("GET", "/service_logic/read?name=x", None, 400, "name"),
    ("GET", "/platform_instance/read?x=1", None, 400, "x"),
    ("GET", "/service_logic/read?slg_name=%FF", None, 400, "UTF-8"),
    ("GET", "/service_space/read", None, 400, "ss_name"),
    ("GET", "/service_space/read?ss_name=existing", None, 404, "existing"),
    ("GET", "/service_space/read?ss_name=$(id)", None, 400, "valid name"),
    # wrong methods
    ("GET", PI, None, 405, "POST"),
    ("GET", SLR, None, 405, "POST"),
    ("POST", "/platform_instance/read", {"pi_name": "r"}, 405, "GET"),
    ("POST", "/service_logic/read", {}, 405, "GET"),
    ("PUT", SL, sl(), 405, "POST"),
    ("DELETE", PIR, {"pi_name": "existing"}, 405, "POST"),
    ("PATCH", "/", None, 405, "GET"),
    # unknown paths
    ("GET", "/nothing", None, 404, "unknown path"),
    ("POST", "/platform_instance/delete", {"pi_name": "existing"}, 404, "unknown path"),
    ("GET", "/platform_instance/read/", None, 404, "unknown path"),
    ("GET", "/../etc/passwd", None, 404, "unknown path"),
    # size
    ("POST", SL, BIG, 413, "larger"),
    ("POST", SL, sl(sn_list=[dict(NODE, sn_name=f"n{i}") for i in range(257)]), 400, "more than"),
]


def raw_request(host, port, method, path, body):
    """Send one request over a raw socket (so any path and any bytes go as given); return (status, headers, body)."""
    head = f"{method} {path} HTTP/1.1\r\nHost: {host}:{port}\r\nConnection: close\r\n"
    if body is not None:
        head += f"Content-Type: application/json\r\nContent-Length: {len(body)}\r\n"
    data = head.encode("latin-1") + b"\r\n" + (body or b"")
    with socket.create_connection((host, port), timeout=10) as sock:
        sock.sendall(data)
        chunks = []
        while True:
            chunk = sock.recv(65536)
            if not chunk:
                break
            chunks.append(chunk)
    raw = b"".join(chunks)
    head, _, payload = raw.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    status = int(lines[0].split()[1])
    headers = {k.strip().lower(): v.strip() for k, v in (line.split(":", 1) for line in lines[1:])}
    return status, headers, payload


def db_digest(path):
    with open(path, "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()


@pytest.fixture
def master(procs, tmp_path):
    agent = RcmpAgent(procs, tmp_path / "master").start()
    assert agent.post(SL, {"slg_name": "used", "sn_list": [NODE]})[0] == 200
    assert agent.post(PI, {"pi_name": "existing", "pi_service_logic": "used"})[0] == 200
    return agent


def test_corpus_is_big_enough():
    assert len(CORPUS) >= 40
    assert {c[3] for c in CORPUS} == {400, 404, 405, 409, 413}


def test_error_corpus_changes_nothing(master):
    before = db_digest(master.db_path)
    reads_before = [master.get(p) for p in ("/platform_instance/read", "/service_logic/read")]
    failures = []
    for method, path, body, expected, word in CORPUS:
        payload = body if isinstance(body, bytes) or body is None else json.dumps(body).encode("utf-8")
        status, headers, raw = raw_request(master.host, master.ext_port, method, path, payload)
        try:
            answer = json.loads(raw.decode("utf-8"))
        except ValueError:
            failures.append(f"{method} {path}: not JSON: {raw[:200]!r}")
            continue
        reason = answer.get("reason")
        if status != expected or answer.get("result") != "ERROR" or set(answer) != {"result", "reason"}:
            failures.append(f"{method} {path} {body!r:.80}: got {status} {answer}, expected {expected} ERROR")
        elif not isinstance(reason, str) or word.lower() not in reason.lower():
            failures.append(f"{method} {path} {body!r:.80}: reason {reason!r} does not name {word!r}")
        elif headers.get("access-control-allow-origin") != "*":
            failures.append(f"{method} {path}: no CORS header on an error")
        elif status == 405 and "allow" not in headers:
            failures.append(f"{method} {path}: 405 without Allow")
    assert not failures, "\n".join(failures)
    assert db_digest(master.db_path) == before, "a rejected request changed the database file"
    assert [master.get(p) for p in ("/platform_instance/read", "/service_logic/read")] == reads_before
    # and the master still works
    assert master.post(SL, {"slg_name": "after_corpus"})[0] == 200


def test_huge_body_is_refused_without_buffering(master):
    before = db_digest(master.db_path)
    body = b'{"slg_name": "huge", "pad": "' + b"y" * (8 * 1024 * 1024) + b'"}'
    status, _, raw = raw_request(master.host, master.ext_port, "POST", SL, body)
    assert status == 413 and json.loads(raw)["result"] == "ERROR"
    # a chunked body over the limit (no Content-Length) is refused too
    chunk = b"z" * 4096
    data = (f"POST {SL} HTTP/1.1\r\nHost: x\r\nConnection: close\r\nTransfer-Encoding: chunked\r\n\r\n").encode()
    data += b"".join(b"%x\r\n%s\r\n" % (len(chunk), chunk) for _ in range(20)) + b"0\r\n\r\n"
    with socket.create_connection((master.host, master.ext_port), timeout=10) as sock:
        sock.sendall(data)
        answer = b""
        while True:
            part = sock.recv(65536)
            if not part:
                break
            answer += part
    assert answer.startswith(b"HTTP/1.1 413"), answer[:200]
    assert db_digest(master.db_path) == before
