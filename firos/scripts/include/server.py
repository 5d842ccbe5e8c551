"""FIROS's HTTP server: the API of docs/FIROS.md and the broker's notifications on the configured addresses, and
the same API for the operator on FIROS's administration socket.

Owns routing, JSON parsing, strict JSON answers, body size limits, who may call what, the worker pool with its
shares and deadlines, and the mapping of errors to answers in one place (`ApiError` → its status, any other
exception → 500 logged); handlers stay a few lines calling the bridge.

Who may call what (docs/SECURITY.md, "FIROS"): reads (`GET /robots`, `/robot/<name>`, `/stats`, `/metrics`) and
the broker's notifications (`POST /firos`) on every listener; the administrative calls (whitelist edits, robot
connect and disconnect) on the administration socket (a Unix socket, 0600: FIROS's own user and root; nothing a
broker can be told to notify reaches it), or over TCP only with `Authorization: Bearer <server.admin_token>` when
one is configured; never with an `Origin` header (a web page). Being on this machine proves nothing: a broker here
can be subscribed to notify any URL. Bodies must be JSON (`application/json` or `application/ld+json`), so that a
web page cannot post to FIROS without a CORS preflight, which FIROS does not grant.

Bounded: a fixed pool of worker threads serves every listener from a bounded queue. Each source address holds at
most its share of connections (the broker's addresses a larger one) and, while the broker's address is known, the
other addresses together leave some workers to it; beyond, a connection gets a short 503 and is closed. Every
request must arrive whole within REQUEST_DEADLINE (a byte now and then does not extend it), also the wait for the
next request on a kept-alive connection; a connection is closed after the first answer it gets once it is
LIFETIME − REQUEST_DEADLINE old, so none holds a worker past LIFETIME by trickling requests. What a peer sends
reaches the log cut (`log_guard.shown`) and through a budget. JSON nested deeper than a parser can follow is a 400.
"""

import collections
import errno
import hmac
import io
import json
import logging
import os
import queue
import re
import socket
import socketserver
import stat
import threading
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, HTTPServer

from include.bridge import ApiError
from include.log_guard import Budget, shown
from include.ngsi_encoding import json_safe

log = logging.getLogger("firos.server")

MAX_BODY = 1 << 20
WORKERS = 16                # threads serving connections
QUEUE_LIMIT = 32            # accepted connections waiting for a worker
PER_SOURCE = 4              # connections one source address holds (at a worker or waiting)
BROKER_SHARE = 8            # ... the broker's addresses
BROKER_RESERVE = 4          # workers the other addresses together leave to the broker's, when it is known
REQUEST_DEADLINE = 10.0     # seconds for a request to arrive whole (also the keep-alive idle time)
LIFETIME = 30.0             # seconds a connection lives at most (closed after an answer, see the docstring)
ADMIN_SOURCE = "the administration socket"   # the source of every connection on it (one share)
JSON_TYPES = ("application/json", "application/ld+json")
BUSY = json.dumps({"result": "ERROR", "reason": "FIROS is busy: too many connections; try again"}).encode()


def answer_bytes(answer):
    """Strict JSON of an answer: a float JSON cannot carry is the string "NaN", "Infinity" or "-Infinity", as
    FIROS writes such values into the broker."""
    try:
        return json.dumps(answer, allow_nan=False).encode("utf-8")
    except ValueError:
        return json.dumps(json_safe(answer), allow_nan=False).encode("utf-8")


