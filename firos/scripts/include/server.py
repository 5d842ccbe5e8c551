"""FIROS's HTTP server: the API of CONTRACTS §3 and the broker's notifications, on one configured address.

Owns routing, JSON parsing, body size limits, who may edit the whitelist, and the mapping of errors to answers in
one place (`ApiError` → its status, any other exception → 500 logged); handlers stay a few lines calling the
bridge.

Bounded (docs/SECURITY.md, "FIROS"): a fixed pool of worker threads serves connections from a bounded queue;
beyond it, and beyond a few connections per client address, a connection gets a short 503 and is closed. Every
request must arrive whole within a deadline (a slow client is cut, without a traceback); JSON nested deeper than
a parser can follow is a 400. The whitelist-editing endpoints (and connect/disconnect) answer only requests from
this machine, or, when `server.admin_token` is configured, only requests carrying it; requests from web pages
(an `Origin` header) never. Bodies must be JSON (`application/json` or `application/ld+json`), so that a web page
cannot post to FIROS without a CORS preflight, which FIROS does not grant.
"""

import collections
import hmac
import io
import ipaddress
import json
import logging
import queue
import re
import socket
import threading
import time
from http.server import BaseHTTPRequestHandler, HTTPServer

from include.bridge import ApiError

log = logging.getLogger("firos.server")

MAX_BODY = 1 << 20
WORKERS = 16                # threads serving connections
QUEUE_LIMIT = 32            # accepted connections waiting for a worker
PER_CLIENT = 8              # connections of one client address, waiting or served
REQUEST_DEADLINE = 10.0     # seconds for a request to arrive whole (also the keep-alive idle time)
JSON_TYPES = ("application/json", "application/ld+json")
BUSY = json.dumps({"result": "ERROR", "reason": "FIROS is busy: too many connections; try again"}).encode()


class _DeadlineReader(io.RawIOBase):
    """The socket's input, but every receive shares one deadline (the handler's): a client sending a byte now
    and then cannot hold a worker longer than REQUEST_DEADLINE."""

    def __init__(self, sock, handler):
        super().__init__()
        self._sock = sock
        self._handler = handler

    def readable(self):
        return True

    def readinto(self, buffer):
        remaining = self._handler.deadline - time.monotonic()
        if remaining <= 0:
            raise TimeoutError("the request did not arrive in time")
        self._sock.settimeout(remaining)
        return self._sock.recv_into(buffer)


class FirosHandler(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"
    server_version = "FIROS/1.0"
    disable_nagle_algorithm = True   # headers and body are two writes: without this, delayed ACKs add 40 ms
    timeout = REQUEST_DEADLINE
    firos = None            # set on the subclass made by make_servers
    admin_token = None      # server.admin_token: whitelist edits need it (from anywhere) when set
    stats = None
    deadline = 0.0

    def setup(self):
        super().setup()
        plain, self.rfile = self.rfile, io.BufferedReader(_DeadlineReader(self.connection, self), 65536)
        plain.close()   # else the socket's file count keeps it open after the connection ends

    def handle_one_request(self):
        self.deadline = time.monotonic() + REQUEST_DEADLINE
        super().handle_one_request()

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

    # (method, path, handler, admin): admin routes change what FIROS maps and are for the operator only
    ROUTES = [
        ("GET", re.compile(r"^/robots/?$"), "robots", False),
        ("GET", re.compile(r"^/robot/(?P<name>[^/]+)/?$"), "robot", False),
        ("POST", re.compile(r"^/robot/connect/?$"), "connect", True),
        ("POST", re.compile(r"^/robot/disconnect/(?P<name>[^/]+)/?$"), "disconnect", True),
        ("POST", re.compile(r"^/whitelist/write/?$"), "whitelist_write", True),
        ("POST", re.compile(r"^/whitelist/remove/?$"), "whitelist_remove", True),
        ("POST", re.compile(r"^/whitelist/restore/?$"), "whitelist_restore", True),
        ("POST", re.compile(r"^/firos/?$"), "notification", False),
        ("GET", re.compile(r"^/stats/?$"), "get_stats", False),
    ]

    def _dispatch(self, method):
        path = self.path.split("?", 1)[0]
        try:
            route, match, allowed = None, None, []
            for route_method, pattern, handler, admin in self.ROUTES:
                found = pattern.match(path)
                if found:
                    if route_method == method:
                        route, match = (handler, admin), found
                        break
                    allowed.append(route_method)
            if route is not None and route[1]:
                self._authorize_admin()
            body = self._read_body()
            if route is not None:
                status, answer = getattr(self, "h_" + route[0])(body, **match.groupdict())
                return self._send(status, answer)
            if allowed:
                raise ApiError(405, f"{method} is not allowed on {path[:200]}; use "
                                    f"{', '.join(sorted(set(allowed)))}")
            raise ApiError(404, f"no such resource: {path[:200]}")
        except ApiError as exc:
            self._send(exc.status, {"result": "ERROR", "reason": exc.reason})
        except Exception:
            log.exception("internal error answering %s %s", method, path[:200])
            self._send(500, {"result": "ERROR", "reason": "internal error in FIROS (see its log)"})

    def _authorize_admin(self):
        """Whitelist edits: never from a web page; with a token, only with it; without, only from this machine."""
        if self.headers.get("Origin") is not None:
            self.close_connection = True
            raise ApiError(403, "FIROS does not accept whitelist or robot changes from web pages")
        if self.admin_token:
            given = self.headers.get("Authorization") or ""
            scheme, _, token = given.partition(" ")
            if scheme.lower() != "bearer" or not hmac.compare_digest(token.strip().encode(),
                                                                      self.admin_token.encode()):
                self.close_connection = True
                raise ApiError(401, "this needs the header 'Authorization: Bearer <server.admin_token>'")
            return
        if not self._client_is_local():
            self.close_connection = True
            raise ApiError(403, "whitelist and robot changes are accepted only from the machine FIROS runs on "
                                "(or with server.admin_token)")

    def _client_is_local(self):
        """True when the peer is this machine: a loopback address, or the very address it connected to."""
        peer = self.client_address[0]
        try:
            if ipaddress.ip_address(peer).is_loopback:
                return True
            return peer == self.connection.getsockname()[0]
        except (ValueError, OSError):
            return False

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
        if size == 0:
            return b""
        content_type = (self.headers.get("Content-Type") or "").split(";")[0].strip().lower()
        if content_type not in JSON_TYPES:
            self.close_connection = True
            raise ApiError(415, "bodies must be JSON with Content-Type: application/json")
        try:
            body = self.rfile.read(size)
        except OSError:
            body = b""
        if len(body) < size:
            self.close_connection = True
            raise ApiError(408, f"the body did not arrive within {REQUEST_DEADLINE:g} s")
        return body

    def _json(self, body, required=True):
        if not body.strip():
            if required:
                raise ApiError(400, "a JSON body is required")
            return None
        try:
            return json.loads(body.decode("utf-8"))
        except RecursionError:
            raise ApiError(400, "body is not acceptable JSON: nested too deeply") from None
        except (ValueError, UnicodeDecodeError) as exc:
            raise ApiError(400, f"body is not valid JSON: {exc}") from None

    def _send(self, status, answer):
        data = json.dumps(answer).encode("utf-8")
        try:
            self.connection.settimeout(REQUEST_DEADLINE)
            self.send_response(status)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(data)))
            if self.close_connection:
                self.send_header("Connection", "close")
            self.end_headers()
            self.wfile.write(data)
        except OSError:   # the client went away or does not read: nothing more to say to it
            self.close_connection = True

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


