"""FIROS under attack: each test does what a probe did (issue 12 rows 4, 5, 11, 12 and FIROS's half of 13; issue 18
rows 4, 7 and 9), as an attacker would, and asserts the safe outcome. Real ROS master, stand-in broker, FIROS child
and HTTP on loopback; the remote attacker of issue 12 row 4 and the broker turned against FIROS's administration
(issue 18 row 7) stand on hosts of a test LAN (network namespaces).
"""

import json
import os
import socket
import threading
import time

import pytest

from tests.ngsi_broker.testing import start_broker
from tests.support.firos import Firos, received, request, talker, write_config
from tests.support.polling import wait_until
from tests.support.processes import ProcessGroup
from tests.support.rosmaster import RosMaster

pytestmark = pytest.mark.slow   # real ROS master, broker and FIROS children

ATTACKER = "127.0.0.2"          # another loopback address: a client that is not the tests' own
SLOW_CLIENTS = 400


def command(robot, attr, msg_type, value):
    """A v2 notification as the broker would send it, commanding ``attr`` of ``robot``."""
    return {"subscriptionId": "0" * 24, "data": [{
        "id": robot, "type": "ROBOT", attr: {"type": msg_type, "value": value, "metadata": {}},
        "COMMAND": {"type": "COMMAND", "value": [attr], "metadata": {}}}]}


def raw_request(port, data, host="127.0.0.1", source=None, timeout=10.0):
    """Send raw bytes, return everything answered until the server closes (or the timeout)."""
    sock = socket.create_connection((host, port), timeout=timeout,
                                    source_address=(source, 0) if source else None)
    try:
        sock.sendall(data)
        chunks = []
        while True:
            chunk = sock.recv(65536)
            if not chunk:
                break
            chunks.append(chunk)
            if b"\r\n\r\n" in b"".join(chunks) and _complete(b"".join(chunks)):
                break
        return b"".join(chunks)
    finally:
        sock.close()


def _complete(answer):
    head, _, body = answer.partition(b"\r\n\r\n")
    for line in head.split(b"\r\n"):
        if line.lower().startswith(b"content-length:"):
            return len(body) >= int(line.split(b":", 1)[1])
    return False


def threads_of(pid):
    return len(os.listdir(f"/proc/{pid}/task"))


def rss_kib(pid):
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    raise AssertionError("no VmRSS")


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    """One ROS master, broker and FIROS for the loopback attacks; a peer publishes s1 and listens on p1."""
    tmp = tmp_path_factory.mktemp("firos-security")
    (tmp / "logs").mkdir()
    group = ProcessGroup(log_dir=str(tmp / "logs"))
    try:
        master = RosMaster(group).start()
        broker = start_broker(group)
        config = write_config(str(tmp / "config"), broker.port)
        peer = talker(group, master, tmp, "--rate", "5", "--pub", "/end_end_test/s1", "std_msgs/String",
                      json.dumps({"data": "hello"}), "--sub", "/end_end_test/p1", "std_msgs/String")
        firos = Firos(group, master, config).start()
        wait_until(lambda: "p1" in {t["name"] for t in firos.robots().get("end_end_test", {}).get("topics", [])},
                   timeout=20, message="end_end_test connected with p1")
        yield type("Stack", (), {"group": group, "master": master, "broker": broker, "firos": firos,
                                 "peer": peer, "tmp": tmp})
    finally:
        group.stop_all()


def whitelist_now(firos):
    status, body = firos.admin("/whitelist/write", {})
    assert status == 200, body
    return body["reason"]


# --- row 5: a regex that backtracks exponentially -----------------------------------------------------------------

@pytest.mark.parametrize("pattern", ["(a|a)*b", "(a+)+b", "(a*)*b", "(x)\\1", ".*a.*b.*c", "a" * 300])
def test_row5_catastrophic_whitelist_patterns_are_refused_and_change_nothing(stack, pattern):
    before = whitelist_now(stack.firos)
    status, body = stack.firos.admin("/whitelist/write", {"end_end_test": {"publisher": [pattern]}})
    assert status == 400, body
    assert body["result"] == "ERROR" and ("refused" in body["reason"] or "longer than" in body["reason"]), body
    assert whitelist_now(stack.firos) == before


