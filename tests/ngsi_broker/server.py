"""The broker's HTTP side: routing, tenant headers, body size limit, content types and Orion's error shapes.

``BrokerServer`` puts the store, the notifier and both APIs behind a stdlib ``ThreadingHTTPServer`` speaking
HTTP/1.1 with keep-alive (one thread per connection). Every request is parsed into a ``Request`` (query
parameters, ``Fiware-Service`` → tenant, ``Fiware-ServicePath`` → write path and query paths, JSON body) and
answered with a ``Response``. A ``model.NgsiError`` becomes Orion's NGSI v2 ``{"error", "description"}`` under
``/v2`` and Orion's ``orionError`` (or ``subscribeError`` for the v1 subscription operations) under ``/v1`` and
``/NGSI10``. Unknown URLs get Orion's "Service not found" 400, wrong methods a 405 with ``Allow``.
Paths under ``/ngsi-ld/`` go to ``ngsild.NgsiLd`` (same body limit and faults, ProblemDetails errors).
``/_standin/faults`` (not an Orion URL) lets a test make the next requests fail, to exercise its error paths.
"""

import json
import logging
import re
import threading
import time
import uuid
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import parse_qs, unquote, urlsplit

from . import model
from .model import NgsiError
from .ngsild import LdProblem, NgsiLd, problem_response
from .ngsiv1 import NgsiV1
from .ngsiv2 import NgsiV2
from .subscriptions import Notifications, Notifier

log = logging.getLogger("ngsi_broker")

MAX_BODY = 1024 * 1024  # Orion's default request payload limit (1 MB)
DRAIN_LIMIT = 64 * 1024 * 1024  # a refused body up to this size is read and dropped before answering
ORION_VERSION = "3.9.0"
REASON_PHRASES = {400: "Bad Request", 404: "Not Found", 405: "Method Not Allowed", 406: "Not Acceptable",
                  409: "Conflict", 411: "Length Required", 413: "Request Entity Too Large",
                  415: "Unsupported Media Type", 422: "Unprocessable Content", 500: "Internal Server Error"}
SERVICE_NOT_FOUND = "Service not found. Check your URL as probably it is wrong."


class Response:
    """What a handler answers: status, body bytes, content type (None: no body) and extra headers."""

    def __init__(self, status, body=b"", content_type="application/json", headers=None):
        self.status = status
        self.body = body
        self.content_type = content_type
        self.headers = headers or {}


class Request:
    """One parsed request as the API handlers see it."""

    def __init__(self, method, path, query, headers, body, api):
        self.method = method
        self.path = path
        self.query = query
        self.headers = headers
        self.body = body
        self.api = api  # "v1" | "v2" | "other"
        self.correlator = headers.get("Fiware-Correlator") or str(uuid.uuid1())
        content_type = headers.get("Content-Type")
        self.content_type = content_type.split(";")[0].strip().lower() if content_type else None
        self.tenant = ""
        self.update_path = "/"
        self.query_paths = [("/", True)]

    def read_tenant(self, handler_name):
        """Tenant and service paths from the headers: reads (and subscriptions) take a list of paths with
        ``/#`` for "and below" (default: everything); writes take exactly one path (default ``/``)."""
        self.tenant = model.parse_tenant(self.headers.get("Fiware-Service"))
        service_path = self.headers.get("Fiware-ServicePath")
        if handler_name in READ_HANDLERS:
            self.query_paths = model.parse_query_service_paths(service_path)
        else:
            self.update_path = model.parse_update_service_path(service_path)
            self.query_paths = [(self.update_path, False)]

    def param(self, name):
        values = self.query.get(name)
        return values[-1] if values else None

    def header(self, name):
        return self.headers.get(name)

    def json(self):
        if not self.body:
            raise NgsiError(411, "ContentLengthRequired", "Zero/No Content-Length in PUT/POST/PATCH request")
        try:
            return json.loads(self.body.decode("utf-8"))
        except (ValueError, UnicodeDecodeError):
            raise NgsiError(400, "ParseError", "Errors found in incoming JSON buffer"
                            if self.api == "v2" else "JSON Parse Error") from None

    def json_response(self, status, body, headers=None):
        return Response(status, json.dumps(body).encode("utf-8"), "application/json", headers)

    def empty_response(self, status, headers=None):
        return Response(status, b"", None, headers)

    def raw_response(self, status, body, content_type):
        return Response(status, body, content_type)