class WorkerPool:
    """A fixed number of threads serving accepted connections from a bounded queue, shared by FIROS's listeners;
    it also counts the connections of each client address."""

    def __init__(self, workers=WORKERS, queue_limit=QUEUE_LIMIT, per_client=PER_CLIENT):
        self.per_client = per_client
        self._waiting = queue.Queue(maxsize=queue_limit)
        self._clients = collections.Counter()
        self._lock = threading.Lock()
        self._threads = [threading.Thread(target=self._work, name=f"firos-http-{i}", daemon=True)
                         for i in range(workers)]
        for thread in self._threads:
            thread.start()

    def submit(self, server, request, client_address):
        """Queue a connection; False when the pool or this client is full (the caller refuses it)."""
        client = client_address[0]
        with self._lock:
            if self._clients[client] >= self.per_client:
                return False
            self._clients[client] += 1
        try:
            self._waiting.put_nowait((server, request, client_address))
            return True
        except queue.Full:
            self._release(client)
            return False

    def held(self):
        """Connections the pool holds now: at a worker or waiting for one."""
        with self._lock:
            return sum(self._clients.values())

    def waiting(self):
        """Connections waiting for a worker."""
        return self._waiting.qsize()

    def _release(self, client):
        with self._lock:
            self._clients[client] -= 1
            if self._clients[client] <= 0:
                del self._clients[client]

    def _work(self):
        while True:
            item = self._waiting.get()
            if item is None:
                return
            server, request, client_address = item
            try:
                server.finish_request(request, client_address)
            except Exception as exc:  # a client that vanished mid-answer: not worth a traceback
                log.debug("connection from %s ended: %s", client_address[0], exc)
            finally:
                server.shutdown_request(request)
                self._release(client_address[0])

    def close(self):
        for _ in self._threads:
            try:
                self._waiting.put(None, timeout=1.0)
            except queue.Full:
                break


class FirosHTTPServer(HTTPServer):
    """One listening address; its connections are served by the shared ``WorkerPool``, so the number of threads
    stays fixed whatever the clients do."""

    allow_reuse_address = True
    request_queue_size = 128        # the listen backlog: a burst of connections waits for the accept loop

    def __init__(self, address, handler, pool):
        if ":" in address[0]:
            self.address_family = socket.AF_INET6
        self.pool = pool
        super().__init__(address, handler)

    def process_request(self, request, client_address):
        if not self.pool.submit(self, request, client_address):
            self._refuse(request)

    def _refuse(self, request):
        try:
            request.settimeout(0.2)
            request.sendall(b"HTTP/1.1 503 Service Unavailable\r\nContent-Type: application/json\r\n"
                            b"Retry-After: 1\r\nConnection: close\r\nContent-Length: "
                            + str(len(BUSY)).encode() + b"\r\n\r\n" + BUSY)
        except OSError:
            pass
        self.shutdown_request(request)


def make_servers(firos, port, hosts, admin_token=None, pool=None):
    """One server per address in ``hosts`` (never a wildcard unless configured so), sharing one worker pool;
    OSError names the address that cannot be bound (the servers already made are closed)."""
    handler = type("BoundFirosHandler", (FirosHandler,), {"firos": firos, "admin_token": admin_token})
    pool = pool or WorkerPool()
    servers = []
    try:
        for host in hosts:
            try:
                servers.append(FirosHTTPServer((host, port), handler, pool))
            except OSError as exc:
                raise OSError(exc.errno, f"{host}:{port}: {exc.strerror}") from None
    except OSError:
        for server in servers:
            server.server_close()
        pool.close()
        raise
    return servers


def close_servers(servers):
    """Stop serving (each was started with serve_in_thread) and stop the shared pool."""
    for server in servers:
        server.shutdown()
        server.server_close()
    if servers:
        servers[0].pool.close()


def serve_in_thread(server):
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.2},
                              name="firos-http", daemon=True)
    thread.start()
    return thread