def test_row5_an_attribute_of_27_a_costs_nothing(stack):
    # the probe's attribute; with (a|a)*b refused above, matching it is a plain lookup: the answer comes at once
    started = time.monotonic()
    status, body = request(stack.firos.port, "POST", "/firos",
                           command("end_end_test", "a" * 27, "std_msgs.msg.String", {"data": "x"}), timeout=5)
    assert status == 200 and body["reason"] == {}, body
    assert time.monotonic() - started < 5
    assert stack.firos.get("/robots")[0] == 200


def test_row5_a_catastrophic_pattern_in_whitelist_json_stops_firos_with_one_line(procs, ros_master, tmp_path):
    config = write_config(str(tmp_path / "config"), 9, whitelist={"robot\\w+": {"publisher": ["(a|a)*b"]}})
    proc = procs.start(["/usr/bin/rosrun", "firos", "core.py", "-P", "1", "--config", config],
                       env=ros_master.env({"ROS_LOG_DIR": str(tmp_path / "roslog")}), name="firos-bad")
    wait_until(lambda: proc.poll() is not None, timeout=20, message="FIROS to refuse its whitelist")
    assert proc.returncode == 1
    output = procs.output(proc).strip()
    assert output.count("\n") == 0 and "whitelist.json" in output and "(a|a)*b" in output, output


# --- row 4: commands only on the ROS graph's topics, with their own type ------------------------------------------

def test_row4_a_command_uses_the_topics_own_type_never_the_callers(stack):
    status, body = request(stack.firos.port, "POST", "/firos",
                           command("end_end_test", "p1", "geometry_msgs.msg.Twist", {"linear": {"x": 9.0}}))
    assert status == 400 and "std_msgs.msg.String" in body["reason"], body
    # a topic nobody uses and that whitelist.json does not name is never created, whatever type is given
    status, body = request(stack.firos.port, "POST", "/firos",
                           command("end_end_test", "cmd_vel", "geometry_msgs.msg.Twist", {"linear": {"x": 9.0}}))
    assert status == 200 and body["reason"] == {}, body
    assert "/end_end_test/cmd_vel" not in dict(stack.master.topic_types())
    status, body = request(stack.firos.port, "POST", "/firos",
                           command("end_end_test", "p1", "std_msgs.msg.String", {"data": "legit"}))
    assert status == 200 and body["reason"] == {"end_end_test": ["p1"]}, body
    wait_until(lambda: {"data": "legit"} in received(stack.group, stack.peer, "/end_end_test/p1"), timeout=15,
               message="the legitimate command on /end_end_test/p1")
    assert {"linear": {"x": 9.0}} not in received(stack.group, stack.peer, "/end_end_test/p1")


def test_row4_whitelist_edits_from_web_pages_and_non_json_bodies_are_refused(stack):
    before = whitelist_now(stack.firos)
    status, body = request(stack.firos.port, "POST", "/whitelist/write", {"end_end_test": {"publisher": ["x"]}},
                           headers={"Origin": "http://evil.example"})
    assert status == 403, body
    answer = raw_request(stack.firos.port, b"POST /firos HTTP/1.1\r\nHost: x\r\nContent-Type: text/plain\r\n"
                                           b"Origin: http://evil.example\r\nContent-Length: 2\r\n\r\n{}")
    assert answer.startswith(b"HTTP/1.1 415 "), answer
    assert b"access-control-allow-origin" not in answer.lower()
    assert whitelist_now(stack.firos) == before


# --- row 11: unknown names are never kept --------------------------------------------------------------------------