_ID = r"(?P<eid>[^/]+)"
_ATTR = r"(?P<attr>[^/]+)"
_SUB = r"(?P<sid>[^/]+)"
READ_HANDLERS = {"version", "faults.list", "faults.add", "faults.clear", "v2.root", "v2.list_entities", "v2.get_entity", "v2.get_attrs", "v2.get_attr",
                 "v2.get_attr_value", "v2.create_subscription", "v2.list_subscriptions", "v2.get_subscription",
                 "v2.patch_subscription", "v2.delete_subscription", "v1.query_context", "v1.subscribe_context",
                 "v1.update_context_subscription", "v1.unsubscribe_context", "v1.get_entity_attribute"}
V1_OPERATIONS = {"updatecontext": "update_context", "querycontext": "query_context",
                 "subscribecontext": "subscribe_context", "unsubscribecontext": "unsubscribe_context",
                 "updatecontextsubscription": "update_context_subscription"}


def _routes():
    """(compiled path regex, api, {method: handler name}, content types allowed besides JSON)."""
    table = [
        (r"/version", "other", {"GET": "version"}),
        (r"/_standin/faults", "other", {"GET": "faults.list", "POST": "faults.add", "DELETE": "faults.clear"}),
        (r"/v2/?", "v2", {"GET": "v2.root"}),
        (r"/v2/entities", "v2", {"GET": "v2.list_entities", "POST": "v2.create_entity"}),
        (rf"/v2/entities/{_ID}", "v2", {"GET": "v2.get_entity", "DELETE": "v2.delete_entity"}),
        (rf"/v2/entities/{_ID}/attrs", "v2", {"GET": "v2.get_attrs", "POST": "v2.post_attrs",
                                              "PATCH": "v2.patch_attrs", "PUT": "v2.put_attrs"}),
        (rf"/v2/entities/{_ID}/attrs/{_ATTR}", "v2", {"GET": "v2.get_attr", "PUT": "v2.put_attr",
                                                      "DELETE": "v2.delete_attr"}),
        (rf"/v2/entities/{_ID}/attrs/{_ATTR}/value", "v2", {"GET": "v2.get_attr_value",
                                                            "PUT": "v2.put_attr_value"}),
        (r"/v2/op/update", "v2", {"POST": "v2.op_update"}),
        (r"/v2/subscriptions", "v2", {"GET": "v2.list_subscriptions", "POST": "v2.create_subscription"}),
        (rf"/v2/subscriptions/{_SUB}", "v2", {"GET": "v2.get_subscription", "PATCH": "v2.patch_subscription",
                                              "DELETE": "v2.delete_subscription"}),
        (rf"/v1/contextEntities/{_ID}", "v1", {"PUT": "v1.put_entity", "DELETE": "v1.delete_entity"}),
        (rf"/v1/contextEntities/{_ID}/attributes/{_ATTR}", "v1", {"GET": "v1.get_entity_attribute"}),
    ]
    return [(re.compile("^" + pattern + "$"), api, methods) for pattern, api, methods in table]


ROUTES = _routes()
V1_ROUTE = re.compile(r"^/(?:v1|ngsi10)/(?P<op>[A-Za-z]+)$", re.IGNORECASE)


def match_route(path):
    """(api, {method: handler name}, [path arguments]) for a path, or None."""
    for regex, api, methods in ROUTES:
        match = regex.match(path)
        if match:
            return api, methods, [unquote(v) for v in match.groups()]
    match = V1_ROUTE.match(path)
    if match and match.group("op").lower() in V1_OPERATIONS:
        return "v1", {"POST": "v1." + V1_OPERATIONS[match.group("op").lower()]}, []
    return None


