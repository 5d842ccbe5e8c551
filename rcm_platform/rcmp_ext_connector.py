"""The RDAPI: the master's HTTP interface for users (Twisted web), master only.

Owns the routes of CONTRACTS §2, JSON in and out (``{"result": "OK" | "ERROR", "reason": ...}``), the request
body size limit (413, the body is discarded as it arrives, never buffered), parsing of query strings and bodies
(``Content-Type: application/json`` only, 415 otherwise; nesting bounded), and the mapping of ``CommandError``
subclasses to HTTP statuses, done in one place (``_answer_error``). Handlers stay thin: parse, call one command of
``PlatformCommands`` / ``ServiceCommands``, render. A client's mistake never gets a 500; an unexpected error is
logged with its traceback and answered with a 500 whose reason says to look at the log.

Also owns who may call it (CONTRACTS §10, docs/SECURITY.md):
- bearer tokens (``Tokens``: the SHA-256 hashes kept in the robotics data, re-read every second and whenever an
  unknown token arrives, so ``rcmp_n token add/revoke`` takes effect while the agent runs; compared with
  ``hmac.compare_digest``). With no token the RDAPI is open and the log says so once; with any, every call but
  ``GET /``, ``OPTIONS`` and the console's static files needs ``Authorization: Bearer TOKEN`` (401), and writes
  need an ``admin`` token (403);
- CORS: any page may read; only the RDAPI's own origin and the (ext) ``allowed_origins`` may write (a POST with
  another ``Origin`` is 403, and preflights offer it GET only);
- the listener: HTTP or, with (ext) ``rdapi_tls_cert`` / ``rdapi_tls_key``, HTTPS through Twisted's SSL endpoint;
  at most ``max_connections`` connections (``max_per_address`` from one address; counted by
  ``rcmp_inter_communication.ConnectionCaps``, as the agent port's), a 503 to the rest; idle
  connections closed after ``idle_timeout``, a request whose headers and body take longer than
  ``request_deadline`` dropped, and a keep-alive connection closed after its current answer once it is
  ``connection_lifetime`` seconds old, so slow or trickling clients cannot hold a slot.

What a client sends reaches the log only through ``rcmp_log_guard``: paths, methods, query keys and the error
sentences built from them are cut (``shown``), and the lines of answered errors, which anyone can cause, go
through the site's ``Budget``. Every answer is strict JSON (``strict_dumps``: no bare NaN or Infinity).

And what it tells about itself: ``/metrics`` (a read route like the others, given a ``metrics`` object by
``rcmp_node``: ``rcmp_metrics`` renders it) and ``Rdapi.request_observers``, told of every finished request by its
route (``route_label``: one of the routes, ``/console/``, ``/console/api/`` or ``other``; never the raw path),
method (``METHOD_LABELS`` or ``other``), status and duration.
"""

import hashlib
import hmac
import json
import logging
import re
import secrets
import time

from twisted.application import service
from twisted.internet import defer, endpoints, protocol, task, threads
from twisted.web import http, resource, server

from .rcmp_inter_communication import ConnectionCaps, json_depth, strict_dumps
from .rcmp_log_guard import Budget, shown
from .rcmp_command import (BadRequest, CommandError, Forbidden, MethodNotAllowed, NotFound, TooLarge,
                           Unauthorized, UnsupportedMediaType)

log = logging.getLogger("rcm_platform.rdapi")