def test_row11_300_disconnects_of_a_60kb_name_keep_nothing(stack):
    pid = stack.firos.python_pid()
    name = "x" * 60_000
    # from the network they are refused before the name is looked at; on the administration socket (someone
    # who may administer FIROS, or a script gone wrong) each is a 400 and nothing about the name is kept
    assert request(stack.firos.port, "POST", f"/robot/disconnect/{name}")[0] == 403

    def attack():
        for _ in range(300):
            status, body = stack.firos.admin(f"/robot/disconnect/{name}")
            assert status == 400 and len(body["reason"]) < 300, (status, str(body)[:300])

    attack()                 # warm-up: the allocator's high-water mark for such requests is reached
    before = rss_kib(pid)
    attack()
    attack()
    grown = rss_kib(pid) - before
    # before the fix each round of 300 kept 18 MB for good (36 MB here); the allocator's noise is a few MB
    assert grown < 12 * 1024, f"FIROS kept {grown} KiB after 600 refused disconnects"
    assert stack.firos.admin("/robot/disconnect/nobody")[0] == 404
    assert stack.firos.get("/robots")[0] == 200


# --- row 13 (FIROS's half): deeply nested JSON --------------------------------------------------------------------

@pytest.mark.parametrize("path", ["/firos", "/whitelist/write", "/robot/connect"])
def test_row13_deeply_nested_json_is_a_400_and_firos_keeps_serving(stack, path):
    send = stack.firos.post if path == "/firos" else stack.firos.admin
    status, body = send(path, raw=b"[" * 100_000 + b"]" * 100_000)
    assert status == 400 and body["result"] == "ERROR" and "nested" in body["reason"], body
    assert stack.firos.get("/robots")[0] == 200


# --- row 12: slow clients ------------------------------------------------------------------------------------------

def test_row12_400_slow_clients_get_no_thread_each_and_no_traceback(stack):
    pid = stack.firos.python_pid()
    baseline = threads_of(pid)
    slow = []
    try:
        for _ in range(SLOW_CLIENTS):
            sock = socket.create_connection(("127.0.0.1", stack.firos.port), timeout=20,
                                            source_address=(ATTACKER, 0))
            sock.sendall(b"POST /firos HTTP/1.1\r\nHost: x\r\n")    # and then nothing more
            slow.append(sock)
        assert threads_of(pid) <= baseline + 4, (threads_of(pid), baseline)   # 412 before the fix
        # everyone else is still served while the slow clients hang
        assert stack.firos.get("/robots")[0] == 200
        # every slow client is answered (503 at once beyond the caps) or cut (at the request deadline)
        answers = []
        for sock in slow:
            data = b""
            try:
                while True:
                    chunk = sock.recv(4096)
                    if not chunk:
                        break
                    data += chunk
            except (ConnectionResetError, TimeoutError):
                pass
            answers.append(data)
        refused = [a for a in answers if a.startswith(b"HTTP/1.1 503 ")]
        assert len(refused) >= SLOW_CLIENTS - 40, len(refused)
        assert all(a == b"" or a.startswith((b"HTTP/1.1 503 ", b"HTTP/1.1 408 ")) for a in answers), \
            {a[:40] for a in answers}
        assert b"Traceback" not in answers[0] and all(b" 500 " not in a[:20] for a in answers)
    finally:
        for sock in slow:
            sock.close()
    assert threads_of(pid) <= baseline + 4
    assert stack.firos.get("/robots")[0] == 200
    assert "Traceback" not in stack.firos.output()


# --- issue 18 row 4: keep-alive connections trickling requests ---------------------------------------------------

REQUEST = b"GET /robots HTTP/1.1\r\nHost: firos\r\n\r\n"


def read_answer(sock):
    """(status, headers as a lower-case dict) of one answer on a kept-alive connection; (None, {}) when closed."""
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = sock.recv(65536)
        if not chunk:
            return None, {}
        data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    headers = {k.strip().lower(): v.strip() for k, _, v in (line.partition(":") for line in lines[1:])}
    length = int(headers.get("content-length", 0))
    while len(body) < length:
        chunk = sock.recv(65536)
        if not chunk:
            break
        body += chunk
    return int(lines[0].split()[1]), headers