def error_response(api, exc, handler_name=""):
    """An ``NgsiError`` in the shape Orion uses for this API."""
    if api == "v2":
        body = {"error": exc.error, "description": exc.description}
    else:
        phrase = REASON_PHRASES.get(exc.status) or HTTPStatus(exc.status).phrase
        error_code = {"code": str(exc.status), "reasonPhrase": phrase,
                      "details": exc.description}
        if exc.status == 413:  # Orion's v1 answer to a too large payload
            body = {"errorCode": error_code}
        elif handler_name in ("v1.subscribe_context", "v1.update_context_subscription") \
                and exc.error not in ("ParseError", "ContentLengthRequired"):
            body = {"subscribeError": {"errorCode": error_code}}
        else:
            body = {"orionError": error_code}
    return Response(exc.status, json.dumps(body).encode("utf-8"))


class Faults:
    """Test-only fault injection (``/_standin/faults``, not an Orion URL): the next ``count`` requests whose
    path matches ``path`` (a regular expression, default any NGSI path) and, if given, ``method`` get HTTP
    ``status`` with Orion's error body for that API, or, with status 0, a closed connection and no answer."""

    def __init__(self):
        self._lock = threading.Lock()
        self._faults = []

    def add(self, req):
        body = req.json()
        if not isinstance(body, dict):
            raise model.bad_request("a fault is a JSON object")
        status, count = body.get("status", 500), body.get("count", 1)
        if not isinstance(status, int) or not (status == 0 or 400 <= status <= 599):
            raise model.bad_request("status must be 0 (close the connection) or an HTTP error status 400-599")
        if not isinstance(count, int) or count < 1:
            raise model.bad_request("count must be a positive whole number")
        path = body.get("path", r"^/(v1|v2|NGSI10|ngsi10)/")
        try:
            regex = re.compile(path)
        except (re.error, TypeError):
            raise model.bad_request("path must be a regular expression") from None
        method = body.get("method")
        if method is not None and method not in ("GET", "POST", "PUT", "PATCH", "DELETE"):
            raise model.bad_request("method must be GET, POST, PUT, PATCH or DELETE")
        with self._lock:
            self._faults.append({"status": status, "count": count, "path": path, "regex": regex,
                                 "method": method})
        return req.empty_response(201)

    def list(self, req):
        with self._lock:
            body = [{k: v for k, v in f.items() if k != "regex"} for f in self._faults]
        return req.json_response(200, body)

    def clear(self, req):
        with self._lock:
            self._faults.clear()
        return req.empty_response(204)

    def take(self, method, path):
        """The status of the fault this request meets (counting it down), or None."""
        if path.startswith("/_standin/"):
            return None
        with self._lock:
            for fault in self._faults:
                if (fault["method"] in (None, method)) and fault["regex"].search(path):
                    fault["count"] -= 1
                    if fault["count"] == 0:
                        self._faults.remove(fault)
                    return fault["status"]
        return None


