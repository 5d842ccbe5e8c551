"""What every NGSI version's client shares: one HTTP/1.1 keep-alive connection to the context broker, the errors, and
the interface FIROS's other modules call.

Owns the connection (one per client object; reconnects once when the broker dropped a kept-alive connection), error
classification by HTTP status (`BrokerUnavailable` = cannot reach the broker or it answered 5xx, worth retrying;
`BrokerError` = the broker refused the request, with its `status`; retrying the same thing will not help;
`RequestTooLarge` = a 413, from the broker or because FIROS itself would not send a request over `max_request_size`),
"already gone" (404) meaning success for deletes and "no such entity" for reads, the readable text of an error
answer, and strict JSON: nothing FIROS sends holds NaN or Infinity (`ros_conversion` writes them as strings). Updates
are built from attributes encoded once each (`encode_attribute` gives the attribute's JSON text, whose length the
sender uses to pack requests under the limit; `update_body` joins them). The request and answer shapes of each
version are its subclass's (`ngsi_v1`, `ngsi_v2`, `ngsi_ld`, chosen once from `ngsi_version` by
`ngsi_versions.client_for`). A client object is not shared between threads without its lock; each thread that talks
to the broker has its own. Each request is told to the client's ``observer`` (``fn(status, seconds)``, the metrics)
with its HTTP status class (``"2xx"``, ``"4xx"``, ...) or ``"timeout"`` / ``"connection"``.
"""

import abc
import datetime
import http.client
import json
import socket
import threading
import time
import urllib.parse

COMMAND = "COMMAND"
DESCRIPTIONS = "descriptions"
NOT_FOUND = 404
TOO_LARGE = 413


class BrokerUnavailable(Exception):
    """The broker cannot be reached or answered with a server error: keep the data and retry later."""


class BrokerError(Exception):
    """The broker refused a request; ``status`` is its HTTP status (or the one its body names), the text carries
    its answer."""

    def __init__(self, status, text):
        super().__init__(f"broker answered {status}: {text[:300]}")
        self.status = status


class RequestTooLarge(BrokerError):
    """A request over the broker's size limit: refused by the broker (413) or never sent (over
    ``max_request_size``). ``size`` is its size in bytes when known."""

    def __init__(self, text, size=None):
        super().__init__(TOO_LARGE, text)
        self.size = size


class NotificationError(ValueError):
    """A notification body is not one of the configured NGSI version."""


def notified_entities(data):
    """The entities of a notification's "data" member (NGSI v2 and NGSI-LD): a list of objects each with a string
    "id"; NotificationError otherwise."""
    if not isinstance(data, list):
        raise NotificationError("\"data\" must be a list of entities")
    for entity in data:
        if not isinstance(entity, dict) or not isinstance(entity.get("id"), str):
            raise NotificationError("every entity in \"data\" needs a string \"id\"")
    return data


def problem_text(parsed, text):
    """The readable part of an error answer: NGSI-LD ProblemDetails ("title: detail [type]"), Orion v2's
    {"error", "description"}, or the raw text."""
    if isinstance(parsed, dict):
        if "type" in parsed and ("title" in parsed or "detail" in parsed):
            kind = str(parsed.get("type", "")).rsplit("/", 1)[-1]
            title = parsed.get("title") or kind
            detail = parsed.get("detail")
            return f"{title}: {detail} [{kind}]" if detail else f"{title} [{kind}]"
        if "error" in parsed and "description" in parsed:
            return f"{parsed['error']}: {parsed['description']}"
    return text


_STRICT_ENCODER = json.JSONEncoder(separators=(",", ":"), allow_nan=False)   # made once: json.dumps with these
                                                                           # arguments makes one a call


def strict_json(obj):
    """Compact JSON text of ``obj``; ValueError for NaN or an infinity (JSON has none)."""
    return _STRICT_ENCODER.encode(obj)


def json_string(text):
    """A str as JSON text (the json module's own C quoting, the cheapest way for names and ids)."""
    return json.encoder.encode_basestring_ascii(text)


def json_member(name, value):
    """``"name":<value as JSON>``: one member of a JSON object, for bodies built from parts."""
    return json_string(name) + ":" + strict_json(value)


