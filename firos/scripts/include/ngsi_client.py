"""Talking to the NGSI context broker (Orion): one HTTP/1.1 keep-alive connection per client object, and the
request and answer shapes of NGSI v2 and NGSI v1 for every call FIROS makes.

Owns: entity updates in batches (v2 `POST /v2/op/update`, v1 `updateContext` APPEND), entity read and delete,
subscriptions (create, refresh before expiry, remove), and parsing broker notifications of both formats into
`(entity id, {attribute: (type, value)})`. Attribute values go out through `include.ngsi_encoding` (v1 `%27` text,
v2 percent-encoded strings) and come back decoded. `BrokerUnavailable` = cannot reach the broker or it answered
5xx (worth retrying); `BrokerError` = the broker refused the request (4xx; retrying the same thing will not help).
A client object is not shared between threads without its lock; each thread that talks to the broker has its own.
"""

import datetime
import http.client
import json
import socket
import threading
import urllib.parse

from include import ngsi_encoding

COMMAND = "COMMAND"
DESCRIPTIONS = "descriptions"

LD_BASE = "/ngsi-ld/v1"
LD_CONTEXT_REL = "http://www.w3.org/ns/json-ld#context"
LD_MESSAGE_TYPE = "messageType"     # NGSI-LD: the sub-Property carrying an attribute's message type
LD_PLAIN_TYPES = (COMMAND, "DescriptionData")   # attribute types FIROS does not write as messageType
LD_ATTRIBUTE_TYPES = ("Property", "Relationship", "GeoProperty", "LanguageProperty", "JsonProperty",
                      "VocabProperty", "ListProperty", "ListRelationship")
LD_NOT_ATTRIBUTES = ("id", "type", "@context", "scope", "createdAt", "modifiedAt", "deletedAt", "location",
                     "observationSpace", "operationSpace")


class BrokerUnavailable(Exception):
    """The broker cannot be reached or answered with a server error: keep the data and retry later."""


class BrokerError(Exception):
    """The broker refused a request (4xx); the text carries its answer."""

    def __init__(self, status, text):
        super().__init__(f"broker answered {status}: {text[:300]}")
        self.status = status


class NotificationError(ValueError):
    """A notification body is not an NGSI v1, v2 or NGSI-LD notification."""


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