MAX_BODY = 64 * 1024
MAX_JSON_DEPTH = 8          # an RDAPI body is at most 3 deep (body, list, item); deeper ones are refused
WELCOME = b"<html><body>Welcome to the RCM platform node server!</body></html>"
# CORS answers: any page may read; the RDAPI's own origin and allowed_origins may also write
CORS_READ = (
    (b"Access-Control-Allow-Origin", b"*"),
    (b"Access-Control-Allow-Methods", b"GET, HEAD, OPTIONS"),
    (b"Access-Control-Allow-Headers", b"Authorization"),
    (b"Access-Control-Max-Age", b"600"),
    (b"Vary", b"Origin"),
)
CORS_WRITE = (
    (b"Access-Control-Allow-Methods", b"GET, HEAD, POST, OPTIONS"),
    (b"Access-Control-Allow-Headers", b"Authorization, Content-Type"),
    (b"Access-Control-Max-Age", b"600"),
    (b"Vary", b"Origin"),
)
# paths anyone may GET without a token: the welcome page and the console's static files (issue 11), not its
# API (/console/api/: the platform's state, live), which needs a token like any read
PUBLIC_PATHS = ("/", "/console")
PUBLIC_PREFIXES = ("/console/",)
PRIVATE_PREFIXES = ("/console/api/",)

MAX_CONNECTIONS = 256       # open RDAPI connections at once (the agent's fd limit is at least 1024)
MAX_PER_ADDRESS = 32        # of which from one source address
IDLE_TIMEOUT = 60.0         # seconds a keep-alive connection may sit idle
REQUEST_DEADLINE = 15.0     # seconds from a request's first line to its last body byte
CONNECTION_LIFETIME = 120.0  # seconds a keep-alive connection is kept (then closed after its current answer)

METHOD_LABELS = ("GET", "HEAD", "POST", "OPTIONS")   # request_observers get these, "other" for any other method
UNKNOWN_ROUTE = "other"     # request_observers' route for a path that is no route
LOST = "lost"               # request_observers' status for a request whose client left before any answer

TOKEN_REFRESH = 1.0         # seconds between re-reads of the token table
TOKEN_RE = re.compile(r"[A-Za-z0-9._~+/=-]{1,256}\Z")


# -- tokens --------------------------------------------------------------------------------------------------------

def new_token():
    """A new bearer token (256 random bits, URL-safe text) and the SHA-256 hex digest kept in its place."""
    token = secrets.token_urlsafe(32)
    return token, token_hash(token)


def token_hash(token):
    return hashlib.sha256(token.encode("utf-8")).hexdigest()


class Tokens(service.Service):
    """The RDAPI's tokens as last read from the robotics data (``data.tokens()``), with their roles.

    Loaded when the service starts (before the listener, so the RDAPI is never open by mistake), re-read in a
    thread every ``interval`` seconds (a revoked token stops working within that) and at once when an unknown
    token arrives (a new token works at its first use); concurrent re-reads are one.
    """

    def __init__(self, data, reactor, interval=TOKEN_REFRESH):
        self.data = data
        self.reactor = reactor
        self.interval = interval
        self._entries = ()        # ((sha256 hex bytes, name, role), ...)
        self._loaded = False
        self._refreshing = None   # the Deferred of the re-read in flight
        self._loop = None

    @property
    def required(self):
        """True when at least one token exists: every call but the public ones needs one."""
        return bool(self._entries)

    def startService(self):
        super().startService()
        self._set(self.data.tokens())
        self._loop = task.LoopingCall(self.refresh)
        self._loop.clock = self.reactor
        self._loop.start(self.interval, now=False)

    def stopService(self):
        if self._loop is not None and self._loop.running:
            self._loop.stop()
        return super().stopService()

    def _set(self, rows):
        was_open = self._loaded and not self._entries
        self._entries = tuple((r["sha256"].encode("ascii"), r["name"], r["role"]) for r in rows)
        if not self._entries and not was_open:
            log.warning("the RDAPI has no tokens: anyone who can reach it may read and provision; add one with "
                        "'rcmp_n token add NAME --role admin' (docs/SECURITY.md)")
        elif self._entries and (was_open or not self._loaded):
            log.info("the RDAPI needs a token (%d known)", len(self._entries))
        self._loaded = True

    def refresh(self):
        """Re-read the tokens in a thread; a Deferred that fires (never fails) when done."""
        if self._refreshing is None:
            d = threads.deferToThread(self.data.tokens)

            def done(rows):
                self._refreshing = None
                self._set(rows)

            def failed(failure):
                self._refreshing = None
                log.warning("cannot re-read the RDAPI tokens (keeping the previous ones): %s",
                            failure.getErrorMessage())
            d.addCallbacks(done, failed)
            self._refreshing = d
        result = defer.Deferred()
        self._refreshing.addBoth(lambda r: (result.callback(None), r)[1])
        return result

    def lookup(self, token):
        """``(name, role)`` of ``token`` or None; every known hash is compared, in constant time each."""
        digest = token_hash(token).encode("ascii")
        found = None
        for sha, name, role in self._entries:
            if hmac.compare_digest(digest, sha):
                found = (name, role)
        return found