def test_issue18_row4_keepalive_connections_trickling_requests_leave_the_broker_its_workers(stack):
    """16 keep-alive connections from two addresses, one small request every 8 s each (the probe's attack, which
    held every worker for as long as it went on): each address keeps its share of 4, the broker's notification
    (from its own address) and another client are served meanwhile, and every held connection is closed at its
    lifetime."""
    held, refused = [], 0
    for number in range(16):
        sock = socket.create_connection(("127.0.0.1", stack.firos.port), timeout=15,
                                        source_address=(("127.0.0.2", "127.0.0.3")[number % 2], 0))
        sock.sendall(REQUEST)
        status, headers = read_answer(sock)
        if status == 200 and headers.get("connection") != "close":
            held.append(sock)
        else:
            assert status == 503, (status, headers)
            refused += 1
            sock.close()
    assert (len(held), refused) == (8, 8)
    opened = time.monotonic()
    closed_after = {}
    stop = threading.Event()

    def trickle(sock):                     # the attacker's pace: one request every 8 s until FIROS hangs up
        while not stop.wait(8.0):
            try:
                sock.sendall(REQUEST)
                status, headers = read_answer(sock)
            except OSError:
                status, headers = None, {}
            if status is None or headers.get("connection") == "close":
                closed_after[sock] = time.monotonic() - opened
                return
    threads = [threading.Thread(target=trickle, args=(sock,), daemon=True) for sock in held]
    for thread in threads:
        thread.start()
    try:
        # while they hold their share: a command through the broker (its notification comes from the broker's
        # address, 127.0.0.1) reaches the robot, and a client from a third address is served
        before = len(received(stack.group, stack.peer, "/end_end_test/p1"))
        status, _ = request(stack.broker.port, "POST", "/v2/op/update?options=forcedUpdate", {
            "actionType": "append", "entities": [{
                "id": "end_end_test", "type": "ROBOT",
                "p1": {"type": "std_msgs.msg.String", "value": {"data": "while held"}},
                "COMMAND": {"type": "COMMAND", "value": ["p1"]}}]})
        assert status == 204
        wait_until(lambda: len(received(stack.group, stack.peer, "/end_end_test/p1")) > before, timeout=8,
                   message="the broker's command while the attacker holds its share")
        other = socket.create_connection(("127.0.0.1", stack.firos.port), timeout=8, source_address=("127.0.0.4", 0))
        other.sendall(REQUEST)
        assert read_answer(other)[0] == 200
        other.close()
        assert time.monotonic() - opened < 8, "the checks above must run while the connections are held"
        # the total deadline: each is closed after the first answer at 20 s or more (30 s lifetime - 10 s deadline)
        for thread in threads:
            thread.join(45)
        assert len(closed_after) == 8 and all(20 <= after < 35 for after in closed_after.values()), closed_after
    finally:
        stop.set()
        for sock in held:
            sock.close()
    assert stack.firos.get("/robots")[0] == 200


# --- issue 18 row 9: a whitelisted topic absent from the ROS graph, with a type the caller chose --------------------

def test_issue18_row9_a_topic_absent_from_the_graph_is_not_created_with_the_callers_type(stack):
    assert stack.firos.admin("/whitelist/write", {"end_end_test": {"publisher": ["goal"]}})[0] == 200
    try:
        note = command("end_end_test", "goal", "geometry_msgs.msg.PoseStamped", {"pose": {"position": {"x": 9.0}}})
        for _ in range(50):
            status, body = request(stack.firos.port, "POST", "/firos", note)
            assert status == 200 and body["reason"] == {}, body
        assert "/end_end_test/goal" not in dict(stack.master.topic_types())       # no publisher was made
        said = [line for line in stack.firos.output().splitlines()
                if "'/end_end_test/goal' is not in the ROS graph" in line]
        assert 1 <= len(said) <= 10, said                                       # through the budget
    finally:
        stack.firos.admin("/whitelist/remove", {"end_end_test": {"publisher": ["goal"]}})


