"""Access control of the RDAPI (CONTRACTS §10, issue 12), tried as an attacker would, against a real master.

Row 3 of issue 12 (a foreign web page provisioning with ``text/plain``), bearer tokens made with the real
``rcmp_n token`` command while the agent runs (401 / 403 / revocation / only a hash on disk), HTTPS with a
certificate made here and a real TLS client, nested JSON bodies, and the connection caps.
"""

import datetime
import http.client
import ipaddress
import json
import os
import socket
import sqlite3
import ssl
import subprocess

import pytest

from tests.support.polling import wait_until
from tests.support.rcmp_agent import PYTHON, REPO, RcmpAgent

SL = "/service_logic/provisioning"
JSON = {"Content-Type": "application/json"}
EVIL = "http://evil.example"


@pytest.fixture
def master(procs, tmp_path):
    return RcmpAgent(procs, tmp_path / "master").start()


def rcmp_token(agent, *args):
    """The real ``rcmp_n token ...`` (``python3 -m rcm_platform``) on the agent's home; returns the run."""
    return subprocess.run([PYTHON, "-m", "rcm_platform", "--home", agent.home, "token", *args],
                          capture_output=True, text=True, timeout=60, env=agent.env(), cwd=REPO)


def add_token(agent, name, role):
    done = rcmp_token(agent, "add", name, "--role", role)
    assert done.returncode == 0, done.stderr
    token = done.stdout.strip()
    assert len(token) >= 43 and "\n" not in token
    return token


def call(agent, method, path, body=None, token=None, headers=None):
    headers = dict(headers or {})
    if body is not None:
        headers.setdefault("Content-Type", "application/json")
    if token is not None:
        headers["Authorization"] = f"Bearer {token}"
    return agent.request(method, path, body, headers)


def slg_names(agent, token=None):
    status, answer, _ = call(agent, "GET", "/service_logic/read", token=token)
    assert status == 200, answer
    return {n["slg_name"] for n in answer["reason"]}


# -- row 3: a foreign page -------------------------------------------------------------------------------------

def test_foreign_page_cannot_provision(procs, tmp_path):
    master = RcmpAgent(procs, tmp_path / "master", allowed_origins="https://console.example:8443").start()
    # the attack of the issue: a "simple" cross-site request (text/plain needs no preflight)
    status, answer, headers = master.request("POST", SL, b'{"slg_name": "evil1"}',
                                             {"Content-Type": "text/plain", "Origin": EVIL})
    assert status in (403, 415) and answer["result"] == "ERROR", answer
    assert headers.get("access-control-allow-origin") != EVIL
    # the same with a form's type, and with JSON (which a browser would only send after a preflight)
    for content_type in ("application/x-www-form-urlencoded", "multipart/form-data; boundary=x",
                         "application/json"):
        status, answer, _ = master.request("POST", SL, b'{"slg_name": "evil2"}',
                                           {"Content-Type": content_type, "Origin": EVIL})
        assert status in (403, 415), (content_type, status, answer)
    status, answer, _ = master.request("POST", "/platform_instance/provisioning",
                                       b'{"pi_name": "evil_r", "pi_service_logic": "empty"}',
                                       {"Content-Type": "application/json", "Origin": EVIL})
    assert status == 403 and "allowed_origins" in answer["reason"], answer
    assert not {"evil1", "evil2"} & slg_names(master)
    assert master.get("/platform_instance/read")[1]["reason"] == []
    # the preflight a browser sends first does not offer POST to that page
    status, _, headers = master.request("OPTIONS", SL, headers={
        "Origin": EVIL, "Access-Control-Request-Method": "POST", "Access-Control-Request-Headers": "content-type"})
    assert status == 204
    assert "POST" not in headers["access-control-allow-methods"]
    assert "content-type" not in headers["access-control-allow-headers"].lower()
    # ... while reading stays allowed to any page
    status, _, headers = master.request("GET", "/service_logic/read", headers={"Origin": EVIL})
    assert status == 200 and headers["access-control-allow-origin"] == "*"
    # a listed origin may write, and its preflight says so
    friend = "https://console.example:8443"
    status, _, headers = master.request("OPTIONS", SL, headers={"Origin": friend,
                                                                "Access-Control-Request-Method": "POST"})
    assert headers["access-control-allow-origin"] == friend and "POST" in headers["access-control-allow-methods"]
    assert "origin" in headers["vary"].lower()
    status, answer, headers = master.request("POST", SL, b'{"slg_name": "friendly"}',
                                             {"Content-Type": "application/json", "Origin": friend})
    assert status == 200 and headers["access-control-allow-origin"] == friend, answer
    # and so may the RDAPI's own pages (the console): Origin equals the address the browser used
    own = f"http://{master.host}:{master.ext_port}"
    status, answer, _ = master.request("POST", SL, b'{"slg_name": "own"}',
                                       {"Content-Type": "application/json", "Origin": own})
    assert status == 200, answer
    assert {"friendly", "own"} <= slg_names(master)