class RdapiRequest(server.Request):
    """A request that stops storing its body once it is over ``max_body`` bytes and remembers it was too large."""

    max_body = MAX_BODY

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.too_large = False
        self._body_size = 0

    def gotLength(self, length):
        if length is not None and length > self.max_body:
            self.too_large = True
            length = 0
        super().gotLength(length)

    def handleContentChunk(self, data):
        if self.too_large:
            return
        self._body_size += len(data)
        if self._body_size > self.max_body:
            self.too_large = True
            self.content.seek(0)
            self.content.truncate()
            return
        super().handleContentChunk(data)


_TOO_DEEP = object()


class Route:
    """One path: the handler per method and the query parameters it takes (name -> required). A ``raw`` route's
    handler fires with ``(content type, bytes)``, sent as they are (``/metrics``), instead of a JSON answer's
    ``reason``."""

    def __init__(self, handlers, query=None, raw=False):
        self.handlers = handlers
        self.query = query or {}
        self.raw = raw

    @property
    def allowed(self):
        return sorted(self.handlers) + ["OPTIONS"]


class Rdapi(resource.Resource):
    """The whole RDAPI as one leaf resource with a table of routes.

    ``tokens``: a ``Tokens`` (None: the RDAPI is open); ``allowed_origins``: origins (``scheme://host[:port]``)
    whose pages may write besides the RDAPI's own; ``metrics``: what ``GET /metrics`` asks (``scrape()`` ->
    Deferred((content type, bytes)), or failing with a CommandError), None for no such route.
    """

    isLeaf = True

    def __init__(self, platform, service, tokens=None, allowed_origins=(), console=None, metrics=None,
                 clock=time.monotonic):
        super().__init__()
        self.errors_log = Budget(log, "RDAPI error lines", clock=clock)   # anyone can cause them
        self.platform = platform
        self.service = service
        self.tokens = tokens
        self.allowed_origins = frozenset(o.lower() for o in allowed_origins)
        self.console = console      # rcmp_console.ConsoleResource: everything under /console
        self._console_route = Route({"GET": None})
        self._encoded = {}  # (path, query) -> (the answer object, its JSON bytes)
        self.routes = {
            "/": Route({"GET": None}),
            "/platform_instance/read": Route({"GET": lambda q, b: platform.read(q.get("pi_type"))},
                                             query={"pi_type": False}),
            "/platform_instance/provisioning": Route({"POST": lambda q, b: platform.provisioning(b)}),
            "/platform_instance/r_provisioning": Route({"POST": lambda q, b: platform.r_provisioning(b)}),
            "/service_logic/read": Route({"GET": lambda q, b: service.read(q.get("slg_name"))},
                                         query={"slg_name": False}),
            "/service_logic/provisioning": Route({"POST": lambda q, b: service.provisioning(b)}),
            "/service_logic/r_provisioning": Route({"POST": lambda q, b: service.r_provisioning(b)}),
            "/service_space/read": Route({"GET": lambda q, b: service.service_space(q["ss_name"])},
                                         query={"ss_name": True}),
        }
        if metrics is not None:
            self.routes["/metrics"] = Route({"GET": lambda q, b: metrics.scrape()}, raw=True)
        self.request_observers = []   # fn(route, method, status, seconds) once each request finished

    # -- who may call ------------------------------------------------------------------------------------------

    @staticmethod
    def _own_origin(request):
        host = request.getHeader(b"host")
        if not host:
            return None
        scheme = "https" if request.isSecure() else "http"
        return f"{scheme}://{host.decode('latin-1')}".lower()

    def origin_may_write(self, request):
        """True when the request has no ``Origin`` (not a browser page), or the page is ours or allowed."""
        origin = request.getHeader(b"origin")
        if origin is None:
            return True
        origin = origin.decode("latin-1").lower()
        return origin in self.allowed_origins or origin == self._own_origin(request)

    def _cors(self, request):
        origin = request.getHeader(b"origin")
        if origin is not None and self.origin_may_write(request):
            request.setHeader(b"Access-Control-Allow-Origin", origin)
            headers = CORS_WRITE
        else:
            headers = CORS_READ
        for name, value in headers:
            request.setHeader(name, value)

    @staticmethod
    def is_public(path, method):
        return method in ("GET", "HEAD") and (path in PUBLIC_PATHS or path.startswith(PUBLIC_PREFIXES)) \
            and not path.startswith(PRIVATE_PREFIXES)

    @staticmethod
    def _bearer(request):
        """The token of an ``Authorization: Bearer TOKEN`` header; None without one; Unauthorized if malformed."""
        header = request.getHeader(b"authorization")
        if header is None:
            return None
        scheme, _, token = header.decode("latin-1").strip().partition(" ")
        token = token.strip()
        if scheme.lower() != "bearer" or not TOKEN_RE.match(token):
            raise Unauthorized("the Authorization header must be 'Bearer TOKEN' with a token made by "
                               "'rcmp_n token add'")
        return token

    def _authorize(self, request, method, token, refreshed):
        """Raise Unauthorized / Forbidden unless ``token`` may make this call; None when a re-read may help."""
        if token is None:
            raise Unauthorized("this RDAPI needs a token: send 'Authorization: Bearer TOKEN' (tokens are made "
                               "with 'rcmp_n token add NAME --role read|admin' on the master)")
        found = self.tokens.lookup(token)
        if found is None:
            if not refreshed:
                return None
            raise Unauthorized("unknown or revoked token")
        name, role = found
        if method == "POST" and role != "admin":
            raise Forbidden(f"the token '{name}' may only read; writes need a token with --role admin")
        return found

    # -- requests ----------------------------------------------------------------------------------------------

    def route_label(self, path):
        """What ``request_observers`` are told instead of ``path``: a bounded set of words."""
        if path in self.routes:
            return path
        if self.console is not None and (path == "/console" or path.startswith("/console/")):
            return "/console/api/" if path.startswith("/console/api/") else "/console/"
        return UNKNOWN_ROUTE

    def _observe(self, request, path, method):
        route = self.route_label(path)
        method = method if method in METHOD_LABELS else "other"
        started = time.monotonic()

        def finished(result):
            lost = result is not None and not getattr(request, "startedWriting", False)
            status = LOST if lost else str(request.code)
            for observer in list(self.request_observers):
                try:
                    observer(route, method, status, time.monotonic() - started)
                except Exception:
                    log.exception("request observer failed")
        request.notifyFinish().addBoth(finished)

    def render(self, request):
        self._cors(request)
        method = request.method.decode("latin-1")
        path = request.path.decode("latin-1")
        if self.request_observers:
            self._observe(request, path, method)
        try:
            if self.console is not None and (path == "/console" or path.startswith("/console/")):
                route = self._console_route   # GET only; its API behind the tokens like any read
            else:
                route = self.routes.get(path)
            if route is None:
                raise NotFound(f"unknown path {shown(path, 100)}: see the RDAPI documentation for the calls")
            if method == "OPTIONS":
                request.setHeader(b"Allow", ", ".join(route.allowed).encode())
                request.setResponseCode(204)
                return b""
            handler_method = "GET" if method == "HEAD" else method
            if handler_method not in route.handlers:
                raise MethodNotAllowed(f"{path} does not take {shown(method, 20)}; use "
                                       f"{' or '.join(route.allowed)}", route.allowed)
            if self.tokens is None or self.is_public(path, method):
                return self._dispatch(request, route, method, path)
            if not self.tokens.required:
                # open; but a caller sending a token knows of one that may have been added since the last re-read
                if request.getHeader(b"authorization") is None:
                    return self._dispatch(request, route, method, path)
                token = None
            else:
                token = self._bearer(request)
                if self._authorize(request, handler_method, token, refreshed=False) is not None:
                    return self._dispatch(request, route, method, path)
        except CommandError as exc:
            return self._answer_error(request, exc)
        # an unknown token: perhaps one added since the last re-read
        finished = []
        request.notifyFinish().addBoth(finished.append)

        def again(_):
            if finished:
                return
            try:
                if self.tokens.required:
                    self._authorize(request, handler_method, self._bearer(request), refreshed=True)
                result = self._dispatch(request, route, method, path)
            except CommandError as exc:
                result = self._answer_error(request, exc)
            if result is not server.NOT_DONE_YET:
                request.write(result)
                request.finish()
        self.tokens.refresh().addCallback(again)
        return server.NOT_DONE_YET

    def _dispatch(self, request, route, method, path):
        """The call itself, once the caller may make it: bytes, or NOT_DONE_YET while the command runs."""
        if route is self._console_route:
            return self.console.render(request)
        handler_method = "GET" if method == "HEAD" else method
        if handler_method == "POST":
            if not self.origin_may_write(request):
                origin = request.getHeader(b"origin").decode("latin-1")
                raise Forbidden(f"pages from {shown(origin, 100)} may not write to the RDAPI (only its own origin "
                                f"and the allowed_origins of the master's .init.cfg may)")
        if request.too_large:
            raise TooLarge(f"the request body is larger than {request.max_body} bytes")
        if handler_method == "POST":
            self._check_content_type(request)
        query = self._query(request, route)
        if path == "/":
            request.setHeader(b"Content-Type", b"text/html; charset=utf-8")
            return WELCOME
        body = self._body(request) if handler_method == "POST" else None
        d = defer.maybeDeferred(route.handlers[handler_method], query, body)
        finished = []
        request.notifyFinish().addBoth(finished.append)

        def ok(reason):
            if finished:
                return
            if route.raw:
                content_type, data = reason
                request.setResponseCode(200)
                request.setHeader(b"Content-Type", content_type.encode("latin-1"))
                request.setHeader(b"Content-Length", str(len(data)).encode())
                request.write(data)
                request.finish()
                return
            if method == "POST":
                log.info("RDAPI %s %s: OK: %s", method, path, shown(reason, 300))
                self._write(request, 200, {"result": "OK", "reason": reason})
                return
            # reads: the commands hand out the same object while it is current; encode it once
            key = (path, tuple(sorted(query.items())))
            hit = self._encoded.get(key)
            if hit is None or hit[0] is not reason:
                if len(self._encoded) >= 1024:
                    self._encoded.clear()
                hit = self._encoded[key] = (reason, self._dumps({"result": "OK", "reason": reason}))
            self._send(request, 200, hit[1])

        def error(failure):
            if finished:
                return
            if failure.check(CommandError):
                self._answer_error(request, failure.value, finish=True)
            else:
                log.error("RDAPI %s %s: unexpected error", shown(method, 20), shown(path),
                          exc_info=(failure.type, failure.value, failure.getTracebackObject()))
                self._write(request, 500, {"result": "ERROR",
                                           "reason": "internal error of the RCM master; see its log (rcmp.log)"})
        d.addCallback(ok)
        d.addErrback(error)  # also catches a failure to encode an answer in ok()
        return server.NOT_DONE_YET

    @staticmethod
    def _check_content_type(request):
        value = request.getHeader(b"content-type")
        media = value.decode("latin-1").split(";", 1)[0].strip().lower() if value else ""
        if media != "application/json":
            raise UnsupportedMediaType(f"the request body must be sent with 'Content-Type: application/json' "
                                       f"(this request has {shown(media, 60) if media else 'none'})")

    @staticmethod
    def _query(request, route):
        query = {}
        for raw_key, values in (request.args or {}).items():
            try:
                key = raw_key.decode("utf-8")
                decoded = [v.decode("utf-8") for v in values]
            except UnicodeDecodeError:
                raise BadRequest("the query string is not valid UTF-8") from None
            if key not in route.query:
                expected = ", ".join(route.query) or "none"
                raise BadRequest(f"unknown query parameter {shown(key, 60)} (expected: {expected})")
            if len(decoded) != 1:
                raise BadRequest(f"the query parameter {key!r} is given {len(decoded)} times")
            query[key] = decoded[0]
        for key, required in route.query.items():
            if required and key not in query:
                raise BadRequest(f"the query parameter {key!r} is required")
        return query

    @staticmethod
    def _body(request):
        request.content.seek(0)
        raw = request.content.read()
        if not raw.strip():
            raise BadRequest("the request body is empty: a JSON object is expected")
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError:
            raise BadRequest("the request body is not valid UTF-8") from None
        try:
            body = json.loads(text)
        except RecursionError:
            body = _TOO_DEEP
        except ValueError as exc:
            raise BadRequest(f"the request body is not valid JSON: {exc}") from None
        if body is _TOO_DEEP or json_depth(body, MAX_JSON_DEPTH) > MAX_JSON_DEPTH:
            raise BadRequest(f"the request body is nested more than {MAX_JSON_DEPTH} levels deep")
        if not isinstance(body, dict):
            raise BadRequest("the request body must be a JSON object")
        return body

    def _answer_error(self, request, exc, finish=False):
        status = exc.status
        if isinstance(exc, MethodNotAllowed) and exc.allowed:
            request.setHeader(b"Allow", ", ".join(exc.allowed).encode())
        if isinstance(exc, TooLarge):
            request.setHeader(b"Connection", b"close")
        if isinstance(exc, Unauthorized):
            request.setHeader(b"WWW-Authenticate", b'Bearer realm="rcm-platform"')
        elif isinstance(exc, Forbidden) and "--role admin" in str(exc):
            request.setHeader(b"WWW-Authenticate", b'Bearer realm="rcm-platform", error="insufficient_scope"')
        self.errors_log.info("RDAPI %s %s: %d %s", shown(request.method.decode("latin-1"), 20),
                             shown(request.path.decode("latin-1")), status, shown(str(exc), 300))
        payload = {"result": "ERROR", "reason": str(exc)}
        if finish:
            self._write(request, status, payload)
            return None
        return self._encode(request, status, payload)

    @staticmethod
    def _dumps(payload):
        return strict_dumps(payload, sort_keys=True).encode("utf-8")

    def _encode(self, request, status, payload):
        request.setResponseCode(status)
        request.setHeader(b"Content-Type", b"application/json")
        return self._dumps(payload)

    def _write(self, request, status, payload):
        self._send(request, status, self._dumps(payload))

    @staticmethod
    def _send(request, status, data):
        request.setResponseCode(status)
        request.setHeader(b"Content-Type", b"application/json")
        request.setHeader(b"Content-Length", str(len(data)).encode())
        request.write(data)
        request.finish()