def test_a_flood_of_refused_requests_leaves_firos_log_its_evidence(stack):
    before = stack.firos.output()
    for number in range(300):
        path = "/" + "x" * 16000 if number % 2 else "/whitelist/restore"
        request(stack.firos.port, "POST", path, body={})
    new = stack.firos.output()[len(before):].splitlines()
    # at most a budget's worth (an earlier flood of this module may still hold the window), each line short; the
    # request lines FIROS writes at DEBUG have a budget too
    about = [line for line in new if "answered 404" in line or "refused POST" in line]
    assert len(about) <= 10 and len(new) <= 40 and all(len(line) < 1000 for line in new), (len(new), new[:3])
    assert stack.firos.get("/robots")[0] == 200


# --- where FIROS listens, and the admin token ------------------------------------------------------------------------

def test_server_address_and_admin_token(procs, ros_master, tmp_path):
    broker = start_broker(procs)
    token = "s3cret-token-for-firos-tests"
    config = write_config(str(tmp_path / "config"), broker.port,
                          server={"port": 10100, "address": "127.0.0.3", "admin_token": token})
    firos = Firos(procs, ros_master, config)
    argv = ["/usr/bin/rosrun", "firos", "core.py", "-P", str(firos.port), "--config", config]
    firos.process = procs.start(argv, env=ros_master.env({"ROS_LOG_DIR": str(tmp_path / "roslog")}), name="firos")

    def on(host, method, path, body=None, headers=None):
        import http.client
        conn = http.client.HTTPConnection(host, firos.port, timeout=10)
        try:
            data = None if body is None else json.dumps(body).encode()
            conn.request(method, path, body=data, headers=dict({"Content-Type": "application/json"},
                                                               **(headers or {})))
            resp = conn.getresponse()
            return resp.status, json.loads(resp.read() or b"null")
        finally:
            conn.close()

    def up():
        assert firos.process.poll() is None, firos.output()
        try:
            return on("127.0.0.3", "GET", "/robots")[0] == 200
        except OSError:
            return False
    wait_until(up, timeout=20, message="FIROS on 127.0.0.3")
    with pytest.raises(ConnectionRefusedError):
        on("127.0.0.1", "GET", "/robots")
    edit = {"end_end_test": {"publisher": ["p9"]}}
    assert on("127.0.0.3", "POST", "/whitelist/write", edit)[0] == 401
    assert on("127.0.0.3", "POST", "/whitelist/write", edit, {"Authorization": "Bearer wrong-token-wrong"})[0] == 401
    assert on("127.0.0.3", "POST", "/robot/disconnect/end_end_test")[0] == 401
    status, body = on("127.0.0.3", "POST", "/whitelist/write", edit, {"Authorization": f"Bearer {token}"})
    assert status == 200 and "p9" in body["reason"]["end_end_test"]["publisher"], body
    # the broker's notifications need no token
    assert on("127.0.0.3", "POST", "/firos", {"subscriptionId": "x", "data": []})[0] == 200


# --- row 4 from another host: the probe's attacker on the same network --------------------------------------------

FIROS_PORT = 10100
REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def curl(host, method, url, body=None, headers=(), unix=None):
    """(status, JSON or text) of one request made with curl inside ``host`` (over the Unix socket ``unix``, as the
    operator does on FIROS's machine); status None when unreachable."""
    argv = ["curl", "-s", "--max-time", "5", "-o", "-", "-w", "\n%{http_code}", "-X", method]
    if unix:
        argv += ["--unix-socket", unix]
    for header in headers:
        argv += ["-H", header]
    if body is not None:
        argv += ["-H", "Content-Type: application/json", "--data-binary", json.dumps(body)]
    result = host.run(argv + [url], check=False, stderr=None)
    text, _, status = result.stdout.rpartition("\n")
    if not status.isdigit() or status == "000":
        return None, text
    try:
        return int(status), json.loads(text) if text else None
    except ValueError:
        return int(status), text