class _Handler(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"
    # headers and body leave in two sends: without TCP_NODELAY, Nagle's algorithm holds the body back until
    # the client's delayed ACK (about 40 ms per answer with a body on loopback)
    disable_nagle_algorithm = True

    def version_string(self):
        return "orion-standin"

    def log_message(self, fmt, *args):
        if not self.server.broker.quiet:
            log.info("%s - %s", self.address_string(), fmt % args)

    def do_GET(self):
        self._handle("GET")

    def do_POST(self):
        self._handle("POST")

    def do_PUT(self):
        self._handle("PUT")

    def do_PATCH(self):
        self._handle("PATCH")

    def do_DELETE(self):
        self._handle("DELETE")

    def do_OPTIONS(self):
        self._handle("OPTIONS")

    def _read_body(self, limit):
        """The request body (by Content-Length); NgsiError 413 beyond ``limit``, 411 when chunked."""
        if "chunked" in (self.headers.get("Transfer-Encoding") or "").lower():
            # Orion (microhttpd) needs a Content-Length: a chunked request gets 411 (its body is dropped)
            self.close_connection = True
            self._discard_chunked()
            raise NgsiError(411, "ContentLengthRequired", "Zero/No Content-Length in PUT/POST/PATCH request")
        length_text = self.headers.get("Content-Length")
        if not length_text:
            return b""
        try:
            length = int(length_text)
        except ValueError:
            self.close_connection = True
            raise model.bad_request("invalid Content-Length") from None
        if length > limit:
            self.close_connection = True
            self._discard(length)
            raise NgsiError(413, "RequestEntityTooLarge", f"payload size: {length}, max size supported: {limit}")
        return self.rfile.read(length) if length > 0 else b""

    def _discard(self, length):
        """Read and drop a refused body (up to DRAIN_LIMIT) so the client sees the answer, not a broken pipe."""
        remaining = min(length, DRAIN_LIMIT)
        while remaining > 0:
            chunk = self.rfile.read(min(remaining, 65536))
            if not chunk:
                break
            remaining -= len(chunk)

    def _discard_chunked(self):
        total = 0
        while total <= DRAIN_LIMIT:
            line = self.rfile.readline(1024)
            try:
                size = int(line.split(b";")[0].strip() or b"0", 16)
            except ValueError:
                return
            if size == 0:
                return
            self._discard(size)
            self.rfile.readline(1024)
            total += size

    def _handle(self, method):
        broker = self.server.broker
        parts = urlsplit(self.path)
        path = parts.path
        if path.startswith("/ngsi-ld/"):
            self._handle_ld(method, parts)
            return
        route = match_route(path)
        api = route[0] if route else ("v2" if path.startswith("/v2") else "v1")
        handler_name = ""
        try:
            try:
                body = self._read_body(broker.max_body)
            except NgsiError as exc:
                self._send(error_response(api, exc), close=True)
                return
            if route is None:
                self._send(Response(400, json.dumps({"orionError": {
                    "code": "400", "reasonPhrase": "Bad Request", "details": SERVICE_NOT_FOUND}}).encode()))
                return
            api, methods, args = route
            if method not in methods:
                self._send(Response(405, b"", None, {"Allow": ", ".join(sorted(methods))}))
                return
            handler_name = methods[method]
            fault = broker.faults.take(method, path)
            if fault == 0:
                self.close_connection = True
                return
            if fault is not None:
                raise NgsiError(fault, HTTPStatus(fault).phrase.replace(" ", "").replace("-", ""),
                                "Database Error (fault injected by the stand-in broker)")
            request = Request(method, path, parse_qs(parts.query, keep_blank_values=True), self.headers, body, api)
            if body and request.content_type not in ("application/json", "text/plain"):
                raise NgsiError(415, "UnsupportedMediaType",
                                f"not supported content type: {request.content_type}" if request.content_type
                                else "Content-Type header not used, default application/octet-stream is not "
                                     "supported")
            if body and request.content_type == "text/plain" and handler_name != "v2.put_attr_value":
                raise NgsiError(415, "UnsupportedMediaType", "not supported content type: text/plain")
            request.read_tenant(handler_name)
            response = broker.call(handler_name, request, args)
            response.headers.setdefault("Fiware-Correlator", request.correlator)
            self._send(response)
        except NgsiError as exc:
            self._send(error_response(api, exc, handler_name))
        except Exception:  # a bug of the stand-in itself: say so, keep serving
            log.exception("internal error on %s %s", method, self.path)
            self._send(error_response(api, NgsiError(500, "InternalServerError", "internal error")))

    def _handle_ld(self, method, parts):
        """NGSI-LD: the same body limit and faults, ProblemDetails errors, the rest in ``ngsild``."""
        broker = self.server.broker
        try:
            try:
                body = self._read_body(broker.max_body)
            except NgsiError as exc:
                kind = "BadRequestData" if exc.status != 413 else "RequestEntityTooLarge"
                # the phrase of our own table: Python 3.13 calls 413 "Content Too Large", Orion-LD does not
                title = REASON_PHRASES.get(exc.status) or HTTPStatus(exc.status).phrase
                self._send(problem_response(LdProblem(exc.status, kind, title, exc.description)), close=True)
                return
            fault = broker.faults.take(method, parts.path)
            if fault == 0:
                self.close_connection = True
                return
            if fault is not None:
                self._send(problem_response(LdProblem(fault, "InternalError", HTTPStatus(fault).phrase,
                                                      "fault injected by the stand-in broker")))
                return
            self._send(broker.ld.handle(method, parts.path, parse_qs(parts.query, keep_blank_values=True),
                                        self.headers, body))
        except Exception:  # a bug of the stand-in itself: say so, keep serving
            log.exception("internal error on %s %s", method, self.path)
            self._send(problem_response(LdProblem(500, "InternalError", "Internal Error", "internal error")))

    def _send(self, response, close=False):
        self.send_response(response.status)
        if response.content_type and response.body:
            self.send_header("Content-Type", response.content_type)
        self.send_header("Content-Length", str(len(response.body)))
        response.headers.setdefault("Fiware-Correlator", self.headers.get("Fiware-Correlator") or str(uuid.uuid1()))
        for name, value in response.headers.items():
            self.send_header(name, value)
        if close or self.close_connection:
            self.send_header("Connection", "close")
            self.close_connection = True
        self.end_headers()
        if self.command != "HEAD" and response.body:
            self.wfile.write(response.body)


class _HTTPServer(ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True


class BrokerServer:
    """The whole stand-in broker: store, notifier, both APIs and the HTTP server."""

    def __init__(self, host="127.0.0.1", port=1026, notify_timeout=2.0, max_body=MAX_BODY,
                 v1_initial_notification=True, quiet=False):
        self.store = model.Store()
        self.notifier = Notifier(timeout=notify_timeout)
        self.notifications = Notifications(self.store, self.notifier)
        self.v1 = NgsiV1(self.store, self.notifications, initial_notification=v1_initial_notification)
        self.v2 = NgsiV2(self.store, self.notifications)
        self.ld = NgsiLd(self.store, self.notifier)
        self.faults = Faults()
        self.max_body = max_body
        self.quiet = quiet
        self.httpd = _HTTPServer((host, port), _Handler)
        self.httpd.broker = self
        self._thread = None

    @property
    def host(self):
        return self.httpd.server_address[0]

    @property
    def port(self):
        return self.httpd.server_address[1]

    @property
    def url(self):
        return f"http://{self.host}:{self.port}"

    def call(self, handler_name, request, args):
        if handler_name == "version":
            return request.json_response(200, self.version())
        api, name = handler_name.split(".")
        return getattr(getattr(self, api), name)(request, *args)

    def version(self):
        uptime = int(time.time() - self.store.started)
        days, rest = divmod(uptime, 86400)
        hours, rest = divmod(rest, 3600)
        minutes, seconds = divmod(rest, 60)
        return {"orion": {"version": ORION_VERSION, "uptime": f"{days} d, {hours} h, {minutes} m, {seconds} s",
                          "git_hash": "nogitversion", "compile_time": "", "compiled_by": "", "compiled_in": "",
                          "release_date": "", "machine": "", "doc": "docs/STANDIN_BROKER.md",
                          "libversions": {}, "standin": True}}

    def serve_forever(self):
        self.httpd.serve_forever(poll_interval=0.2)

    def start(self):
        """Serve from a background thread (for in-process use)."""
        self._thread = threading.Thread(target=self.serve_forever, name="ngsi-broker", daemon=True)
        self._thread.start()
        return self

    def shutdown(self):
        """Stop serving (when ``start`` was called), close the socket and stop the notifier."""
        if self._thread is not None:
            self.httpd.shutdown()
        self.httpd.server_close()
        self.notifier.close(timeout=0.5)
        if self._thread is not None:
            self._thread.join(timeout=5)