class RdapiChannel(http.HTTPChannel):
    """An HTTP connection of the RDAPI: counted by its site, dropped when one request takes too long, and closed
    once it is old.

    The site's idle timeout (reset by every byte) closes silent connections; ``request_deadline`` bounds the time
    from a request's first line (or the connection's opening) to its last body byte, which a client trickling
    bytes would otherwise stretch for ever; ``connection_lifetime`` bounds the connection itself, which a client
    sending one small request now and then would otherwise keep for ever: when it is reached, an idle connection
    is closed and a busy one after its current answer (``Connection: close``). A console event stream is a
    request that lasts: its own deadlines are the console's.
    """

    def connectionMade(self):
        super().connectionMade()
        self._deadline = None
        self.expired = False
        self._lifetime = self.callLater(self.site.connection_lifetime, self._expire)
        self._arm()

    def _arm(self):
        if self._deadline is None:
            self._deadline = self.callLater(self.site.request_deadline, self._too_slow)

    def _disarm(self):
        if self._deadline is not None and self._deadline.active():
            self._deadline.cancel()
        self._deadline = None

    def _too_slow(self):
        self._deadline = None
        self.site.slow_dropped += 1
        self.transport.abortConnection()

    def _expire(self):
        self._lifetime = None
        self.expired = True
        self.site.expired += 1
        if not self.requests:
            self.transport.loseConnection()       # between two requests: nothing is lost
            return
        self.persistent = False                   # closed once the answer in progress is written
        for request in self.requests:
            if not request.startedWriting:
                request.setHeader(b"Connection", b"close")

    def checkPersistence(self, request, version):
        if self.expired:
            request.responseHeaders.setRawHeaders(b"connection", [b"close"])
            return False
        return super().checkPersistence(request, version)

    def lineReceived(self, line):
        self._arm()
        super().lineReceived(line)

    def allContentReceived(self):
        self._disarm()
        super().allContentReceived()

    def connectionLost(self, reason):
        self._disarm()
        if self._lifetime is not None and self._lifetime.active():
            self._lifetime.cancel()
        self._lifetime = None
        self.site.channel_closed(self)
        super().connectionLost(reason)