def iso_utc(ts):
    return datetime.datetime.fromtimestamp(ts, datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%fZ")[:-4] + "Z"


def quote(text):
    """``text`` as one URL path segment."""
    return urllib.parse.quote(str(text), safe="")


class NgsiClient(abc.ABC):
    """One connection to the broker. Subclasses speak one NGSI version: they fill in the abstract methods (the
    request and answer shapes) and may change the hooks (headers, ids, answer checks)."""

    version = None              # "v1", "v2" or "ld": the ngsi_version value the subclass speaks
    watches_command = False     # True: subscriptions also watch COMMAND, so that a repeated command notifies

    def __init__(self, settings, timeout=5.0, observer=None):
        self.settings = settings
        self.observer = observer    # fn(status class or "timeout"/"connection", seconds) after each request
        self.host = settings.broker_address
        self.port = settings.broker_port
        self.type = settings.context_type
        self.timeout = timeout
        self.max_request_size = settings.max_request_size
        self.lock = threading.Lock()
        self._conn = None
        self.headers = {"Accept": "application/json"}
        self.headers.update(self.version_headers(settings))

    # --- what each version fills in ----------------------------------------------------------------------------
    def version_headers(self, settings):
        """Headers every request of this version carries (tenant, @context)."""
        return {}

    def check_answer(self, parsed):
        """Raise BrokerError when a successful HTTP answer reports an error in its body (NGSI v1 does)."""

    def entity_id(self, robot):
        """The broker's entity id of a robot."""
        return robot

    def robot_of(self, entity_id):
        """The robot name of a broker entity id, or None when the id is not one FIROS makes."""
        return entity_id if isinstance(entity_id, str) else None

    @abc.abstractmethod
    def encode_attribute(self, name, atype, value):
        """The JSON text of one attribute as this version's update carries it (a plain, decoded ``value``);
        ValueError (NgsiEncodingError) when the value is not JSON-safe."""

    @abc.abstractmethod
    def update_body(self, encoded):
        """The body (bytes) of one update request of ``encoded``: {robot: [encode_attribute texts]}."""

    @abc.abstractmethod
    def _send_update(self, body):
        """Send an update body built by update_body."""

    @abc.abstractmethod
    def _delete_entity(self, robot):
        """Delete the robot's entity (BrokerError 404 when the broker has none)."""

    @abc.abstractmethod
    def _get_entity(self, robot):
        """{attr: {"type", "value"}} of the robot's entity, or None (or BrokerError 404) when there is none."""

    @abc.abstractmethod
    def subscribe(self, robot, url, length, throttling, now, attrs=()):
        """Subscribe to changes of the entity's ``attrs`` (empty: any attribute); returns the subscription id."""

    @abc.abstractmethod
    def refresh(self, sub_id, length, now):
        """Push the subscription's expiry ``length`` seconds ahead; BrokerError 404 if the broker forgot it."""

    @abc.abstractmethod
    def _unsubscribe(self, sub_id):
        """Remove the subscription (BrokerError 404 when the broker has none)."""

    @abc.abstractmethod
    def parse_notification(self, body):
        """[(entity id, entity type, {attr: (type, decoded value)})] from a notification body (parsed JSON);
        NotificationError when the body is not a notification this version's broker sends."""

    # --- common ------------------------------------------------------------------------------------------------
    def update(self, entities):
        """Append/update attributes. ``entities``: {robot: {attr: (type, value)}} with plain (decoded) values."""
        if entities:
            self.send_update({robot: [self.encode_attribute(name, atype, value)
                                      for name, (atype, value) in attrs.items()]
                              for robot, attrs in entities.items()})

    def send_update(self, encoded):
        """Send one update of attributes already encoded ({robot: [encode_attribute texts]});
        RequestTooLarge without sending anything when its body would be over ``max_request_size``."""
        body = self.update_body(encoded)
        if len(body) > self.max_request_size:
            raise RequestTooLarge(f"an update of {len(body)} bytes is over max_request_size "
                                  f"({self.max_request_size} bytes)", len(body))
        self._send_update(body)

    def body_overhead(self):
        """Bytes of an update body that carries nothing."""
        return len(self.update_body({}))

    def entity_overhead(self, robot):
        """Bytes one more robot adds to an update body, besides its attributes and one comma each."""
        return len(self.update_body({robot: []})) - self.body_overhead() + 1

    def delete_entity(self, robot):
        """Delete the robot's entity; an entity that is already gone is fine."""
        try:
            self._delete_entity(robot)
        except BrokerError as exc:
            if exc.status != NOT_FOUND:
                raise

    def get_entity(self, robot):
        """{attr: {"type", "value"}} of the robot's entity with decoded values, or None when the broker has none."""
        try:
            return self._get_entity(robot)
        except BrokerError as exc:
            if exc.status == NOT_FOUND:
                return None
            raise

    def unsubscribe(self, sub_id):
        """Remove a subscription; one the broker no longer has is fine."""
        try:
            self._unsubscribe(sub_id)
        except BrokerError as exc:
            if exc.status != NOT_FOUND:
                raise

    def close(self):
        if self._conn is not None:
            self._conn.close()
            self._conn = None

    def request(self, method, path, body=None, ok=(200, 201, 204), data=None):
        """Send one request (``body`` as JSON, or ``data``, bytes of JSON text) and return (status, headers,
        parsed JSON or None)."""
        headers = dict(self.headers)
        if body is not None:
            data = strict_json(body).encode("utf-8")
        if data is not None:
            headers["Content-Type"] = "application/json"
        started, outcome = time.monotonic(), "connection"
        try:
            status, resp_headers, raw = self._exchange(method, path, headers, data)
            outcome = f"{status // 100}xx"
        except BrokerUnavailable as exc:
            if isinstance(exc.__context__, (socket.timeout, TimeoutError)):
                outcome = "timeout"
            raise
        finally:
            if self.observer is not None:
                try:
                    self.observer(outcome, time.monotonic() - started)
                except Exception:   # a metric must never fail a request
                    pass
        return self._answer(status, resp_headers, raw, data, ok)

    def _exchange(self, method, path, headers, data):
        """(status, headers, raw body) of one request, on the kept-alive connection (made again once if the broker
        had dropped it); BrokerUnavailable when the broker cannot be reached."""
        for attempt in (1, 2):
            if self._conn is None:
                self._conn = http.client.HTTPConnection(self.host, self.port, timeout=self.timeout)
            try:
                self._conn.request(method, path, body=data, headers=headers)
                response = self._conn.getresponse()
                raw = response.read()
                status = response.status
                resp_headers = {k.lower(): v for k, v in response.getheaders()}
                if response.will_close:
                    self.close()
                return status, resp_headers, raw
            except (http.client.RemoteDisconnected, BrokenPipeError, ConnectionResetError,
                    http.client.CannotSendRequest, http.client.ResponseNotReady) as exc:
                self.close()
                if attempt == 2:
                    raise BrokerUnavailable(f"broker {self.host}:{self.port} dropped the connection: {exc}") from None
            except (OSError, http.client.HTTPException) as exc:
                self.close()
                raise BrokerUnavailable(f"cannot reach the broker at {self.host}:{self.port}: {exc}") from None

    def _answer(self, status, resp_headers, raw, data, ok):
        """(status, headers, parsed JSON or None) of an answer; the BrokerError its status (or body) says."""
        text = raw.decode("utf-8", "replace")
        parsed = None
        if text.strip():
            try:
                parsed = json.loads(text)
            except ValueError:
                parsed = None
        if status >= 500:
            raise BrokerUnavailable(f"broker answered {status}: {problem_text(parsed, text)[:200]}")
        if status == TOO_LARGE:
            raise RequestTooLarge(problem_text(parsed, text), len(data or b""))
        if status not in ok:
            raise BrokerError(status, problem_text(parsed, text))
        self.check_answer(parsed)
        return status, resp_headers, parsed


def local_address_towards(host, port):
    """The local IPv4 address this machine uses to reach host:port (no packet is sent)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.connect((socket.gethostbyname(host), port))
        return sock.getsockname()[0]
