"""Subscriptions and notifications: which changes notify whom, in which body, and the sending itself.

A ``Subscription`` is stored in its tenant whichever API created it (NGSI v1 ``subscribeContext`` makes one with
``attrsFormat`` ``legacy``, as Orion lists v1 subscriptions in ``GET /v2/subscriptions``). After every write the
API modules call ``Notifications.entity_changed`` under the store lock; it picks the subscriptions whose subject
matches the entity, whose condition attributes changed, that are active, not expired and not throttled, counts
the notification (``timesSent``, ``lastNotification``) and hands the body to the ``Notifier``.

The ``Notifier`` sends from worker threads, one per destination (scheme, host, port), reusing the HTTP
connection and giving up after a short timeout, so a dead or slow subscriber never blocks the broker or the
other subscribers, and notifications to one receiver keep their order. Results come back as
``lastSuccess``/``lastFailure``/``failsCounter``.
"""

import http.client
import json
import logging
import queue
import secrets
import threading
import time
import uuid
from urllib.parse import urlsplit

from . import model

log = logging.getLogger("ngsi_broker.notify")

USER_AGENT = "orion/3.9.0 (ngsi stand-in broker for tests)"
V2_FORMATS = ("normalized", "keyValues", "values", "legacy")
QUEUE_LIMIT = 10000


def new_subscription_id():
    """24 hexadecimal digits, like Orion's (MongoDB ObjectId) subscription ids."""
    return secrets.token_hex(12)


class EntitySelector:
    """One element of a subscription's subject: id or idPattern, optional type or typePattern."""

    def __init__(self, raw):
        self.raw = raw
        self.id = raw.get("id")
        self.id_pattern = model.compile_pattern(raw["idPattern"]) if raw.get("idPattern") is not None else None
        self.type = raw.get("type")
        self.type_pattern = (model.compile_pattern(raw["typePattern"], "entity typePattern")
                             if raw.get("typePattern") is not None else None)

    def matches(self, entity):
        if self.id is not None and self.id != entity.id:
            return False
        if self.id_pattern is not None and not self.id_pattern.search(entity.id):
            return False
        if self.type and self.type != entity.type:
            return False
        if self.type_pattern is not None and not self.type_pattern.search(entity.type):
            return False
        return True


class Subscription:
    """A subscription of one tenant. Times are epoch seconds; ``expires`` None means never."""

    def __init__(self, sub_id, service, query_paths):
        self.id = sub_id
        self.service = service
        self.query_paths = query_paths
        self.description = None
        self.entities = []            # EntitySelector
        self.condition_attrs = []
        self.notify_attrs = []
        self.except_attrs = []
        self.only_changed_attrs = False
        self.attrs_format = "normalized"
        self.url = None
        self.expires = None
        self.throttling = 0.0
        self.status = "active"
        # statistics, as Orion reports them
        self.times_sent = 0
        self.last_notification = None
        self.last_success = None
        self.last_success_code = None
        self.last_failure = None
        self.last_failure_reason = None
        self.fails_counter = 0
        self._last_sent_monotonic = None
        # NGSI v1 bookkeeping (subscribeContext answers echo these)
        self.v1 = False
        self.v1_duration = None
        self.v1_throttling = None

    def is_expired(self, now):
        return self.expires is not None and now >= self.expires

    def current_status(self, now):
        if self.status == "active" and self.is_expired(now):
            return "expired"
        return self.status

    def matches(self, entity):
        return (model.service_path_matches(entity.service_path, self.query_paths)
                and any(selector.matches(entity) for selector in self.entities))

    def throttled(self, monotonic_now):
        return (self.throttling > 0 and self._last_sent_monotonic is not None
                and monotonic_now - self._last_sent_monotonic < self.throttling)

    def count_sent(self, now, monotonic_now):
        self.times_sent += 1
        self.last_notification = now
        self._last_sent_monotonic = monotonic_now

    def render(self, now):
        """This subscription as ``GET /v2/subscriptions`` shows it."""
        body = {"id": self.id}
        if self.description is not None:
            body["description"] = self.description
        body["subject"] = {"entities": [dict(s.raw) for s in self.entities],
                           "condition": {"attrs": list(self.condition_attrs)}}
        notification = {}
        if self.except_attrs:
            notification["exceptAttrs"] = list(self.except_attrs)
        else:
            notification["attrs"] = list(self.notify_attrs)
        notification["onlyChangedAttrs"] = self.only_changed_attrs
        notification["attrsFormat"] = self.attrs_format
        notification["http"] = {"url": self.url}
        if self.times_sent:
            notification["timesSent"] = self.times_sent
        if self.last_notification is not None:
            notification["lastNotification"] = model.iso_time(self.last_notification)
        if self.last_failure is not None:
            notification["lastFailure"] = model.iso_time(self.last_failure)
            if self.last_failure_reason:
                notification["lastFailureReason"] = self.last_failure_reason
        if self.last_success is not None:
            notification["lastSuccess"] = model.iso_time(self.last_success)
            notification["lastSuccessCode"] = self.last_success_code
        if self.fails_counter:
            notification["failsCounter"] = self.fails_counter
        notification["covered"] = False
        body["notification"] = notification
        if self.expires is not None:
            body["expires"] = model.iso_time(self.expires)
        body["status"] = self.current_status(now)
        if self.throttling:
            body["throttling"] = int(self.throttling) if float(self.throttling).is_integer() else self.throttling
        return body