class Tally:
    """A thread-safe count of events by key (requests by route and status)."""

    def __init__(self):
        self._counts = collections.Counter()
        self._lock = threading.Lock()

    def add(self, key):
        with self._lock:
            self._counts[key] += 1

    def snapshot(self):
        with self._lock:
            return dict(self._counts)


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
    admin_token = None      # server.admin_token: administrative calls over TCP need it
    admin_socket = None     # the administration socket's path, named in refusals
    admin_side = False      # True on the administration socket: administrative calls need nothing more
    metrics = None          # scrape() -> (content type, bytes), or ApiError 503
    notes = None            # the Budget of lines a peer can cause
    requests_log = None     # the Budget of the request lines (DEBUG)
    tally = None            # Tally of requests by (route, status)
    deadline = 0.0
    opened = 0.0

    def setup(self):
        super().setup()
        self.opened = time.monotonic()
        plain, self.rfile = self.rfile, io.BufferedReader(_DeadlineReader(self.connection, self), 65536)
        plain.close()   # else the socket's file count keeps it open after the connection ends

    def handle_one_request(self):
        self.deadline = time.monotonic() + REQUEST_DEADLINE
        super().handle_one_request()

    def address_string(self):
        return self.server.source_of(self.client_address)

    def log_request(self, code="-", size="-"):
        if log.isEnabledFor(logging.DEBUG):
            self.requests_log.log(logging.DEBUG, "%s %s %s", self.address_string(), shown(self.requestline), code)

    def log_message(self, fmt, *args):
        if log.isEnabledFor(logging.DEBUG):
            self.requests_log.log(logging.DEBUG, "%s %s", self.address_string(), shown(fmt % args))

    def send_error(self, code, message=None, explain=None):
        """http.server's own refusals (a malformed request line or headers): a JSON answer like every other,
        the connection closed, one line through the budget."""
        reason = message or HTTPStatus(code).phrase
        self.tally.add(("other", code))
        self.notes.info("answered %d to %s: %s", code, self.address_string(), shown(reason))
        self.close_connection = True
        self._send(code, {"result": "ERROR", "reason": reason})

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

    # (method, path, handler, administrative, route label for the metrics)
    ROUTES = [
        ("GET", re.compile(r"^/robots/?$"), "robots", False, "/robots"),
        ("GET", re.compile(r"^/robot/(?P<name>[^/]+)/?$"), "robot", False, "/robot/<name>"),
        ("POST", re.compile(r"^/robot/connect/?$"), "connect", True, "/robot/connect"),
        ("POST", re.compile(r"^/robot/disconnect/(?P<name>[^/]+)/?$"), "disconnect", True,
         "/robot/disconnect/<name>"),
        ("POST", re.compile(r"^/whitelist/write/?$"), "whitelist_write", True, "/whitelist/write"),
        ("POST", re.compile(r"^/whitelist/remove/?$"), "whitelist_remove", True, "/whitelist/remove"),
        ("POST", re.compile(r"^/whitelist/restore/?$"), "whitelist_restore", True, "/whitelist/restore"),
        ("POST", re.compile(r"^/firos/?$"), "notification", False, "/firos"),
        ("GET", re.compile(r"^/stats/?$"), "get_stats", False, "/stats"),
        ("GET", re.compile(r"^/metrics/?$"), "metrics", False, "/metrics"),
    ]
    ROUTE_LABELS = tuple(route[4] for route in ROUTES) + ("other",)

    def _dispatch(self, method):
        path = self.path.split("?", 1)[0]
        label, status = "other", 500
        try:
            route, match, allowed = None, None, []
            for route_method, pattern, handler, admin, route_label in self.ROUTES:
                found = pattern.match(path)
                if found:
                    label = route_label
                    if route_method == method:
                        route, match = (handler, admin), found
                        break
                    allowed.append(route_method)
            body = self._read_body()           # before any refusal: unread bytes would reset the connection
            if route is not None and route[1]:
                self._authorize_admin(method, path)
            if route is not None:
                answer = getattr(self, "h_" + route[0])(body, **match.groupdict())
                status = answer[0]
                return self._send(*answer)
            if allowed:
                raise ApiError(405, f"{method} is not allowed on {path[:200]}; use "
                                    f"{', '.join(sorted(set(allowed)))}")
            raise ApiError(404, f"no such resource: {path[:200]}")
        except ApiError as exc:
            status = exc.status
            if exc.status not in (401, 403):
                self.notes.info("answered %d to %s %s from %s: %s", exc.status, method, shown(path),
                                self.address_string(), shown(exc.reason))
            self._send(exc.status, {"result": "ERROR", "reason": exc.reason})
        except Exception:
            log.exception("internal error answering %s %s", method, shown(path))
            self._send(500, {"result": "ERROR", "reason": "internal error in FIROS (see its log)"})
        finally:
            self.tally.add((label, status))

    def _authorize_admin(self, method, path):
        """Administrative calls: never from a web page; on the administration socket, nothing more; over TCP only
        with server.admin_token, and not at all without one. Each refusal is a line through the budget."""
        refusal = None
        if self.headers.get("Origin") is not None:
            refusal, why = ApiError(403, "FIROS does not accept whitelist or robot changes from web pages"), \
                "from a web page"
        elif self.admin_side:
            return
        elif self.admin_token:
            given = self.headers.get("Authorization") or ""
            scheme, _, token = given.partition(" ")
            if scheme.lower() != "bearer" or not hmac.compare_digest(token.strip().encode(),
                                                                      self.admin_token.encode()):
                refusal, why = ApiError(401, "this needs the header 'Authorization: Bearer "
                                             "<server.admin_token>'"), "without the admin token"
        else:
            where = "over the network only with server.admin_token"
            if self.admin_socket:
                where = (f"on FIROS's administration socket ({self.admin_socket}: curl --unix-socket "
                         f"{self.admin_socket} http://firos{path[:80]}), or {where}")
            refusal, why = ApiError(403, f"whitelist and robot changes are taken {where}"), \
                "not on the administration socket"
        if refusal is not None:
            self.close_connection = True
            self.notes.warning("refused %s %s from %s (%d): %s", method, shown(path), self.address_string(),
                               refusal.status, why)
            raise refusal

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

    def _send(self, status, answer, content_type="application/json"):
        """Answer (a JSON-like ``answer``, or bytes of ``content_type``); the connection is closed afterwards when
        asked, or when it is old enough that another request might not finish within its LIFETIME."""
        data = answer if isinstance(answer, bytes) else answer_bytes(answer)
        if time.monotonic() - self.opened >= LIFETIME - REQUEST_DEADLINE:
            self.close_connection = True
        try:
            self.connection.settimeout(REQUEST_DEADLINE)
            self.send_response(status)
            self.send_header("Content-Type", content_type)
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

    def h_metrics(self, body):
        if self.metrics is None:
            raise ApiError(503, "this FIROS serves no metrics")
        content_type, data = self.metrics.scrape()
        return 200, data, content_type