class _Busy(protocol.Protocol):
    """What a connection over the caps gets: a 503 with the usual JSON error, then the connection is closed."""

    def __init__(self, reason):
        self.reason = reason

    def connectionMade(self):
        body = strict_dumps({"result": "ERROR", "reason": self.reason}, sort_keys=True).encode()
        self.transport.write(b"HTTP/1.1 503 Service Unavailable\r\nContent-Type: application/json\r\n"
                             b"Retry-After: 5\r\nConnection: close\r\nContent-Length: "
                             + str(len(body)).encode() + b"\r\n\r\n" + body)
        self.transport.loseConnection()


class RdapiSite(server.Site):
    """The RDAPI site: our request and channel classes, connection caps, no per-request access log."""

    requestFactory = RdapiRequest
    displayTracebacks = False
    protocol = RdapiChannel

    def __init__(self, resource, max_connections=MAX_CONNECTIONS, max_per_address=MAX_PER_ADDRESS,
                 idle_timeout=IDLE_TIMEOUT, request_deadline=REQUEST_DEADLINE,
                 connection_lifetime=CONNECTION_LIFETIME, **kwargs):
        super().__init__(resource, timeout=idle_timeout, **kwargs)
        self.caps = ConnectionCaps(max_connections, max_per_address)
        self.request_deadline = request_deadline
        self.connection_lifetime = connection_lifetime
        self.refused = 0              # connections answered 503 for being over a cap
        self.slow_dropped = 0         # connections dropped by the request deadline
        self.expired = 0              # connections closed for their age
        self._warned = False

    @property
    def open_channels(self):
        """The connections open now."""
        return self.caps.open.keys()

    def buildProtocol(self, addr):
        host = getattr(addr, "host", "?")
        over = self.caps.over(host)
        if over == "total":
            return self._busy(f"the RDAPI has {self.caps.max_connections} connections open; try again shortly")
        if over == "address":
            return self._busy(f"{self.caps.max_per_address} RDAPI connections are already open from {host}; "
                              f"close some first")
        channel = super().buildProtocol(addr)
        self.caps.opened(channel, host)
        return channel

    def _busy(self, reason):
        self.refused += 1
        if not self._warned:
            self._warned = True
            log.warning("RDAPI connection refused: %s (said once; see docs/SECURITY.md)", reason)
        busy = _Busy(reason)
        busy.factory = self
        return busy

    def channel_closed(self, channel):
        self.caps.closed(channel)

    def log(self, request):
        pass


