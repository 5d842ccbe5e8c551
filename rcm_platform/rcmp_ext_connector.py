"""The RDAPI: the master's HTTP interface for users (Twisted web), master only.

Owns the routes of CONTRACTS §2, JSON in and out (``{"result": "OK" | "ERROR", "reason": ...}``), CORS (``*``
for GET, POST, OPTIONS), the request body size limit (413, the body is discarded as it arrives, never buffered),
parsing of query strings and bodies, and the mapping of ``CommandError`` subclasses to HTTP statuses, done in one
place (``_answer_error``). Handlers stay thin: parse, call one command of ``PlatformCommands`` /
``ServiceCommands``, render. A client's mistake never gets a 500; an unexpected error is logged with its traceback
and answered with a 500 whose reason says to look at the log.
"""

import json
import logging

from twisted.application import internet
from twisted.internet import defer
from twisted.web import resource, server

from .rcmp_command import BadRequest, CommandError, MethodNotAllowed, NotFound, TooLarge

log = logging.getLogger("rcm_platform.rdapi")

MAX_BODY = 64 * 1024
WELCOME = b"<html><body>Welcome to the RCM platform node server!</body></html>"
CORS_HEADERS = (
    (b"Access-Control-Allow-Origin", b"*"),
    (b"Access-Control-Allow-Methods", b"GET, POST, OPTIONS"),
    (b"Access-Control-Allow-Headers", b"Content-Type"),
)


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


class Route:
    """One path: the handler per method and the query parameters it takes (name -> required)."""

    def __init__(self, handlers, query=None):
        self.handlers = handlers
        self.query = query or {}

    @property
    def allowed(self):
        return sorted(self.handlers) + ["OPTIONS"]


class Rdapi(resource.Resource):
    """The whole RDAPI as one leaf resource with a table of routes."""

    isLeaf = True

    def __init__(self, platform, service):
        super().__init__()
        self.platform = platform
        self.service = service
        self._encoded = {}  # (path, query) -> (the answer object, its JSON bytes)
        self.routes = {
            "/": Route({"GET": None}),
            "/platform_instance/read": Route({"GET": lambda q, b: platform.read()}),
            "/platform_instance/provisioning": Route({"POST": lambda q, b: platform.provisioning(b)}),
            "/platform_instance/r_provisioning": Route({"POST": lambda q, b: platform.r_provisioning(b)}),
            "/service_logic/read": Route({"GET": lambda q, b: service.read(q.get("slg_name"))},
                                         query={"slg_name": False}),
            "/service_logic/provisioning": Route({"POST": lambda q, b: service.provisioning(b)}),
            "/service_logic/r_provisioning": Route({"POST": lambda q, b: service.r_provisioning(b)}),
            "/service_space/read": Route({"GET": lambda q, b: service.service_space(q["ss_name"])},
                                         query={"ss_name": True}),
        }

    def render(self, request):
        for name, value in CORS_HEADERS:
            request.setHeader(name, value)
        method = request.method.decode("latin-1")
        path = request.path.decode("latin-1")
        try:
            route = self.routes.get(path)
            if route is None:
                raise NotFound(f"unknown path {path!r}: see the RDAPI documentation for the calls")
            if method == "OPTIONS":
                request.setHeader(b"Allow", ", ".join(route.allowed).encode())
                request.setResponseCode(204)
                return b""
            handler_method = "GET" if method == "HEAD" else method
            if handler_method not in route.handlers:
                raise MethodNotAllowed(f"{path} does not take {method!r}; use {' or '.join(route.allowed)}",
                                       route.allowed)
            if request.too_large:
                raise TooLarge(f"the request body is larger than {request.max_body} bytes")
            query = self._query(request, route)
            if path == "/":
                request.setHeader(b"Content-Type", b"text/html; charset=utf-8")
                return WELCOME
            body = self._body(request) if handler_method == "POST" else None
            d = defer.maybeDeferred(route.handlers[handler_method], query, body)
        except CommandError as exc:
            return self._answer_error(request, exc)
        finished = []
        request.notifyFinish().addBoth(finished.append)

        def ok(reason):
            if finished:
                return
            if method == "POST":
                log.info("RDAPI %s %s: OK: %s", method, path, reason)
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
                log.error("RDAPI %s %s: unexpected error", method, path,
                          exc_info=(failure.type, failure.value, failure.getTracebackObject()))
                self._write(request, 500, {"result": "ERROR",
                                           "reason": "internal error of the RCM master; see its log (rcmp.log)"})
        d.addCallback(ok)
        d.addErrback(error)  # also catches a failure to encode an answer in ok()
        return server.NOT_DONE_YET

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
                raise BadRequest(f"unknown query parameter {key!r} (expected: {expected})")
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
        except ValueError as exc:
            raise BadRequest(f"the request body is not valid JSON: {exc}") from None
        if not isinstance(body, dict):
            raise BadRequest("the request body must be a JSON object")
        return body

    def _answer_error(self, request, exc, finish=False):
        status = exc.status
        if isinstance(exc, MethodNotAllowed) and exc.allowed:
            request.setHeader(b"Allow", ", ".join(exc.allowed).encode())
        if isinstance(exc, TooLarge):
            request.setHeader(b"Connection", b"close")
        log.info("RDAPI %s %s: %d %s", request.method.decode("latin-1"), request.path.decode("latin-1"),
                 status, exc)
        payload = {"result": "ERROR", "reason": str(exc)}
        if finish:
            self._write(request, status, payload)
            return None
        return self._encode(request, status, payload)

    @staticmethod
    def _dumps(payload):
        return json.dumps(payload, sort_keys=True).encode("utf-8")

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


class RdapiSite(server.Site):
    """The RDAPI site: our request class, no per-request access log (errors and writes are logged instead)."""

    requestFactory = RdapiRequest
    displayTracebacks = False

    def log(self, request):
        pass


def make_site(platform, service, max_body=MAX_BODY):
    """The Twisted site serving the RDAPI with ``PlatformCommands`` ``platform`` and ``ServiceCommands`` ``service``."""
    site = RdapiSite(Rdapi(platform, service), timeout=120)

    class Request(RdapiRequest):
        pass
    Request.max_body = max_body
    site.requestFactory = Request
    return site


def rdapi_service(site, port, interface):
    """A Twisted service listening for the RDAPI on ``interface:port`` while running."""
    return internet.TCPServer(port, site, interface=interface)