class FirosHost:
    """A machine of the test LAN running a ROS master, the stand-in broker (on the machine's own address, as a broker
    beside FIROS would be), FIROS on its address and a ROS peer publishing s1 and listening on p1."""

    def __init__(self, lan, tmp_path):
        from tests.support.processes import ros_env
        self.lan = lan
        self.host = lan.add_host("master")
        address = self.host.address
        uri = f"http://{address}:11311"
        env = ros_env({"ROS_IP": address, "ROS_LOG_DIR": str(tmp_path / "roslog")}, master_uri=uri)
        self.host.start(["/usr/bin/rosmaster", "--core", "-p", "11311"], env=env, name="rosmaster")
        self.host.start(["/usr/bin/python3", "-m", "tests.ngsi_broker", "--host", address, "--port", "1026",
                         "--quiet"], cwd=REPO, name="ngsi-broker")
        config = write_config(str(tmp_path / "config"), 1026)
        with open(os.path.join(config, "config.json")) as f:
            data = json.load(f)
        data["test"]["contextbroker"]["address"] = data["test"]["endpoint"]["address"] = address
        self.admin_socket = str(tmp_path / "admin.sock")
        data["test"]["server"] = {"port": FIROS_PORT, "admin_socket": self.admin_socket}
        with open(os.path.join(config, "config.json"), "w") as f:
            json.dump(data, f)
        wait_until(lambda: self.host.run(["/usr/bin/python3", "-c", "import xmlrpc.client,sys; xmlrpc.client."
                                          "ServerProxy(sys.argv[1]).getPid('/t')", uri], check=False).returncode == 0,
                   timeout=20, message="the ROS master in the master host")
        self.peer = self.host.start(["/usr/bin/python3", "-m", "tests.support.firos_talker", "--rate", "5",
                                     "--pub", "/end_end_test/s1", "std_msgs/String", json.dumps({"data": "hi"}),
                                     "--sub", "/end_end_test/p1", "std_msgs/String"], env=env, cwd=REPO,
                                    name="talker")
        self.firos = self.host.start(["/usr/bin/rosrun", "firos", "core.py", "-P", str(FIROS_PORT), "--config",
                                      config], env=env, name="firos")
        self.base = f"http://{address}:{FIROS_PORT}"
        self.broker = f"http://{address}:1026"

    def mapped(self, from_host):
        """True once FIROS maps end_end_test with p1, as ``from_host`` sees it."""
        assert self.firos.poll() is None, self.lan.procs.output(self.firos)
        status, body = curl(from_host, "GET", self.base + "/robots")
        return status == 200 and any(r["name"] == "end_end_test" and "p1" in {t["name"] for t in r["topics"]}
                                     for r in body)

    def received(self):
        return received(self.lan.procs, self.peer, "/end_end_test/p1")


@pytest.mark.netns
def test_row4_an_attacker_on_the_lan_cannot_change_what_firos_maps_nor_pick_a_type(lan, tmp_path):
    site = FirosHost(lan, tmp_path)
    master, attacker, base = site.host, lan.add_host("attacker"), site.base
    wait_until(lambda: site.mapped(attacker), timeout=30, message="FIROS to map end_end_test, seen from the LAN")

    # the probe: write the whitelist, disconnect, then command with a type of the attacker's choosing
    status, body = curl(attacker, "POST", base + "/whitelist/write", {"end_end_test": {"publisher": ["evil"]}})
    assert status == 403 and "administration socket" in body["reason"], body
    assert curl(attacker, "POST", base + "/whitelist/restore")[0] == 403
    assert curl(attacker, "POST", base + "/robot/disconnect/end_end_test")[0] == 403
    status, body = curl(attacker, "POST", base + "/firos",
                        command("end_end_test", "evil", "geometry_msgs.msg.Twist", {"linear": {"x": 1.0}}))
    assert status == 200 and body["reason"] == {}, body
    status, body = curl(attacker, "POST", base + "/firos",
                        command("end_end_test", "p1", "geometry_msgs.msg.Twist", {"linear": {"x": 1.0}}))
    assert status == 400, body
    # what it could not do from the LAN, nor from FIROS's own machine over TCP, the operator does on the
    # administration socket
    assert curl(master, "POST", base + "/whitelist/write", {"end_end_test": {"publisher": ["p2"]}})[0] == 403
    status, body = curl(master, "POST", "http://firos/whitelist/write", {"end_end_test": {"publisher": ["p2"]}},
                        unix=site.admin_socket)
    assert status == 200 and "p2" in body["reason"]["end_end_test"]["publisher"]
    assert "evil" not in body["reason"]["end_end_test"]["publisher"]
    # and FIROS is not on the master's other addresses
    assert curl(master, "GET", f"http://127.0.0.1:{FIROS_PORT}/robots")[0] is None
    assert curl(attacker, "POST", base + "/firos",
                command("end_end_test", "p1", "std_msgs.msg.String", {"data": "ok"}))[0] == 200
    wait_until(lambda: {"data": "ok"} in site.received(), timeout=15,
               message="the broker-shaped command on /end_end_test/p1")
    assert all("linear" not in m for m in site.received())