def make_site(platform, service, max_body=MAX_BODY, tokens=None, allowed_origins=(), console=None,
              metrics=None, **limits):
    """The Twisted site serving the RDAPI with ``PlatformCommands`` ``platform`` and ``ServiceCommands`` ``service``.

    ``tokens``: a ``Tokens`` or None (open); ``console``: the ``rcmp_console.ConsoleResource`` served under
    /console/ (its static files public, its API behind the tokens like any read); ``metrics``: what serves
    ``GET /metrics`` (``rcmp_metrics``), None for no such route; ``limits``: ``max_connections``,
    ``max_per_address``, ``idle_timeout``, ``request_deadline``, ``connection_lifetime`` of ``RdapiSite``. The
    ``Rdapi`` is ``site.resource``.
    """
    site = RdapiSite(Rdapi(platform, service, tokens=tokens, allowed_origins=allowed_origins,
                           console=console, metrics=metrics), **limits)

    class Request(RdapiRequest):
        pass
    Request.max_body = max_body
    site.requestFactory = Request
    return site


# -- the listener --------------------------------------------------------------------------------------------------

class TlsError(Exception):
    """The RDAPI's certificate or key cannot be used; ``str()`` is one line naming the file and the problem."""


def tls_options(cert_path, key_path):
    """Twisted ``CertificateOptions`` from a PEM certificate (chain) file and a PEM private key file; TlsError."""
    from OpenSSL import crypto
    from twisted.internet import ssl

    def read(path, what):
        try:
            with open(path, "rb") as f:
                return f.read()
        except OSError as exc:
            raise TlsError(f"{path}: cannot read the RDAPI's {what}: {exc.strerror or exc}") from None
    cert_pem, key_pem = read(cert_path, "certificate"), read(key_path, "private key")
    blocks = re.findall(rb"-----BEGIN CERTIFICATE-----.+?-----END CERTIFICATE-----", cert_pem, re.S)
    if not blocks:
        raise TlsError(f"{cert_path}: no PEM certificate in it (expected '-----BEGIN CERTIFICATE-----')")
    try:
        chain = [crypto.load_certificate(crypto.FILETYPE_PEM, block) for block in blocks]
    except crypto.Error:
        raise TlsError(f"{cert_path}: a certificate in it cannot be read (damaged PEM?)") from None
    try:
        key = crypto.load_privatekey(crypto.FILETYPE_PEM, key_pem)
    except crypto.Error:
        raise TlsError(f"{key_path}: not a PEM private key without a passphrase") from None
    try:
        options = ssl.CertificateOptions(privateKey=key, certificate=chain[0], extraCertChain=chain[1:])
        options.getContext().check_privatekey()
    except Exception:  # OpenSSL's errors are lists of library codes: say what they mean here
        raise TlsError(f"{key_path}: this private key does not belong to the certificate in {cert_path}") from None
    if chain[0].has_expired():
        log.warning("the RDAPI's certificate %s has expired: clients will refuse it", cert_path)
    return options


def rdapi_service(site, port, interface, reactor=None, tls=None):
    """A Twisted service listening for the RDAPI on ``interface:port`` while running; HTTPS with ``tls``
    (``tls_options(...)``) through Twisted's SSL endpoint."""
    if reactor is None:
        from twisted.internet import reactor
    if tls is None:
        endpoint = endpoints.TCP4ServerEndpoint(reactor, port, backlog=128, interface=interface)
    else:
        endpoint = endpoints.SSL4ServerEndpoint(reactor, port, tls, backlog=128, interface=interface)
    return _Listener(endpoint, site)


class _Listener(service.Service):
    """Listens on an endpoint while running; a port that cannot be taken raises from ``startService`` (the agent
    stops with one line) instead of being logged later."""

    def __init__(self, endpoint, factory):
        self.endpoint = endpoint
        self.factory = factory
        self.port = None

    def startService(self):
        failures = []
        self.endpoint.listen(self.factory).addCallbacks(self._listening, failures.append)
        if failures:
            failures[0].raiseException()
        super().startService()

    def _listening(self, port):
        self.port = port

    def stopService(self):
        super().stopService()
        port, self.port = self.port, None
        return port.stopListening() if port is not None else None