class AdminHandler(FirosHandler):
    """The same API on the administration socket: administrative calls need nothing more than reaching it."""
    admin_side = True
    disable_nagle_algorithm = False     # a Unix socket has no Nagle's algorithm to disable


class WorkerPool:
    """A fixed number of threads serving accepted connections from a bounded queue, shared by FIROS's listeners;
    it counts the connections each source holds (at a worker or waiting) against its share."""

    def __init__(self, workers=WORKERS, queue_limit=QUEUE_LIMIT, per_source=PER_SOURCE, shares=None,
                 reserve=BROKER_RESERVE):
        self.workers = workers
        self.per_source = per_source
        self.shares = dict(shares or {})     # source -> its share, for the broker's addresses
        # what the sources without a share of their own may hold together: the rest is the broker's
        self.others_limit = workers - reserve if self.shares else workers + queue_limit
        self.refused = 0
        self.refusals = Budget(log, "lines about refused connections")
        self._waiting = queue.Queue(maxsize=queue_limit)
        self._sources = collections.Counter()
        self._lock = threading.Lock()
        self._threads = [threading.Thread(target=self._work, name=f"firos-http-{i}", daemon=True)
                         for i in range(workers)]
        for thread in self._threads:
            thread.start()

    def submit(self, server, request, client_address):
        """Queue a connection; False when the pool or this source is full (the caller refuses it)."""
        source = server.source_of(client_address)
        share = self.shares.get(source, self.per_source)
        with self._lock:
            others = sum(n for s, n in self._sources.items() if s not in self.shares)
            why = None
            if self._sources[source] >= share:
                why = f"it holds its share of {share} connections"
            elif source not in self.shares and others >= self.others_limit:
                why = f"the other addresses hold the {self.others_limit} connections not kept for the broker"
            if why is None:
                self._sources[source] += 1
        if why is None:
            try:
                self._waiting.put_nowait((server, request, client_address, source))
                return True
            except queue.Full:
                self._release(source)
                why = "every worker is busy and every waiting place taken"
        with self._lock:
            self.refused += 1
        self.refusals.warning("refused a connection from %s (503): %s", source, why)
        return False

    def held(self):
        """Connections the pool holds now: at a worker or waiting for one."""
        with self._lock:
            return sum(self._sources.values())

    def waiting(self):
        """Connections waiting for a worker."""
        return self._waiting.qsize()

    def _release(self, source):
        with self._lock:
            self._sources[source] -= 1
            if self._sources[source] <= 0:
                del self._sources[source]

    def _work(self):
        while True:
            item = self._waiting.get()
            if item is None:
                return
            server, request, client_address, source = item
            try:
                server.finish_request(request, client_address)
            except Exception as exc:  # a client that vanished mid-answer: not worth a traceback
                log.debug("connection from %s ended: %s", source, shown(str(exc)))
            finally:
                server.shutdown_request(request)
                self._release(source)

    def close(self):
        self.refusals.flush()
        for _ in self._threads:
            try:
                self._waiting.put(None, timeout=1.0)
            except queue.Full:
                break


class _Pooled:
    """What FIROS's listeners share: their connections go to the ``WorkerPool``, which refuses beyond a share."""

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