# --- building subscriptions from NGSI v2 bodies ----------------------------------------------------------

def _string_list(value, what):
    if not isinstance(value, list) or not all(isinstance(item, str) for item in value):
        raise model.bad_request(f"{what} must be an array of strings")
    return list(value)


def _entity_selectors(raw_entities):
    if not isinstance(raw_entities, list) or not raw_entities:
        raise model.bad_request("no subject entities specified")
    selectors = []
    for raw in raw_entities:
        if not isinstance(raw, dict):
            raise model.bad_request("subject entities must be JSON objects")
        has_id, has_pattern = raw.get("id") is not None, raw.get("idPattern") is not None
        if has_id == has_pattern:
            raise model.bad_request("a subject entity needs exactly one of id and idPattern")
        if has_id:
            model.check_identifier(raw["id"], "entity id")
        if raw.get("type") is not None and raw.get("typePattern") is not None:
            raise model.bad_request("a subject entity cannot have both type and typePattern")
        if raw.get("type") is not None:
            model.check_identifier(raw["type"], "entity type")
        unknown = set(raw) - {"id", "idPattern", "type", "typePattern"}
        if unknown:
            raise model.bad_request(f"unrecognized field in subject entity: {sorted(unknown)[0]}")
        selectors.append(EntitySelector(raw))
    return selectors


def check_url(url):
    if not isinstance(url, str):
        raise model.bad_request("Invalid URL")
    parts = urlsplit(url)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise model.bad_request("Invalid URL")
    try:
        parts.port  # noqa: B018 - raises ValueError on a bad port
    except ValueError:
        raise model.bad_request("Invalid URL") from None
    return url


