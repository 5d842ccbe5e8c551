"""Helpers for FIROS tests (owned by the FIROS tests): configuration folders, FIROS as a real child
(`rosrun firos core.py -P PORT --config DIR`, its administration socket in a short folder of its own), `rostopic`
children, a small JSON HTTP client over TCP or a Unix socket, FIROS's modules on the import path with the settings
of a written configuration, a recording HTTP server standing for a broker, and Prometheus text parsed.
"""

import http.client
import json
import os
import socket
import sys
import tempfile
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import yaml

from .polling import wait_until
from .ports import stable_free_ports

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
FIROS_SCRIPTS = os.path.join(ROOT, "firos", "scripts")

SEED_WHITELIST = {       # FIROS's config/whitelist.json: the seed's entries, and p1 with its type declared
    "turtle\\w+": {"publisher": ["cmd_vel"], "subscriber": ["pose"]},
    "robot\\w+": {"publisher": ["cmd_vel.*teleop", ".*move_base/goal", ".*move_base/cancel"],
                  "subscriber": [".*move_base/result"]},
    "end_end_test": {"publisher": [{"topic": "p1", "type": "std_msgs/String"}], "subscriber": ["s1"]},
}


def write_config(config_dir, broker_port, version="v2", whitelist=None, descriptions=None, **extra):
    """Write config.json (environment "test"), whitelist.json and robotdescriptions.json into config_dir."""
    os.makedirs(config_dir, exist_ok=True)
    block = {"server": {"port": 10100},
             "contextbroker": {"address": "127.0.0.1", "port": broker_port,
                               "subscription": {"throttling": 0, "subscription_length": 60,
                                                "subscription_refresh_delay": 30}},
             "endpoint": {"address": "127.0.0.1"},
             "log_level": "DEBUG", "ngsi_version": version, "discovery_interval": 0.2,
             "retry_max_delay": 0.5}
    block.update(extra)
    with open(os.path.join(config_dir, "config.json"), "w") as f:
        json.dump({"environment": "test", "test": block}, f, indent=2)
    with open(os.path.join(config_dir, "whitelist.json"), "w") as f:
        json.dump(SEED_WHITELIST if whitelist is None else whitelist, f, indent=2)
    with open(os.path.join(config_dir, "robotdescriptions.json"), "w") as f:
        json.dump(descriptions or {}, f, indent=2)
    return config_dir


def import_firos():
    """Put FIROS's scripts folder on the import path (its modules are ``core`` and ``include.*``)."""
    if FIROS_SCRIPTS not in sys.path:
        sys.path.insert(0, FIROS_SCRIPTS)


def settings_for(config_dir, broker_port, version="v2", **extra):
    """FIROS's ``Settings`` from a configuration written by ``write_config`` into ``config_dir``."""
    import_firos()
    from include.config import load_settings
    write_config(str(config_dir), broker_port, version=version, **extra)
    return load_settings(str(config_dir))


class RecordingBroker:
    """A real HTTP server on loopback that records each request as (client port, path, body) and answers it with
    ``answer(index, method, path, body) -> (status, JSON body or None)``; by default 500 to the first
    ``failures`` requests and 204 afterwards (a broker in trouble, then well)."""

    def __init__(self, failures=0, answer=None):
        self.requests = []
        self.failures = failures
        self.answer = answer or (lambda index, method, path, body: (500 if index < failures else 204, None))
        recorder = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def log_message(self, *args):
                pass

            def _record(self):
                length = int(self.headers.get("Content-Length") or 0)
                body = json.loads(self.rfile.read(length)) if length else None
                recorder.requests.append((self.client_address[1], self.path, body))
                status, answer = recorder.answer(len(recorder.requests) - 1, self.command, self.path, body)
                data = b"" if answer is None else json.dumps(answer).encode()
                self.send_response(status)
                if data:
                    self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data)

            do_GET = do_POST = do_PATCH = do_DELETE = _record

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.port = self.httpd.server_address[1]
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def close(self):
        self.httpd.shutdown()
        self.httpd.server_close()


class UnixHTTPConnection(http.client.HTTPConnection):
    """HTTP over a Unix socket, as ``curl --unix-socket PATH http://firos/...`` speaks it."""

    def __init__(self, path, timeout=10.0):
        super().__init__("firos", timeout=timeout)
        self.socket_path = path

    def connect(self):
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.settimeout(self.timeout)
        self.sock.connect(self.socket_path)


def request(port, method, path, body=None, raw=None, timeout=10.0, headers=None, unix=None):
    """(status, parsed JSON or text) of one HTTP request to 127.0.0.1:port, or to the Unix socket ``unix``."""
    conn = UnixHTTPConnection(unix, timeout) if unix else http.client.HTTPConnection("127.0.0.1", port,
                                                                                    timeout=timeout)
    try:
        data = raw if raw is not None else (None if body is None else json.dumps(body).encode())
        hdrs = {"Content-Type": "application/json"} if data is not None else {}
        hdrs.update(headers or {})
        conn.request(method, path, body=data, headers=hdrs)
        resp = conn.getresponse()
        text = resp.read().decode("utf-8", "replace")
    finally:
        conn.close()
    try:
        return resp.status, json.loads(text)
    except ValueError:
        return resp.status, text


