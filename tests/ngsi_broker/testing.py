"""Helpers for tests that use the stand-in broker: the broker as a real child process, a real HTTP server
that receives notifications, and a small HTTP client.

    broker = start_broker(procs)                 # procs: tests.support.processes.ProcessGroup (fixture)
    broker.url                                   # "http://127.0.0.1:PORT"
    with NotificationReceiver() as receiver:     # receiver.url: where subscriptions should notify
        ...
        receiver.wait_for(1)                     # polls with a deadline; returns the received notifications
    client = BrokerClient(broker.url, service="tenant")   # small HTTP client: client.post(path, body) -> Reply

The broker child listens on a port it picked itself (``--port 0``), so there is no race for a free port.
"""

import http.client
import json
import os
import re
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import urlsplit

from tests.support.polling import wait_until

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
_LISTENING = re.compile(r"ngsi_broker listening on (http://[\d.]+:(\d+))")


class BrokerProcess:
    """A running stand-in broker child: ``url``, ``host``, ``port``, ``process``."""

    def __init__(self, process, url, port, host):
        self.process = process
        self.url = url
        self.port = port
        self.host = host


def start_broker(procs, host="127.0.0.1", extra_args=(), timeout=15.0):
    """Start ``python3 -m tests.ngsi_broker`` as a child of ``procs`` and wait until it listens."""
    argv = ["/usr/bin/python3", "-m", "tests.ngsi_broker", "--host", host, "--port", "0", *extra_args]
    process = procs.start(argv, name="ngsi_broker", cwd=REPO_ROOT)

    def listening():
        if process.poll() is not None:
            raise AssertionError(f"ngsi_broker exited with {process.returncode}: {procs.output(process)}")
        return _LISTENING.search(procs.output(process))

    match = wait_until(listening, timeout=timeout, message="the stand-in broker to listen")
    return BrokerProcess(process, match.group(1), int(match.group(2)), host)


class Notification:
    """One request the receiver got: method, path, headers (case-insensitive), raw body, parsed JSON."""

    def __init__(self, method, path, headers, body):
        self.received_at = time.monotonic()
        self.method = method
        self.path = path
        self.headers = headers
        self.body = body
        try:
            self.json = json.loads(body.decode("utf-8"))
        except ValueError:
            self.json = None

    def __repr__(self):
        return f"Notification({self.method} {self.path} {self.body[:200]!r})"


class NotificationReceiver:
    """A real HTTP server on loopback that records every POST and answers ``status`` (default 200)."""

    def __init__(self, host="127.0.0.1", status=200, path="/notify"):
        self.received = []
        self.status = status
        self._lock = threading.Lock()
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"
            disable_nagle_algorithm = True

            def log_message(self, fmt, *args):
                pass

            def do_POST(self):
                length = int(self.headers.get("Content-Length") or 0)
                body = self.rfile.read(length)
                with receiver._lock:
                    receiver.received.append(Notification("POST", self.path, self.headers, body))
                self.send_response(receiver.status)
                self.send_header("Content-Length", "0")
                self.end_headers()

        self._server = ThreadingHTTPServer((host, 0), Handler)
        self._server.daemon_threads = True
        self.host, self.port = self._server.server_address[:2]
        self.url = f"http://{self.host}:{self.port}{path}"
        self._thread = threading.Thread(target=self._server.serve_forever, kwargs={"poll_interval": 0.05},
                                        daemon=True)
        self._thread.start()

    def notifications(self):
        with self._lock:
            return list(self.received)

    def wait_for(self, count, timeout=10.0):
        """Wait until at least ``count`` notifications arrived; return them all."""
        wait_until(lambda: len(self.notifications()) >= count, timeout=timeout,
                   message=f"{count} notification(s) at {self.url}")
        return self.notifications()

    def close(self):
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(timeout=5)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class Reply:
    """An HTTP answer: ``status``, ``headers`` (case-insensitive), raw ``body`` and ``json`` (None if not JSON)."""

    def __init__(self, status, headers, body):
        self.status = status
        self.headers = headers
        self.body = body
        try:
            self.json = json.loads(body.decode("utf-8")) if body else None
        except ValueError:
            self.json = None

    def __repr__(self):
        return f"Reply({self.status}, {self.body[:300]!r})"


class BrokerClient:
    """A tiny HTTP client for the broker; ``service``/``service_path`` become the FIWARE tenant headers."""

    def __init__(self, url, service=None, service_path=None, timeout=10.0):
        parts = urlsplit(url)
        self.host, self.port = parts.hostname, parts.port
        self.service = service
        self.service_path = service_path
        self.timeout = timeout

    def request(self, method, path, body=None, headers=None, raw=None, content_type="application/json"):
        """Send ``body`` as JSON (or ``raw`` bytes as they are) and return a ``Reply``."""
        all_headers = {}
        if self.service is not None:
            all_headers["Fiware-Service"] = self.service
        if self.service_path is not None:
            all_headers["Fiware-ServicePath"] = self.service_path
        data = raw if raw is not None else (json.dumps(body).encode("utf-8") if body is not None else None)
        if data is not None and content_type:
            all_headers["Content-Type"] = content_type
        all_headers.update(headers or {})
        conn = http.client.HTTPConnection(self.host, self.port, timeout=self.timeout)
        try:
            conn.request(method, path, body=data, headers=all_headers)
            response = conn.getresponse()
            return Reply(response.status, response.headers, response.read())
        finally:
            conn.close()

    def get(self, path, **kwargs):
        return self.request("GET", path, **kwargs)

    def post(self, path, body=None, **kwargs):
        return self.request("POST", path, body, **kwargs)

    def patch(self, path, body=None, **kwargs):
        return self.request("PATCH", path, body, **kwargs)

    def put(self, path, body=None, **kwargs):
        return self.request("PUT", path, body, **kwargs)

    def delete(self, path, **kwargs):
        return self.request("DELETE", path, **kwargs)