def apply_v2_fields(sub, body, creating):
    """Validate a ``POST``/``PATCH /v2/subscriptions`` body and set its fields on ``sub`` (all or nothing).

    The fields are checked on a scratch copy first, so a bad PATCH changes nothing.
    """
    if not isinstance(body, dict):
        raise model.NgsiError(400, "ParseError", "Errors found in incoming JSON buffer")
    known = {"description", "subject", "notification", "expires", "status", "throttling"}
    unknown = set(body) - known
    if unknown:
        raise model.bad_request(f"unrecognized field: {sorted(unknown)[0]}")
    changes = {}
    if "description" in body:
        if not isinstance(body["description"], str) or model.value_has_forbidden_chars(body["description"]):
            raise model.bad_request("Invalid characters in description")
        changes["description"] = body["description"]
    if "subject" in body:
        subject = body["subject"]
        if not isinstance(subject, dict):
            raise model.bad_request("subject must be a JSON object")
        changes["entities"] = _entity_selectors(subject.get("entities"))
        condition = subject.get("condition", {})
        if not isinstance(condition, dict):
            raise model.bad_request("condition must be a JSON object")
        changes["condition_attrs"] = _string_list(condition.get("attrs", []), "condition attrs")
    elif creating:
        raise model.bad_request("no subject for subscription specified")
    if "notification" in body:
        notification = body["notification"]
        if not isinstance(notification, dict):
            raise model.bad_request("notification must be a JSON object")
        http_part = notification.get("http")
        if not isinstance(http_part, dict) or "url" not in http_part:
            raise model.bad_request("http notification has no url (only http notifications are supported)")
        changes["url"] = check_url(http_part["url"])
        if "attrs" in notification and "exceptAttrs" in notification:
            raise model.bad_request("http notification has attrs and exceptAttrs")
        changes["notify_attrs"] = _string_list(notification.get("attrs", []), "notification attrs")
        changes["except_attrs"] = _string_list(notification.get("exceptAttrs", []), "notification exceptAttrs")
        fmt = notification.get("attrsFormat", "normalized")
        if fmt not in V2_FORMATS:
            raise model.bad_request("invalid attrsFormat, accepted values: " + ", ".join(V2_FORMATS))
        changes["attrs_format"] = fmt
        only_changed = notification.get("onlyChangedAttrs", False)
        if not isinstance(only_changed, bool):
            raise model.bad_request("onlyChangedAttrs must be a boolean")
        changes["only_changed_attrs"] = only_changed
    elif creating:
        raise model.bad_request("no notification for subscription specified")
    if "expires" in body:
        expires = body["expires"]
        if expires is None or expires == "":
            changes["expires"] = None
        else:
            try:
                changes["expires"] = model.parse_iso_time(expires)
            except (ValueError, TypeError):
                raise model.bad_request("expires has an invalid format") from None
    if "status" in body:
        if body["status"] not in ("active", "inactive"):
            raise model.bad_request("status is not valid: it has to be either active or inactive")
        changes["status"] = body["status"]
    if "throttling" in body:
        throttling = body["throttling"]
        if isinstance(throttling, bool) or not isinstance(throttling, (int, float)):
            raise model.bad_request("throttling must be a number")
        if throttling < 0:
            raise model.bad_request("Negative Number not allowed for throttling")
        changes["throttling"] = float(throttling)
    for name, value in changes.items():
        setattr(sub, name, value)


# --- notification bodies --------------------------------------------------------------------------------

def notification_request(sub, entities, changed, correlator=None):
    """(body bytes, headers) of the notification ``sub`` sends about ``entities``."""
    if sub.attrs_format == "legacy":
        responses = []
        for entity in entities:
            names = model.select_attributes(entity, sub.notify_attrs, sub.except_attrs)
            responses.append(model.v1_context_element_response(entity, names))
        payload = {"subscriptionId": sub.id, "originator": "localhost", "contextResponses": responses}
    else:
        data = []
        for entity in entities:
            names = model.select_attributes(entity, sub.notify_attrs, sub.except_attrs)
            if sub.only_changed_attrs and changed is not None:
                names = [name for name in names if name in changed]
            data.append(model.v2_entity(entity, names, sub.attrs_format))
        payload = {"subscriptionId": sub.id, "data": data}
    headers = {
        "Content-Type": "application/json; charset=utf-8",
        "Accept": "application/json",
        "User-Agent": USER_AGENT,
        "Ngsiv2-AttrsFormat": sub.attrs_format,
        "Fiware-Correlator": correlator or str(uuid.uuid1()),
        "Fiware-ServicePath": entities[0].service_path if entities else "/",
    }
    if sub.service:
        headers["Fiware-Service"] = sub.service
    return json.dumps(payload).encode("utf-8"), headers


