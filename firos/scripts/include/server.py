"""FIROS's HTTP server (stdlib ThreadingHTTPServer): the API of CONTRACTS §3 and the broker's notifications.

Owns routing, JSON parsing, body size limits and the mapping of errors to answers in one place (`ApiError` →
its status, any other exception → 500 logged); handlers stay a few lines calling the bridge.
"""

import json
import logging
import re
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

from include.bridge import ApiError

log = logging.getLogger("firos.server")

MAX_BODY = 1 << 20


class FirosHandler(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"
    server_version = "FIROS/1.0"
    disable_nagle_algorithm = True   # headers and body are two writes: without this, delayed ACKs add 40 ms
    firos = None            # set on the subclass made by make_server
    stats = None

    def log_message(self, fmt, *args):
        log.debug("%s %s", self.address_string(), fmt % args)

    def do_GET(self):
        self._dispatch("GET")

    def do_POST(self):
        self._dispatch("POST")

    def do_PUT(self):
        self._dispatch("PUT")

    def do_DELETE(self):
        self._dispatch("DELETE")

    def do_PATCH(self):
        self._dispatch("PATCH")

    ROUTES = [
        ("GET", re.compile(r"^/robots/?$"), "robots"),
        ("GET", re.compile(r"^/robot/(?P<name>[^/]+)/?$"), "robot"),
        ("POST", re.compile(r"^/robot/connect/?$"), "connect"),
        ("POST", re.compile(r"^/robot/disconnect/(?P<name>[^/]+)/?$"), "disconnect"),
        ("POST", re.compile(r"^/whitelist/write/?$"), "whitelist_write"),
        ("POST", re.compile(r"^/whitelist/remove/?$"), "whitelist_remove"),
        ("POST", re.compile(r"^/whitelist/restore/?$"), "whitelist_restore"),
        ("POST", re.compile(r"^/firos/?$"), "notification"),
        ("GET", re.compile(r"^/stats/?$"), "get_stats"),
    ]

    def _dispatch(self, method):
        path = self.path.split("?", 1)[0]
        try:
            body = self._read_body()
            allowed = []
            for route_method, pattern, handler in self.ROUTES:
                match = pattern.match(path)
                if match:
                    if route_method == method:
                        status, answer = getattr(self, "h_" + handler)(body, **match.groupdict())
                        return self._send(status, answer)
                    allowed.append(route_method)
            if allowed:
                raise ApiError(405, f"{method} is not allowed on {path}; use {', '.join(sorted(set(allowed)))}")
            raise ApiError(404, f"no such resource: {path}")
        except ApiError as exc:
            self._send(exc.status, {"result": "ERROR", "reason": exc.reason})
        except Exception:
            log.exception("internal error answering %s %s", method, path)
            self._send(500, {"result": "ERROR", "reason": "internal error in FIROS (see its log)"})

    def _read_body(self):
        length = self.headers.get("Content-Length")
        if self.headers.get("Transfer-Encoding", "").lower() == "chunked":
            self.close_connection = True
            raise ApiError(411, "send a Content-Length; chunked bodies are not accepted")
        if not length:
            return b""
        try:
            size = int(length)
        except ValueError:
            self.close_connection = True
            raise ApiError(400, "Content-Length is not a number") from None
        if size < 0 or size > MAX_BODY:
            self.close_connection = True
            raise ApiError(413, f"body too large (limit {MAX_BODY} bytes)")
        return self.rfile.read(size)

    def _json(self, body, required=True):
        if not body.strip():
            if required:
                raise ApiError(400, "a JSON body is required")
            return None
        try:
            return json.loads(body.decode("utf-8"))
        except (ValueError, UnicodeDecodeError) as exc:
            raise ApiError(400, f"body is not valid JSON: {exc}") from None

    def _send(self, status, answer):
        data = json.dumps(answer).encode("utf-8")
        self.send_response(status)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(data)))
        self.send_header("Access-Control-Allow-Origin", "*")
        self.end_headers()
        self.wfile.write(data)

    # --- handlers ---------------------------------------------------------------------------------------------
    def h_robots(self, body):
        return 200, self.firos.list_robots()

    def h_robot(self, body, name):
        return 200, self.firos.read_robot(name)

    def h_connect(self, body):
        data = self._json(body, required=False)
        name = None
        if data is not None:
            if isinstance(data, dict) and set(data) <= {"name"}:
                name = data.get("name")
            else:
                raise ApiError(400, "connect takes no body or {\"name\": \"<robot>\"}")
            if name is not None and (not isinstance(name, str) or not name):
                raise ApiError(400, "\"name\" must be a robot name")
        robots = self.firos.connect(name)
        if name is not None and not robots:
            raise ApiError(404, f"robot {name!r} has no whitelisted topics in the ROS graph")
        return 200, {"result": "OK", "reason": robots}

    def h_disconnect(self, body, name):
        self.firos.disconnect(name)
        return 200, {"result": "OK", "reason": f"robot {name} disconnected"}

    def h_whitelist_write(self, body):
        self.firos.whitelist_write(self._json(body))
        return 200, {"result": "OK", "reason": self.firos.whitelist.snapshot()}

    def h_whitelist_remove(self, body):
        self.firos.whitelist_remove(self._json(body))
        return 200, {"result": "OK", "reason": self.firos.whitelist.snapshot()}

    def h_whitelist_restore(self, body):
        self.firos.whitelist_restore()
        return 200, {"result": "OK", "reason": self.firos.whitelist.snapshot()}

    def h_notification(self, body):
        published = self.firos.handle_notification(self._json(body))
        return 200, {"result": "OK", "reason": published}

    def h_get_stats(self, body):
        stats = self.firos.sender.snapshot_stats()
        stats["subscriptions"] = self.firos.subscriptions.ids()
        return 200, stats


class FirosHTTPServer(ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True


def make_server(firos, port, host="0.0.0.0"):
    handler = type("BoundFirosHandler", (FirosHandler,), {"firos": firos})
    return FirosHTTPServer((host, port), handler)


def serve_in_thread(server):
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.2},
                              name="firos-http", daemon=True)
    thread.start()
    return thread