def test_allowed_origins_are_validated(procs, tmp_path):
    for bad in ("*", "evil.example", "http://x.example/path", "ftp://x.example"):
        agent = RcmpAgent(procs, tmp_path / f"m{abs(hash(bad))}", allowed_origins=bad)
        agent.start(wait=False)
        wait_until(lambda: agent.process.poll() is not None, timeout=20, message="the master to refuse")
        assert agent.process.returncode == 2
        assert "allowed_origins" in agent.output() and len(agent.output().strip().splitlines()) == 1


# -- tokens ------------------------------------------------------------------------------------------------------

def test_tokens_401_403_and_revocation_while_running(master):
    # no token: the seed's open RDAPI, and the log says so once
    assert master.post(SL, {"slg_name": "before"})[0] == 200
    assert master.get("/platform_instance/read")[0] == 200
    assert master.wait_log("has no tokens").count("has no tokens") == 1

    admin = add_token(master, "ops", "admin")
    reader = add_token(master, "viewer", "read")
    assert admin != reader
    # takes effect without a restart: a known token at once, the closing of the open RDAPI within the re-read
    # interval (a second)
    assert call(master, "POST", SL, {"slg_name": "by_new_admin"}, token=admin)[0] == 200
    status, answer, headers = wait_until(lambda: (lambda r: r[0] == 401 and r)(
        call(master, "GET", "/platform_instance/read")), timeout=10, message="the RDAPI to need a token")
    assert status == 401 and answer["result"] == "ERROR" and "Bearer" in answer["reason"]
    assert headers["www-authenticate"].startswith("Bearer")
    assert headers["content-type"] == "application/json"
    for bad in ("x" * 43, admin[:-1], admin + "A", "", "a b"):
        status, answer, headers = call(master, "GET", "/service_logic/read", token=bad)
        assert status == 401 and answer["result"] == "ERROR", (bad, answer)
        assert "www-authenticate" in headers
    status, answer, _ = call(master, "GET", "/platform_instance/read", headers={"Authorization": f"Basic {admin}"})
    assert status == 401
    status, answer, _ = call(master, "POST", SL, {"slg_name": "anon"})
    assert status == 401
    # public without a token: the welcome page, and preflights
    status, page, _ = master.request("GET", "/")
    assert status == 200 and "Welcome" in page
    assert master.request("OPTIONS", SL)[0] == 204
    # a read token reads, and may not write
    assert call(master, "GET", "/service_logic/read?slg_name=before", token=reader)[0] == 200
    assert call(master, "GET", "/service_space/read?ss_name=nobody", token=reader)[0] == 404
    status, answer, headers = call(master, "POST", SL, {"slg_name": "by_reader"}, token=reader)
    assert status == 403 and "viewer" in answer["reason"] and "admin" in answer["reason"], answer
    assert 'error="insufficient_scope"' in headers["www-authenticate"]
    # an admin token does everything
    assert call(master, "POST", SL, {"slg_name": "by_admin"}, token=admin)[0] == 200
    assert call(master, "POST", "/platform_instance/provisioning", {"pi_name": "r1", "pi_service_logic": "by_admin"},
                token=admin)[0] == 200
    names = slg_names(master, token=admin)
    assert "by_admin" in names and "anon" not in names and "by_reader" not in names

    # the list names tokens and roles, never a token or its hash
    listed = rcmp_token(master, "list")
    assert listed.returncode == 0
    assert [line.split("\t")[:2] for line in listed.stdout.splitlines()] == [["ops", "admin"], ["viewer", "read"]]
    db = sqlite3.connect(master.db_path)
    stored = db.execute("SELECT name, role, sha256 FROM rdapi_token ORDER BY name").fetchall()
    db.close()
    assert [(n, r) for n, r, _ in stored] == [("ops", "admin"), ("viewer", "read")]
    assert all(len(h) == 64 and h not in listed.stdout for _, _, h in stored)
    with open(master.db_path, "rb") as f:
        raw = f.read()
    assert admin.encode() not in raw and reader.encode() not in raw

    # the same name twice, an unknown role, a bad name, an unknown name: refused with a sentence
    again = rcmp_token(master, "add", "ops", "--role", "read")
    assert again.returncode == 1 and "already exists" in again.stderr and again.stdout == ""
    assert rcmp_token(master, "add", "x", "--role", "root").returncode == 2
    bad_name = rcmp_token(master, "add", "../x", "--role", "read")
    assert bad_name.returncode == 2 and "not a valid name" in bad_name.stderr
    unknown = rcmp_token(master, "revoke", "nobody")
    assert unknown.returncode == 1 and "no token named 'nobody'" in unknown.stderr

    # revoking while it runs: refused within the re-read interval
    assert rcmp_token(master, "revoke", "viewer").returncode == 0
    wait_until(lambda: call(master, "GET", "/platform_instance/read", token=reader)[0] == 401, timeout=10,
               message="the revoked token to be refused")
    assert call(master, "GET", "/platform_instance/read", token=admin)[0] == 200

    # tokens survive a restart
    master.restart()
    assert call(master, "GET", "/platform_instance/read")[0] == 401
    assert call(master, "GET", "/platform_instance/read", token=admin)[0] == 200
    # the last token revoked: open again, and said so
    assert rcmp_token(master, "revoke", "ops").returncode == 0
    wait_until(lambda: call(master, "GET", "/platform_instance/read")[0] == 200, timeout=10,
               message="the RDAPI to be open again")