@pytest.mark.netns
def test_row7_a_broker_beside_firos_cannot_be_made_to_administer_it(lan, tmp_path):
    """Issue 18 row 7: the broker runs on FIROS's machine; a stranger who may use the broker (its API is FIWARE's
    public side) subscribes FIROS's own administrative URLs and makes the broker notify them. The broker's
    requests come from FIROS's machine, which FIROS took for its operator; now they reach only /firos."""
    site = FirosHost(lan, tmp_path)
    stranger = lan.add_host("stranger")
    wait_until(lambda: site.mapped(stranger), timeout=30, message="FIROS to map end_end_test")
    wait_until(lambda: curl(stranger, "GET", site.broker + "/v2/entities/end_end_test?type=ROBOT")[0] == 200,
               timeout=20, message="the robot's entity in the broker")
    whitelist = curl(site.host, "POST", "http://firos/whitelist/write", {}, unix=site.admin_socket)[1]["reason"]
    targets = ["/robot/disconnect/end_end_test", "/whitelist/restore", "/whitelist/remove", "/robot/connect"]
    for number, target in enumerate(targets):
        status, _ = curl(stranger, "POST", site.broker + "/v2/subscriptions", {
            "description": f"stranger {number}", "subject": {
                "entities": [{"id": "end_end_test", "type": "ROBOT"}], "condition": {"attrs": [f"bait{number}"]}},
            "notification": {"http": {"url": site.base + target}}})
        assert status == 201
        status, _ = curl(stranger, "POST", site.broker + "/v2/op/update", {"actionType": "append", "entities": [
            {"id": "end_end_test", "type": "ROBOT", f"bait{number}": {"type": "Number", "value": number}}]})
        assert status == 204

    def refused():
        status, subs = curl(stranger, "GET", site.broker + "/v2/subscriptions")
        ours = [sub for sub in subs if sub.get("description", "").startswith("stranger ")]
        return len(ours) == len(targets) and all(
            sub["notification"].get("lastFailureReason", "").startswith("HTTP 403") for sub in ours) and ours
    subs = wait_until(refused, timeout=20, message="the broker's notifications to be refused with 403")
    assert all(sub["notification"]["timesSent"] >= 1 for sub in subs)
    # nothing changed: the robot is connected, its entity and subscription are there, the whitelist is the same
    assert site.mapped(stranger)
    assert curl(stranger, "GET", site.broker + "/v2/entities/end_end_test?type=ROBOT")[0] == 200
    assert curl(site.host, "POST", "http://firos/whitelist/write", {},
                unix=site.admin_socket)[1]["reason"] == whitelist
    # the broker's real job still works: a command through it reaches the robot
    status, _ = curl(stranger, "POST", site.broker + "/v2/op/update", {"actionType": "append", "entities": [
        {"id": "end_end_test", "type": "ROBOT", "p1": {"type": "std_msgs.msg.String", "value": {"data": "go"}},
         "COMMAND": {"type": "COMMAND", "value": ["p1"]}}]})
    assert status == 204
    wait_until(lambda: {"data": "go"} in site.received(), timeout=15, message="the command through the broker")
    # and FIROS's log says what it refused, briefly
    output = lan.procs.output(site.firos)
    assert "refused POST '/robot/disconnect/end_end_test'" in output and "Traceback" not in output