class Firos:
    """A FIROS child process on its own HTTP port."""

    def __init__(self, procs, master, config_dir, port=None, name="firos"):
        self.procs = procs
        self.master = master
        self.config_dir = config_dir
        self.port = port or stable_free_ports(1)[0]
        self.name = name
        self.process = None
        self.admin_socket = self._admin_socket_in_config()

    def _admin_socket_in_config(self):
        """The configured server.admin_socket, or one written into config.json: in the configuration folder, or
        in a folder of its own under /tmp when that path would be too long for a Unix socket."""
        path = os.path.join(self.config_dir, "config.json")
        with open(path) as f:
            data = json.load(f)
        server = data[data["environment"]].setdefault("server", {})
        if not server.get("admin_socket"):
            socket_path = os.path.join(os.path.abspath(self.config_dir), "admin.sock")
            if len(socket_path) > 100:
                socket_path = os.path.join(tempfile.mkdtemp(prefix="firos-admin-"), "admin.sock")
            server["admin_socket"] = socket_path
            with open(path, "w") as f:
                json.dump(data, f, indent=2)
        return server["admin_socket"]

    def start(self, timeout=20.0):
        argv = ["/usr/bin/rosrun", "firos", "core.py", "-P", str(self.port), "--config", self.config_dir]
        self.process = self.procs.start(argv, env=self.master.env({"ROS_LOG_DIR": self.config_dir + "/roslog"}),
                                        name=self.name)

        def up():
            if self.process.poll() is not None:
                raise AssertionError(f"FIROS exited with {self.process.returncode}: {self.output()}")
            return self.get("/robots")[0] == 200
        wait_until(up, timeout=timeout, message="FIROS to answer GET /robots")
        wait_until(lambda: "/firos" in self.master.nodes(), timeout=timeout, message="/firos to register")
        return self

    def output(self):
        return self.procs.output(self.process)

    def python_pid(self):
        """The pid of FIROS's python process (rosrun execs it) in the child's process group."""
        for entry in os.listdir("/proc"):
            try:
                if entry.isdigit() and os.getpgid(int(entry)) == self.process.pid:
                    with open(f"/proc/{entry}/cmdline", "rb") as f:
                        if b"core.py" in f.read():
                            return int(entry)
            except OSError:
                continue
        raise AssertionError("no FIROS process found")

    def alive(self):
        return self.process.poll() is None

    def get(self, path):
        return request(self.port, "GET", path)

    def post(self, path, body=None, raw=None):
        return request(self.port, "POST", path, body=body, raw=raw)

    def admin(self, path, body=None, raw=None, method="POST"):
        """A request on FIROS's administration socket: what the operator does on FIROS's machine."""
        return request(None, method, path, body=body, raw=raw, unix=self.admin_socket)

    def robots(self):
        status, body = self.get("/robots")
        assert status == 200, body
        return {r["name"]: r for r in body}

    def stats(self):
        return self.get("/stats")[1]


def rostopic_pub(procs, master, tmp, topic, msg_type, value, *extra, rate=None, name="rostopic_pub"):
    """Start `rostopic pub` (once with -1, latched for 3 s, or at ``rate`` Hz) as a child."""
    argv = ["/usr/bin/rostopic", "pub"] + (["-r", str(rate)] if rate else ["-1"]) + [topic, msg_type, value]
    argv += list(extra)
    return procs.start(argv, env=master.env({"ROS_LOG_DIR": str(tmp) + "/roslog"}), name=name)


def rostopic_echo(procs, master, tmp, topic, count=1, name="rostopic_echo"):
    argv = ["/usr/bin/rostopic", "echo", "-n", str(count), topic]
    return procs.start(argv, env=master.env({"ROS_LOG_DIR": str(tmp) + "/roslog"}), name=name)


def echoed_messages(procs, proc):
    """The messages a `rostopic echo` child printed so far, parsed from its YAML output."""
    text = procs.output(proc)
    docs = []
    for chunk in text.split("\n---"):
        lines = [l for l in chunk.splitlines() if l.strip() and not l.startswith("WARNING")]
        if not lines:
            continue
        try:
            doc = yaml.safe_load("\n".join(lines))
        except yaml.YAMLError:
            continue
        if isinstance(doc, dict):
            docs.append(doc)
    return docs


def v2_entity(broker, eid):
    """The broker's v2 entity ``eid`` of type ROBOT, or None."""
    status, body = request(broker.port, "GET", f"/v2/entities/{eid}?type=ROBOT")
    return body if status == 200 else None


def v2_value(broker, eid, attr):
    entity = v2_entity(broker, eid)
    return entity.get(attr) if entity else None


def talker(procs, master, tmp_path, *args, name="firos_talker"):
    """Start tests/support/firos_talker.py (see its docstring) and wait until it is ready."""
    argv = ["/usr/bin/python3", "-m", "tests.support.firos_talker", *args]
    proc = procs.start(argv, env=master.env({"ROS_LOG_DIR": str(tmp_path / "roslog")}), name=name)
    wait_until(lambda: "READY" in procs.output(proc), timeout=15, message=f"{name} to start")
    return proc


def received(procs, proc, topic):
    """The messages (dicts) a firos_talker child printed for ``topic`` so far."""
    out = []
    for line in procs.output(proc).splitlines():
        if line.startswith(f"RECV {topic} "):
            out.append(json.loads(line.split(" ", 2)[2]))
    return out


def metric_samples(text):
    """{(sample name, ((label, value), ...)): value} of a Prometheus text exposition, parsed by prometheus_client's
    own parser (sample names carry ``_total`` in every version of it)."""
    from prometheus_client.parser import text_string_to_metric_families
    found = {}
    for family in text_string_to_metric_families(text):
        for sample in family.samples:
            found[(sample[0], tuple(sorted(sample[1].items())))] = sample[2]
    return found


def wait_subscription(firos, robot):
    return wait_until(lambda: firos.stats()["subscriptions"].get(robot), timeout=10,
                      message=f"FIROS's broker subscription for {robot}")