class Notifications:
    """Decides who is notified of a change and keeps the subscriptions' statistics."""

    def __init__(self, store, notifier):
        self.store = store
        self.notifier = notifier

    def entity_changed(self, tenant, entity, changed, created=False, correlator=None):
        """Called under the store lock after ``entity`` was written; ``changed`` names the attributes that
        changed (or, with forcedUpdate, the attributes the request named)."""
        if not changed and not created:
            return
        now, monotonic_now = time.time(), time.monotonic()
        snapshot = None
        for sub in tenant.subscriptions.values():
            if sub.status != "active" or sub.is_expired(now) or not sub.matches(entity):
                continue
            if sub.condition_attrs and not set(sub.condition_attrs) & set(changed):
                continue
            if sub.throttled(monotonic_now):
                continue
            snapshot = snapshot or entity.snapshot()
            self.send(tenant, sub, [snapshot], set(changed), now, monotonic_now, correlator)

    def send(self, tenant, sub, entities, changed, now=None, monotonic_now=None, correlator=None):
        """Count and queue one notification (under the store lock)."""
        now = time.time() if now is None else now
        monotonic_now = time.monotonic() if monotonic_now is None else monotonic_now
        body, headers = notification_request(sub, entities, changed, correlator)
        sub.count_sent(now, monotonic_now)
        self.notifier.post(sub.url, body, headers, lambda ok, code, reason: self._done(sub, ok, code, reason))

    def _done(self, sub, ok, code, reason):
        with self.store.lock:
            if ok:
                sub.last_success = time.time()
                sub.last_success_code = code
                sub.fails_counter = 0
            else:
                sub.last_failure = time.time()
                sub.last_failure_reason = reason
                sub.fails_counter += 1


# --- sending ----------------------------------------------------------------------------------------------

class _Destination(threading.Thread):
    """Sends the notifications for one (scheme, host, port) in order, over one kept-alive connection."""

    def __init__(self, scheme, host, port, timeout):
        super().__init__(name=f"notify-{host}:{port}", daemon=True)
        self.scheme, self.host, self.port, self.timeout = scheme, host, port, timeout
        self.queue = queue.Queue(maxsize=QUEUE_LIMIT)
        self._conn = None

    def _connection(self):
        if self._conn is None:
            cls = http.client.HTTPSConnection if self.scheme == "https" else http.client.HTTPConnection
            self._conn = cls(self.host, self.port, timeout=self.timeout)
        return self._conn

    def _drop_connection(self):
        if self._conn is not None:
            self._conn.close()
            self._conn = None

    def _post(self, path, body, headers):
        for attempt in (1, 2):
            reused = self._conn is not None
            conn = self._connection()
            try:
                conn.request("POST", path, body=body, headers=headers)
                response = conn.getresponse()
                response.read()
                if response.will_close:
                    self._drop_connection()
                return response.status, response.reason
            except (http.client.RemoteDisconnected, BrokenPipeError, ConnectionResetError):
                self._drop_connection()
                if not reused or attempt == 2:  # a fresh connection failing is a real failure
                    raise
            except Exception:
                self._drop_connection()
                raise
        raise ConnectionError("unreachable")

    def run(self):
        while True:
            item = self.queue.get()
            if item is None:
                self._drop_connection()
                return
            path, body, headers, done = item
            try:
                status, reason = self._post(path, body, headers)
            except (OSError, http.client.HTTPException) as exc:
                log.info("notification to %s://%s:%s%s failed: %s", self.scheme, self.host, self.port, path, exc)
                done(False, None, f"Couldn't connect to server: {exc}")
            else:
                ok = 200 <= status < 300
                if not ok:
                    log.info("notification to %s:%s%s answered %s %s", self.host, self.port, path, status, reason)
                done(ok, status, None if ok else f"HTTP {status} {reason}")


class Notifier:
    """Posts notification bodies from worker threads (one per destination) with a short timeout."""

    def __init__(self, timeout=2.0):
        self.timeout = timeout
        self._lock = threading.Lock()
        self._destinations = {}
        self._closed = False

    def post(self, url, body, headers, done):
        parts = urlsplit(url)
        scheme = parts.scheme
        port = parts.port or (443 if scheme == "https" else 80)
        path = parts.path or "/"
        if parts.query:
            path += "?" + parts.query
        key = (scheme, parts.hostname, port)
        with self._lock:
            if self._closed:
                return
            destination = self._destinations.get(key)
            if destination is None:
                destination = self._destinations[key] = _Destination(scheme, parts.hostname, port, self.timeout)
                destination.start()
        try:
            destination.queue.put_nowait((path, body, headers, done))
        except queue.Full:
            done(False, None, "too many notifications waiting for this receiver")

    def close(self, timeout=None):
        """Stop the workers (notifications still queued are sent first, each within its timeout)."""
        with self._lock:
            self._closed = True
            destinations = list(self._destinations.values())
        for destination in destinations:
            destination.queue.put(None)
        for destination in destinations:
            destination.join(timeout if timeout is not None else self.timeout + 1)