def test_token_command_refuses_a_robot_folder(procs, tmp_path):
    robot = RcmpAgent(procs, tmp_path / "robot", role="robot", name="r1", ip_master="127.0.0.1", ic_port=1)
    done = rcmp_token(robot, "add", "ops", "--role", "admin")
    assert done.returncode == 2 and "belong to the master" in done.stderr and done.stdout == ""
    assert not os.path.exists(os.path.join(robot.home, "robotics_data.db"))


def test_version_1_data_is_migrated(procs, tmp_path):
    home = tmp_path / "master"
    home.mkdir()
    RcmpAgent(procs, home)  # writes the configuration only
    db = sqlite3.connect(str(home / "robotics_data.db"))
    db.executescript("""
        CREATE TABLE schema_version (version INTEGER NOT NULL);
        INSERT INTO schema_version VALUES (1);
        CREATE TABLE service_logic (slg_name TEXT PRIMARY KEY, ss_side TEXT NOT NULL DEFAULT 'S',
            is_default INTEGER NOT NULL DEFAULT 0, created TEXT NOT NULL);
        CREATE TABLE service_node (slg_name TEXT, position INTEGER, sn_package TEXT, sn_type TEXT, sn_name TEXT,
            sn_params TEXT, sn_side TEXT, PRIMARY KEY (slg_name, position));
        CREATE TABLE service_launcher (slg_name TEXT, position INTEGER, sl_package TEXT, sl_file_launcher TEXT,
            sl_name TEXT, sl_params TEXT, sl_side TEXT, PRIMARY KEY (slg_name, position));
        CREATE TABLE platform_instance (pi_name TEXT PRIMARY KEY, slg_name TEXT, is_master INTEGER NOT NULL DEFAULT 0,
            address TEXT, inbound_open_ports TEXT NOT NULL DEFAULT '', created TEXT NOT NULL);
        CREATE TABLE connection (pi_name TEXT PRIMARY KEY, address TEXT NOT NULL, paired INTEGER NOT NULL DEFAULT 0,
            since TEXT NOT NULL);
        CREATE TABLE service_space (ss_name TEXT PRIMARY KEY, ros_master_uri TEXT, inbound_port INTEGER,
            created TEXT NOT NULL);
        INSERT INTO service_logic VALUES ('old_logic', 'S', 0, '2025-01-01 00:00:00');
    """)
    db.close()
    master = RcmpAgent(procs, home)
    assert add_token(master, "ops", "admin")
    master.start()
    assert call(master, "GET", "/service_logic/read")[0] == 401
    db = sqlite3.connect(str(home / "robotics_data.db"))
    assert db.execute("SELECT version FROM schema_version").fetchall() == [(2,)]
    db.close()