def iso_utc(ts):
    return datetime.datetime.fromtimestamp(ts, datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%fZ")[:-4] + "Z"


def iso_duration(seconds):
    return f"PT{int(round(seconds))}S"


def encode_value(version, value):
    """An attribute value as it goes on the wire: v1 message objects are %27 JSON text, v2 strings encoded."""
    if version == "v1":
        if isinstance(value, dict):
            return ngsi_encoding.encode_v1(value)
        return ngsi_encoding.encode_v2(value)
    return ngsi_encoding.encode_v2(value)


def decode_value(version, value):
    """The inverse of encode_value; a v1 text that is not a %27 JSON object stays a (decoded) string."""
    if isinstance(value, str):
        stripped = value.strip()
        if stripped.startswith("{"):
            try:
                decoded = ngsi_encoding.decode_v1(stripped)
                if isinstance(decoded, dict):
                    return decoded
            except ValueError:
                pass
    return ngsi_encoding.decode_v2(value)


class NgsiClient:
    """One connection to the broker speaking NGSI ``version`` ("v1", "v2" or "ld")."""

    def __init__(self, settings, timeout=5.0):
        self.settings = settings
        self.version = settings.ngsi_version
        self.host = settings.broker_address
        self.port = settings.broker_port
        self.type = settings.context_type
        self.timeout = timeout
        self.lock = threading.Lock()
        self._conn = None
        self.headers = {"Accept": "application/json"}
        if self.version == "ld":
            # NGSI-LD names the @context of a JSON body (and of the terms in a query) in a Link header
            self.headers["Link"] = f'<{settings.ld_context}>; rel="{LD_CONTEXT_REL}"; type="application/ld+json"'
            if settings.fiware_service:
                self.headers["NGSILD-Tenant"] = settings.fiware_service
        else:
            if settings.fiware_service:
                self.headers["Fiware-Service"] = settings.fiware_service
            if settings.fiware_servicepath:
                self.headers["Fiware-ServicePath"] = settings.fiware_servicepath

    # --- names --------------------------------------------------------------------------------------------
    def entity_id(self, robot):
        """The broker's entity id of a robot (NGSI-LD: a URN)."""
        if self.version == "ld":
            return ngsi_encoding.ld_entity_id(self.type, robot)
        return robot

    def robot_of(self, entity_id):
        """The robot name of a broker entity id, or None when the id is not one FIROS makes."""
        if self.version != "ld":
            return entity_id if isinstance(entity_id, str) else None
        try:
            return ngsi_encoding.robot_from_ld_entity_id(entity_id, self.type)
        except ngsi_encoding.NgsiEncodingError:
            return None

    # --- HTTP -------------------------------------------------------------------------------------------------
    def close(self):
        if self._conn is not None:
            self._conn.close()
            self._conn = None

    def request(self, method, path, body=None, ok=(200, 201, 204)):
        """Send one request (JSON body) and return (status, headers, parsed JSON or None)."""
        data = None
        headers = dict(self.headers)
        if body is not None:
            data = json.dumps(body, separators=(",", ":")).encode("utf-8")
            headers["Content-Type"] = "application/json"
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
                break
            except (http.client.RemoteDisconnected, BrokenPipeError, ConnectionResetError,
                    http.client.CannotSendRequest, http.client.ResponseNotReady) as exc:
                self.close()
                if attempt == 2:
                    raise BrokerUnavailable(f"broker {self.host}:{self.port} dropped the connection: {exc}") from None
            except (OSError, http.client.HTTPException) as exc:
                self.close()
                raise BrokerUnavailable(f"cannot reach the broker at {self.host}:{self.port}: {exc}") from None
        text = raw.decode("utf-8", "replace")
        parsed = None
        if text.strip():
            try:
                parsed = json.loads(text)
            except ValueError:
                parsed = None
        if status >= 500:
            raise BrokerUnavailable(f"broker answered {status}: {problem_text(parsed, text)[:200]}")
        if status not in ok:
            raise BrokerError(status, problem_text(parsed, text))
        if self.version == "v1" and isinstance(parsed, dict):
            _raise_v1_error(parsed)
        return status, resp_headers, parsed

    # --- entities ---------------------------------------------------------------------------------------------
    def update(self, entities):
        """Append/update attributes. ``entities``: {id: {attr: (type, value)}} with plain (decoded) values."""
        if not entities:
            return
        if self.version == "ld":
            self._ld_upsert(entities)
        elif self.version == "v2":
            payload = []
            for eid, attrs in entities.items():
                entity = {"id": eid, "type": self.type}
                for name, (atype, value) in attrs.items():
                    entity[name] = {"type": atype, "value": encode_value("v2", value)}
                payload.append(entity)
            self.request("POST", "/v2/op/update", {"actionType": "append", "entities": payload})
        else:
            elements = []
            for eid, attrs in entities.items():
                elements.append({"type": self.type, "isPattern": "false", "id": eid, "attributes": [
                    {"name": name, "type": atype, "value": encode_value("v1", value)}
                    for name, (atype, value) in attrs.items()]})
            self.request("POST", "/v1/updateContext", {"contextElements": elements, "updateAction": "APPEND"})

    def _ld_upsert(self, entities):
        """NGSI-LD batch upsert with options=update: entities are created when missing, otherwise the given
        attributes are replaced and the others kept (ETSI GS CIM 009 5.6.8 / 6.15.3.1). A 207 answer lists the
        entities the broker refused: that is a BrokerError naming them."""
        payload = []
        for robot, attrs in entities.items():
            entity = {"id": self.entity_id(robot), "type": self.type}
            for name, (atype, value) in attrs.items():
                entity[name] = ld_property(atype, value)
            payload.append(entity)
        status, _, answer = self.request("POST", f"{LD_BASE}/entityOperations/upsert?options=update", payload,
                                         ok=(200, 201, 204, 207))
        if status == 207:
            errors = (answer or {}).get("errors") if isinstance(answer, dict) else None
            if errors:
                text = "; ".join(f"{e.get('entityId')}: {problem_text(e.get('error'), json.dumps(e.get('error')))}"
                                 for e in errors if isinstance(e, dict))
                raise BrokerError(207, f"batch upsert refused for {text}")

    def delete_entity(self, eid):
        """Delete the entity; an entity that is already gone is fine."""
        try:
            if self.version == "ld":
                self.request("DELETE", f"{LD_BASE}/entities/{_q(self.entity_id(eid))}")
            elif self.version == "v2":
                self.request("DELETE", f"/v2/entities/{_q(eid)}?type={_q(self.type)}")
            else:
                self.request("POST", "/v1/updateContext", {"contextElements": [
                    {"type": self.type, "isPattern": "false", "id": eid}], "updateAction": "DELETE"})
        except BrokerError as exc:
            if exc.status != 404 and "404" not in str(exc):
                raise

    def get_entity(self, eid):
        """{attr: {"type", "value"}} of the entity with decoded values, or None when the broker has no such entity."""
        try:
            if self.version == "ld":
                _, _, body = self.request("GET", f"{LD_BASE}/entities/{_q(self.entity_id(eid))}")
                if not isinstance(body, dict):
                    return None
                # the message type where FIROS wrote one, else the NGSI-LD attribute type ("Property")
                return {name: {"type": atype or _ld_kind(body[name]), "value": value}
                        for name, (atype, value) in ld_attributes(body, strict=False).items()}
            if self.version == "v2":
                _, _, body = self.request("GET", f"/v2/entities/{_q(eid)}?type={_q(self.type)}")
                if not isinstance(body, dict):
                    return None
                return {name: {"type": attr.get("type"), "value": decode_value("v2", attr.get("value"))}
                        for name, attr in body.items() if isinstance(attr, dict)}
            _, _, body = self.request("POST", "/v1/queryContext", {
                "entities": [{"type": self.type, "isPattern": "false", "id": eid}]})
        except BrokerError as exc:
            if exc.status == 404 or "404" in str(exc):
                return None
            raise
        for response in (body or {}).get("contextResponses", []):
            element = response.get("contextElement", {})
            if element.get("id") == eid:
                return {a.get("name"): {"type": a.get("type"), "value": decode_value("v1", a.get("value"))}
                        for a in element.get("attributes", []) if isinstance(a, dict)}
        return None

    # --- subscriptions ----------------------------------------------------------------------------------------
    def subscribe(self, eid, url, length, throttling, now, attrs=()):
        """Subscribe to changes of the entity's ``attrs`` (empty: any attribute); returns the subscription id."""
        if self.version == "ld":
            body = {"type": "Subscription", "description": f"FIROS commands for {eid}",
                    "entities": [{"id": self.entity_id(eid), "type": self.type}],
                    "notification": {"format": "normalized",
                                     "endpoint": {"uri": url, "accept": "application/json"}},
                    "expiresAt": iso_utc(now + length)}
            if attrs:
                body["watchedAttributes"] = list(attrs)
            if throttling > 0:
                body["throttling"] = throttling
            _, headers, _ = self.request("POST", f"{LD_BASE}/subscriptions", body)
            sub_id = urllib.parse.unquote(headers.get("location", "").rstrip("/").rsplit("/", 1)[-1])
            if not sub_id:
                raise BrokerError(201, "subscription created without a Location header")
            return sub_id
        if self.version == "v2":
            body = {"description": f"FIROS commands for {eid}",
                    "subject": {"entities": [{"id": eid, "type": self.type}], "condition": {"attrs": list(attrs)}},
                    "notification": {"http": {"url": url}, "attrs": [], "attrsFormat": "normalized"},
                    "expires": iso_utc(now + length), "throttling": int(round(throttling))}
            _, headers, _ = self.request("POST", "/v2/subscriptions", body)
            location = headers.get("location", "")
            sub_id = location.rstrip("/").rsplit("/", 1)[-1]
            if not sub_id:
                raise BrokerError(201, "subscription created without a Location header")
            return sub_id
        body = {"entities": [{"type": self.type, "isPattern": "false", "id": eid}], "attributes": [],
                "reference": url, "duration": iso_duration(length),
                "notifyConditions": [{"type": "ONCHANGE", "condValues": list(attrs)}],
                "throttling": iso_duration(throttling)}
        _, _, answer = self.request("POST", "/v1/subscribeContext", body)
        sub_id = ((answer or {}).get("subscribeResponse") or {}).get("subscriptionId")
        if not sub_id:
            raise BrokerError(200, f"subscribeContext answered without a subscriptionId: {answer}")
        return sub_id

    def refresh(self, sub_id, length, now):
        """Push the subscription's expiry ``length`` seconds ahead; BrokerError 404 if the broker forgot it."""
        if self.version == "ld":
            self.request("PATCH", f"{LD_BASE}/subscriptions/{_q(sub_id)}", {"expiresAt": iso_utc(now + length)})
        elif self.version == "v2":
            self.request("PATCH", f"/v2/subscriptions/{_q(sub_id)}", {"expires": iso_utc(now + length)})
        else:
            self.request("POST", "/v1/updateContextSubscription",
                         {"subscriptionId": sub_id, "duration": iso_duration(length)})

    def unsubscribe(self, sub_id):
        try:
            if self.version == "ld":
                self.request("DELETE", f"{LD_BASE}/subscriptions/{_q(sub_id)}")
            elif self.version == "v2":
                self.request("DELETE", f"/v2/subscriptions/{_q(sub_id)}")
            else:
                self.request("POST", "/v1/unsubscribeContext", {"subscriptionId": sub_id})
        except BrokerError as exc:
            if exc.status != 404 and "404" not in str(exc):
                raise


def _q(text):
    return urllib.parse.quote(str(text), safe="")


def _raise_v1_error(answer):
    """NGSI v1 reports errors with HTTP 200 and an errorCode / statusCode inside the body."""
    error = answer.get("errorCode")
    for wrapper in ("subscribeError", "orionError"):      # updateContextSubscription / parse errors
        inner = answer.get(wrapper)
        if isinstance(inner, dict):
            error = inner.get("errorCode", inner)
    if isinstance(error, dict) and str(error.get("code", "200")) != "200":
        raise BrokerError(int(error.get("code", 400)) if str(error.get("code", "")).isdigit() else 400,
                          json.dumps(answer))
    for key in ("contextResponses",):
        for response in answer.get(key, []) or []:
            status = (response or {}).get("statusCode") or {}
            code = str(status.get("code", "200"))
            if code != "200":
                raise BrokerError(int(code) if code.isdigit() else 400, json.dumps(answer))
    status = answer.get("statusCode")
    if isinstance(status, dict) and str(status.get("code", "200")) != "200":
        code = str(status.get("code"))
        raise BrokerError(int(code) if code.isdigit() else 400, json.dumps(answer))


def ld_property(atype, value):
    """An NGSI-LD Property for a FIROS attribute: the value as it is; a message value (a dict with firosstamp)
    also gets ``observedAt`` (its stamp) and its message type as the sub-Property ``messageType``."""
    prop = {"type": "Property", "value": value}
    if isinstance(value, dict):
        _, stamp = ngsi_encoding.split_firosstamp(value)
        if stamp is not None:
            prop["observedAt"] = iso_utc(stamp)
    if atype not in LD_PLAIN_TYPES:
        prop[LD_MESSAGE_TYPE] = {"type": "Property", "value": atype}
    return prop


def _ld_kind(attr):
    """The NGSI-LD type of an attribute (of its first instance when it has several)."""
    if isinstance(attr, list) and attr:
        attr = attr[0]
    return attr.get("type") if isinstance(attr, dict) else None


def ld_attributes(entity, strict=True):
    """{name: (message type or None, value)} of an NGSI-LD entity in normalized form. An attribute given as a
    list of instances (datasetId) counts by its default instance (the one without datasetId, else the first).
    ``strict``: a malformed attribute is a NotificationError, otherwise it is left out."""
    attrs = {}
    eid = entity.get("id")
    for name, attr in entity.items():
        if name in LD_NOT_ATTRIBUTES:
            continue
        if isinstance(attr, list) and attr:
            attr = next((a for a in attr if isinstance(a, dict) and "datasetId" not in a), attr[0])
        problem = None
        if not isinstance(attr, dict):
            problem = f"attribute \"{name}\" of \"{eid}\" must be an object"
        elif attr.get("type") not in LD_ATTRIBUTE_TYPES:
            problem = f"attribute \"{name}\" of \"{eid}\" needs a \"type\" such as \"Property\""
        elif attr["type"] == "Relationship":
            if "object" not in attr:
                problem = f"Relationship \"{name}\" of \"{eid}\" needs an \"object\""
        elif not any(key in attr for key in ("value", "json", "vocab", "languageMap", "valueList",
                                             "objectList")):
            problem = f"{attr['type']} \"{name}\" of \"{eid}\" needs a \"value\""
        if problem:
            if strict:
                raise NotificationError(problem)
            continue
        if attr["type"] == "Relationship":
            value = attr["object"]
        else:
            value = next(attr[key] for key in ("value", "json", "vocab", "languageMap", "valueList", "objectList")
                         if key in attr)
        mtype = attr.get(LD_MESSAGE_TYPE)
        mtype = mtype.get("value") if isinstance(mtype, dict) else None
        attrs[name] = (mtype if isinstance(mtype, str) else (COMMAND if name == COMMAND else None), value)
    return attrs


def parse_ld_notification(body):
    """[(entity id, entity type, {attr: (message type or None, value)})] from an NGSI-LD notification
    (ETSI GS CIM 009 5.3.1: {"id", "type": "Notification", "subscriptionId", "notifiedAt", "data": [entities]});
    NotificationError when the body is not one."""
    if not isinstance(body, dict):
        raise NotificationError("a notification must be a JSON object")
    if body.get("type") != "Notification" or "data" not in body:
        raise NotificationError("not an NGSI-LD notification: expected {\"type\": \"Notification\", "
                                "\"data\": [entities], ...}")
    data = body["data"]
    if not isinstance(data, list):
        raise NotificationError("\"data\" must be a list of entities")
    result = []
    for entity in data:
        if not isinstance(entity, dict) or not isinstance(entity.get("id"), str):
            raise NotificationError("every entity in \"data\" needs a string \"id\"")
        result.append((entity["id"], entity.get("type"), ld_attributes(entity)))
    return result


def parse_notification(body, version="v2"):
    """[(entity id, entity type, {attr: (type, decoded value)})] from a notification: NGSI-LD's when ``version``
    is "ld", else v1's or v2's (told apart by their shape); NotificationError when the body is none of these."""
    if version == "ld":
        return parse_ld_notification(body)
    if not isinstance(body, dict):
        raise NotificationError("a notification must be a JSON object")
    result = []
    if "data" in body:
        data = body["data"]
        if not isinstance(data, list):
            raise NotificationError("\"data\" must be a list of entities")
        for entity in data:
            if not isinstance(entity, dict) or not isinstance(entity.get("id"), str):
                raise NotificationError("every entity in \"data\" needs a string \"id\"")
            attrs = {}
            for name, attr in entity.items():
                if name in ("id", "type"):
                    continue
                if not isinstance(attr, dict) or "value" not in attr:
                    raise NotificationError(f"attribute \"{name}\" of \"{entity['id']}\" needs a \"value\"")
                attrs[name] = (attr.get("type"), decode_value("v2", attr["value"]))
            result.append((entity["id"], entity.get("type"), attrs))
        return result
    if "contextResponses" in body:
        responses = body["contextResponses"]
        if not isinstance(responses, list):
            raise NotificationError("\"contextResponses\" must be a list")
        for response in responses:
            element = response.get("contextElement") if isinstance(response, dict) else None
            if not isinstance(element, dict) or not isinstance(element.get("id"), str):
                raise NotificationError("every contextResponse needs a contextElement with a string \"id\"")
            attributes = element.get("attributes", [])
            if not isinstance(attributes, list):
                raise NotificationError("\"attributes\" must be a list")
            attrs = {}
            for attr in attributes:
                if not isinstance(attr, dict) or not isinstance(attr.get("name"), str) or "value" not in attr:
                    raise NotificationError("every attribute needs a string \"name\" and a \"value\"")
                attrs[attr["name"]] = (attr.get("type"), decode_value("v1", attr["value"]))
            result.append((element["id"], element.get("type"), attrs))
        return result
    raise NotificationError("not an NGSI notification: expected \"data\" (v2) or \"contextResponses\" (v1)")


def local_address_towards(host, port):
    """The local IPv4 address this machine uses to reach host:port (no packet is sent)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.connect((socket.gethostbyname(host), port))
        return sock.getsockname()[0]