class FirosHTTPServer(_Pooled, HTTPServer):
    """One listening address; its connections are served by the shared ``WorkerPool``, so the number of threads
    stays fixed whatever the clients do."""

    allow_reuse_address = True
    request_queue_size = 128        # the listen backlog: a burst of connections waits for the accept loop

    def __init__(self, address, handler, pool):
        if ":" in address[0]:
            self.address_family = socket.AF_INET6
        self.pool = pool
        super().__init__(address, handler)

    def source_of(self, client_address):
        return client_address[0]

    def describe(self):
        return f"{self.server_address[0]} port {self.server_address[1]}"


class AdminSocketServer(_Pooled, socketserver.UnixStreamServer):
    """The administration socket: a Unix socket at ``path``, 0600, in a folder only FIROS's user may change; every
    connection is one source (the operator's) in the shared pool."""

    request_queue_size = 16

    def __init__(self, path, handler, pool):
        self.pool = pool
        self.path = path
        _prepare_socket_path(path)
        umask = os.umask(0o177)      # the socket is made 0600: no moment when others may connect
        try:
            super().__init__(path, handler)
        finally:
            os.umask(umask)
        self._inode = os.stat(path).st_ino

    def source_of(self, client_address):
        return ADMIN_SOURCE

    def describe(self):
        return f"administration socket {self.path}"

    def server_close(self):
        super().server_close()
        try:
            if os.stat(self.path).st_ino == self._inode:
                os.unlink(self.path)
        except OSError:
            pass


def _prepare_socket_path(path):
    """Make the socket's folder (0700) if it is missing, refuse one that others may change, and remove a socket
    left by a FIROS that did not stop (none answers on it); OSError naming the path otherwise."""
    folder = os.path.dirname(path) or "."
    os.makedirs(folder, mode=0o700, exist_ok=True)
    mode = os.stat(folder).st_mode
    if mode & 0o022 and not mode & stat.S_ISVTX:
        raise OSError(errno.EPERM, f"{folder}: others may write in the administration socket's folder")
    try:
        found = os.lstat(path)
    except FileNotFoundError:
        return
    if not stat.S_ISSOCK(found.st_mode):
        raise OSError(errno.EEXIST, f"{path}: exists and is not a socket")
    probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    probe.settimeout(1.0)
    try:
        probe.connect(path)
    except OSError:
        os.unlink(path)       # nobody answers: left behind by a FIROS that was killed
        return
    finally:
        probe.close()
    raise OSError(errno.EADDRINUSE, f"{path}: another FIROS answers on this administration socket")


def make_servers(firos, port, hosts, admin_token=None, pool=None, admin_socket=None, shares=None, metrics=None):
    """One server per address in ``hosts`` (never a wildcard unless configured so) and, with ``admin_socket``
    (a path), the administration socket, all sharing one worker pool (``shares``: {source address: share} for the
    broker's addresses); OSError names the address or path that cannot be bound (the servers already made are
    closed)."""
    common = {"firos": firos, "admin_token": admin_token, "admin_socket": admin_socket, "metrics": metrics,
              "notes": Budget(log, "lines about refused or failed requests"), "tally": Tally(),
              "requests_log": Budget(log, "request lines")}
    handler = type("BoundFirosHandler", (FirosHandler,), common)
    admin_handler = type("BoundAdminHandler", (AdminHandler,), common)
    pool = pool or WorkerPool(shares=shares)
    servers = []
    try:
        for host in hosts:
            try:
                servers.append(FirosHTTPServer((host, port), handler, pool))
            except OSError as exc:
                raise OSError(exc.errno, f"{host}:{port}: {exc.strerror}") from None
        if admin_socket is not None:
            try:
                servers.append(AdminSocketServer(admin_socket, admin_handler, pool))
            except OSError as exc:
                text = exc.strerror or str(exc)
                raise OSError(exc.errno, text if admin_socket in text else f"{admin_socket}: {text}") from None
    except OSError:
        for server in servers:
            server.server_close()
        pool.close()
        raise
    return servers


def bind(servers, firos=None, metrics=None):
    """Give the servers' handlers the bridge and the metrics (made after the servers, which bind first)."""
    for server in servers:
        if firos is not None:
            server.RequestHandlerClass.firos = firos
        if metrics is not None:
            server.RequestHandlerClass.metrics = metrics


def close_servers(servers):
    """Stop serving (each was started with serve_in_thread) and stop the shared pool."""
    for server in servers:
        server.shutdown()
        server.server_close()
    if servers:
        servers[0].RequestHandlerClass.notes.flush()
        servers[0].RequestHandlerClass.requests_log.flush()
        servers[0].pool.close()


def serve_in_thread(server):
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.2},
                              name="firos-http", daemon=True)
    thread.start()
    return thread