# -- HTTPS -----------------------------------------------------------------------------------------------------

def make_certificate(folder, common_name="127.0.0.1"):
    """A self-signed certificate for the IP 127.0.0.1 and its key, as PEM files; returns their paths."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)])
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
            .serial_number(x509.random_serial_number()).not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days=1))
            .add_extension(x509.SubjectAlternativeName([x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]),
                           critical=False)
            .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
            .sign(key, hashes.SHA256()))
    os.makedirs(folder, exist_ok=True)
    cert_path, key_path = os.path.join(folder, "rdapi.crt"), os.path.join(folder, "rdapi.key")
    with open(cert_path, "wb") as f:
        f.write(cert.public_bytes(serialization.Encoding.PEM))
    with open(key_path, "wb") as f:
        f.write(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                  serialization.NoEncryption()))
    return cert_path, key_path


def https(agent, cafile, method, path, body=None, headers=None):
    context = ssl.create_default_context(cafile=cafile)
    conn = http.client.HTTPSConnection(agent.host, agent.ext_port, timeout=10, context=context)
    try:
        conn.request(method, path, body=body, headers=headers or {})
        resp = conn.getresponse()
        return resp.status, resp.read().decode(), {k.lower(): v for k, v in resp.getheaders()}
    finally:
        conn.close()


def test_https_with_a_real_tls_client(procs, tmp_path):
    cert, key = make_certificate(str(tmp_path / "tls"))
    master = RcmpAgent(procs, tmp_path / "master", rdapi_tls_cert=cert, rdapi_tls_key=key)
    master.start(wait=False)
    status, page, _ = wait_until(lambda: https(master, cert, "GET", "/"), timeout=20, message="the HTTPS RDAPI")
    assert status == 200 and "Welcome" in page
    assert "RDAPI on https://" in master.log_text()
    token = add_token(master, "ops", "admin")
    status, answer, _ = https(master, cert, "POST", SL, b'{"slg_name": "over_tls"}',
                              {"Content-Type": "application/json", "Authorization": f"Bearer {token}"})
    assert status == 200, answer
    wait_until(lambda: https(master, cert, "GET", "/service_logic/read?slg_name=over_tls")[0] == 401, timeout=10,
               message="the HTTPS RDAPI to need a token")
    # a client that does not trust the certificate refuses it; plain HTTP gets no answer
    with pytest.raises(ssl.SSLCertVerificationError):
        conn = http.client.HTTPSConnection(master.host, master.ext_port, timeout=10,
                                           context=ssl.create_default_context())
        try:
            conn.request("GET", "/")
        finally:
            conn.close()
    with pytest.raises((http.client.HTTPException, OSError)):
        master.request("GET", "/platform_instance/read", timeout=5)


@pytest.mark.parametrize("problem", ["missing_key_key", "no_such_file", "wrong_key", "not_pem"])
def test_tls_problems_stop_the_master_with_one_line(procs, tmp_path, problem):
    cert, key = make_certificate(str(tmp_path / "tls"))
    other_cert, other_key = make_certificate(str(tmp_path / "other"))
    keys = {"rdapi_tls_cert": cert, "rdapi_tls_key": key}
    if problem == "missing_key_key":
        keys["rdapi_tls_key"] = None
    elif problem == "no_such_file":
        keys["rdapi_tls_cert"] = str(tmp_path / "nope.crt")
    elif problem == "wrong_key":
        keys["rdapi_tls_key"] = other_key
    else:
        with open(key, "w") as f:
            f.write("not a key\n")
    master = RcmpAgent(procs, tmp_path / "master", **keys)
    master.start(wait=False)
    wait_until(lambda: master.process.poll() is not None, timeout=20, message="the master to refuse to start")
    assert master.process.returncode == 2
    lines = master.output().strip().splitlines()
    assert len(lines) == 1 and "rdapi_tls" in lines[0], lines


# -- bodies and connections --------------------------------------------------------------------------------------

def test_nested_json_is_refused(master):
    for body in (b"[" * 30000 + b"]" * 30000,
                 b'{"slg_name": "deep", "sn_list": ' + b"[" * 5000 + b"]" * 5000 + b"}",
                 json.dumps({"slg_name": "deep", "sn_list": [[[[[[[[[[{}]]]]]]]]]]}).encode()):
        status, answer, _ = master.request("POST", SL, body, JSON)
        assert status == 400 and "nested" in answer["reason"], answer
    assert "deep" not in slg_names(master)
    assert "Traceback" not in master.log_text() and "RecursionError" not in master.log_text()
    assert master.post(SL, {"slg_name": "fine"})[0] == 200


def test_connections_from_one_address_are_capped(master):
    from rcm_platform.rcmp_ext_connector import MAX_PER_ADDRESS
    held = []
    try:
        for _ in range(MAX_PER_ADDRESS):
            held.append(socket.create_connection((master.host, master.ext_port), timeout=10))
        # the next one from the same address gets a 503 with the usual JSON error, and is closed
        with socket.create_connection((master.host, master.ext_port), timeout=10) as extra:
            answer = b""
            while chunk := extra.recv(4096):
                answer += chunk
        head, _, body = answer.partition(b"\r\n\r\n")
        assert head.startswith(b"HTTP/1.1 503") and json.loads(body)["result"] == "ERROR", answer
        # another address is still served
        conn = http.client.HTTPConnection(master.host, master.ext_port, timeout=10, source_address=("127.0.0.2", 0))
        conn.request("GET", "/platform_instance/read")
        assert conn.getresponse().status == 200
        conn.close()
    finally:
        for sock in held:
            sock.close()
    wait_until(lambda: master.get("/platform_instance/read")[0] == 200, timeout=10,
               message="the address to be served again once its connections closed")


# -- row 2: params that would become options or files of our tools -----------------------------------------------

NODE = {"sn_package": "robotics_test", "sn_type": "talker.py", "sn_name": "talker", "sn_params": "", "sn_side": "S"}
LAUNCHER = {"sl_package": "robotics_test", "sl_file_launcher": "two_talkers.launch", "sl_name": "talkers",
            "sl_params": "", "sl_side": "S"}


@pytest.mark.parametrize("field,params,expected", [
    ("sl_params", "--pid=/tmp/victim /tmp/evil.launch", "arg:=value"),
    ("sl_params", "/tmp/evil.launch", "arg:=value"),
    ("sl_params", "rate:=2 --wait", "arg:=value"),
    ("sl_params", "-p 11311", "arg:=value"),
    ("sl_params", "rate:=2 other.launch", "arg:=value"),
    ("sl_params", "__log:=/any/path", "__log:="),
    ("sl_params", "rate:=2 __master:=http://evil:11311", "__master:="),
    ("sn_params", "__log:=/any/path", "__log:="),
    ("sn_params", "--rate 2 __master:=http://evil:11311", "__master:="),
    ("sn_params", "__ip:=203.0.113.9", "__ip:="),
    ("sn_params", "'__hostname:=evil'", "__hostname:="),
])
def test_params_that_would_redirect_our_tools_are_refused(master, field, params, expected):
    item = dict(NODE if field == "sn_params" else LAUNCHER, **{field: params})
    body = {"slg_name": "attack", "sn_list" if field == "sn_params" else "sl_list": [item]}
    status, answer = master.post(SL, body)
    assert status == 400 and answer["result"] == "ERROR" and expected in answer["reason"], answer
    assert field in answer["reason"]
    assert master.get("/service_logic/read?slg_name=attack")[0] == 404


def test_params_a_program_may_have_stay_allowed(master):
    nodes = [dict(NODE, sn_name="pub", sn_package="rostopic", sn_type="rostopic",
                  sn_params="pub -r 2 /chatter std_msgs/String 'data: hi'"),
             dict(NODE, sn_name="talker", sn_params="--rate 2 'hello world' __name:=t2 __ns:=/x chatter:=other")]
    launchers = [dict(LAUNCHER, sl_params="rate:=2 greeting:='hello world' robot_name:=r1")]
    status, answer = master.post(SL, {"slg_name": "fine", "sn_list": nodes, "sl_list": launchers})
    assert status == 200, answer
    assert master.get("/service_logic/read?slg_name=fine")[1]["reason"]["sn_list"] == nodes
