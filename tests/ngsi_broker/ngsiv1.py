"""NGSI v1 (NGSI10) as Orion before 3.10 answered it, over the same store as NGSI v2.

``updateContext`` (APPEND, APPEND_STRICT, UPDATE, DELETE, REPLACE), ``queryContext`` (``isPattern`` regular
expressions, attribute filter, Orion's ``errorCode`` 404 "No context element found"), ``subscribeContext``
(ONCHANGE conditions, ISO 8601 ``duration`` and ``throttling``, Orion's initial notification),
``updateContextSubscription`` and ``unsubscribeContext``. The server maps ``/v1/<op>`` and ``/NGSI10/<op>`` here,
plus the three ``/v1/contextEntities`` convenience calls Orion kept after 3.10.

Per-element failures are answered, as Orion did, with HTTP 200 and an NGSI ``statusCode`` inside the body;
malformed requests raise ``model.NgsiError`` and the server renders them as Orion's ``orionError``.
"""

import time

from . import model
from .model import bad_request
from .subscriptions import Subscription, EntitySelector, check_url, new_subscription_id

UPDATE_ACTIONS = ("APPEND", "APPEND_STRICT", "UPDATE", "DELETE", "REPLACE")
DEFAULT_DURATION = "PT24H"
DEFAULT_LIMIT = 20
MAX_LIMIT = 1000
OK = {"code": "200", "reasonPhrase": "OK"}
NOT_FOUND = "No context element found"
ILLEGAL_VALUE = "Illegal value for JSON field"  # Orion's v1 answer to a forbidden character
INVALID_PARAMETER = "request parameter is invalid/not allowed"


def _is_pattern(raw):
    value = raw.get("isPattern", "false")
    if value in (True, "true", "TRUE", "True"):
        return True
    if value in (False, "false", "FALSE", "False", "", None):
        return False
    raise bad_request("invalid value for isPattern")


def _string_list(value, what):
    if value is None:
        return []
    if not isinstance(value, list) or not all(isinstance(item, str) for item in value):
        raise bad_request(f"{what} must be a list of strings")
    return list(value)


def _parse_attribute(raw):
    """One v1 attribute ({name, type, value, metadatas}) → (name, stored attribute)."""
    if not isinstance(raw, dict):
        raise bad_request("an attribute must be a JSON object")
    name = raw.get("name", "")
    model.check_identifier(name, "attribute name")
    attr_type = raw.get("type", "")
    if attr_type != "":
        model.check_identifier(attr_type, "attribute type")
    value = raw.get("value", "")
    model.check_attribute_value(attr_type, value, ILLEGAL_VALUE)
    metadata = {}
    for md in raw.get("metadatas", []) or []:
        if not isinstance(md, dict):
            raise bad_request("a metadata must be a JSON object")
        md_name = md.get("name", "")
        model.check_identifier(md_name, "metadata name")
        md_type = md.get("type", "")
        if md_type != "":
            model.check_identifier(md_type, "metadata type")
        model.check_attribute_value(md_type, md.get("value", ""), ILLEGAL_VALUE)
        metadata[md_name] = {"type": md_type, "value": md.get("value", "")}
    return name, {"type": attr_type, "value": value, "metadata": metadata}


def _parse_element(raw):
    if not isinstance(raw, dict):
        raise bad_request("a contextElement must be a JSON object")
    entity_id = raw.get("id", "")
    model.check_identifier(entity_id, "entity id")
    if _is_pattern(raw):
        raise bad_request("isPattern true is not allowed in updateContext")
    entity_type = raw.get("type", "") or ""
    if entity_type:
        model.check_identifier(entity_type, "entity type")
    attributes = raw.get("attributes", []) or []
    if not isinstance(attributes, list):
        raise bad_request("attributes must be a list")
    attrs = {}
    for attr in attributes:
        name, parsed = _parse_attribute(attr)
        attrs[name] = parsed
    return entity_id, entity_type, attrs


def _duration(text, what):
    try:
        return model.parse_duration(text)
    except ValueError:
        raise bad_request(f"invalid payload: wrong syntax for {what}: {text}") from None


class NgsiV1:
    """The NGSI v1 handlers over one store (shared with NGSI v2)."""

    def __init__(self, store, notifications, initial_notification=True):
        self.store = store
        self.notifications = notifications
        self.initial_notification = initial_notification

    # --- updateContext ------------------------------------------------------------------------------------
    def update_context(self, req):
        body = req.json()
        if not isinstance(body, dict):
            raise model.NgsiError(400, "ParseError", "JSON Parse Error")
        action = body.get("updateAction")
        if not isinstance(action, str) or action.upper() not in UPDATE_ACTIONS:
            raise bad_request("invalid update action type: right ones are: " + ", ".join(UPDATE_ACTIONS))
        action = action.upper()
        raw_elements = body.get("contextElements")
        if not isinstance(raw_elements, list) or not raw_elements:
            raise bad_request("empty contextElements")
        elements = [_parse_element(raw) for raw in raw_elements]  # all checked before any change
        responses = []
        with self.store.lock:
            tenant = self.store.tenant(req.tenant)
            for entity_id, entity_type, attrs in elements:
                status = self._update_one(req, tenant, action, entity_id, entity_type, attrs)
                responses.append({
                    "contextElement": {
                        "attributes": [model.v1_attribute(name, attr, with_value=False)
                                       for name, attr in attrs.items()],
                        "id": entity_id,
                        "isPattern": "false",
                        "type": entity_type,
                    },
                    "statusCode": status,
                })
        return req.json_response(200, {"contextResponses": responses})

    def _update_one(self, req, tenant, action, entity_id, entity_type, attrs):
        found = tenant.find(entity_id, entity_type or None, [(req.update_path, False)])
        entity = found[0] if found else None
        if action in ("APPEND", "APPEND_STRICT"):
            created = entity is None
            if created:
                entity = model.Entity(entity_id, entity_type, req.update_path)
                tenant.add(entity)
            elif action == "APPEND_STRICT":
                existing = [name for name in attrs if name in entity.attrs]
                if existing:
                    return {"code": "400", "reasonPhrase": "Bad Request",
                            "details": f"one or more of the attributes in the request already exist: "
                                       f"[ {', '.join(existing)} ]"}
            changed = model.set_attributes(entity, attrs)
            self.notifications.entity_changed(tenant, entity, changed, created=created, correlator=req.correlator)
            return dict(OK)
        if entity is None:
            return {"code": "404", "reasonPhrase": NOT_FOUND, "details": entity_id}
        if action in ("UPDATE", "DELETE"):
            missing = [name for name in attrs if name not in entity.attrs]
            if missing:
                return {"code": "472", "reasonPhrase": INVALID_PARAMETER,
                        "details": f"action: {action} - entity: [{entity.id}, {entity.type}] - "
                                   f"offending attribute: {missing[0]}"}
        if action == "DELETE":
            if not attrs:
                tenant.remove(entity)
            else:
                for name in attrs:
                    del entity.attrs[name]
                entity.modified = time.time()
            return dict(OK)
        changed = model.set_attributes(entity, attrs, replace=(action == "REPLACE"))
        self.notifications.entity_changed(tenant, entity, changed, correlator=req.correlator)
        return dict(OK)

    # --- queryContext -------------------------------------------------------------------------------------
    def _matchers(self, raw_entities):
        if not isinstance(raw_entities, list) or not raw_entities:
            raise bad_request("no entities in the request")
        matchers = []
        for raw in raw_entities:
            if not isinstance(raw, dict):
                raise bad_request("an entity must be a JSON object")
            entity_id = raw.get("id", "")
            entity_type = raw.get("type", "") or None
            if _is_pattern(raw):
                regex = model.compile_pattern(entity_id)
                matchers.append(lambda eid, etype, r=regex, t=entity_type:
                                r.search(eid) is not None and (t is None or etype == t))
            else:
                model.check_identifier(entity_id, "entity id")
                matchers.append(lambda eid, etype, i=entity_id, t=entity_type:
                                eid == i and (t is None or etype == t))
        return matchers

    def query_context(self, req):
        body = req.json()
        if not isinstance(body, dict):
            raise model.NgsiError(400, "ParseError", "JSON Parse Error")
        matchers = self._matchers(body.get("entities"))
        attributes = _string_list(body.get("attributes"), "attributes")
        limit, offset = self._pagination(req)
        with self.store.lock:
            found = self.store.tenant(req.tenant).query(matchers, None, req.query_paths)
            selected = []
            for entity in found:
                names = model.select_attributes(entity, attributes)
                if attributes and not names:
                    continue
                selected.append((entity, names))
            page = selected[offset:offset + limit]
            responses = [model.v1_context_element_response(entity, names) for entity, names in page]
        if not responses:
            error = {"code": "404", "reasonPhrase": NOT_FOUND}
            if offset and selected:
                error["details"] = f"Number of matching entities: {len(selected)}. Offset is {offset}"
            return req.json_response(200, {"errorCode": error})
        body = {"contextResponses": responses}
        if req.param("details") == "on":
            body["errorCode"] = {"code": "200", "reasonPhrase": "OK", "details": f"Count: {len(selected)}"}
        return req.json_response(200, body)

    def _pagination(self, req):
        values = []
        for name, default, minimum in (("limit", DEFAULT_LIMIT, 1), ("offset", 0, 0)):
            text = req.param(name)
            if text is None:
                values.append(default)
                continue
            if not text.isdigit() or int(text) < minimum or (name == "limit" and int(text) > MAX_LIMIT):
                raise bad_request(f"Bad pagination {name}: /{text}/")
            values.append(int(text))
        return values

    # --- subscriptions ------------------------------------------------------------------------------------
    def _conditions(self, raw):
        if raw is None:
            return []
        if not isinstance(raw, list):
            raise bad_request("notifyConditions must be a list")
        attrs = []
        for condition in raw:
            if not isinstance(condition, dict) or condition.get("type") != "ONCHANGE":
                raise bad_request("invalid notifyCondition type: only ONCHANGE is supported")
            for name in _string_list(condition.get("condValues"), "condValues"):
                if name not in attrs:
                    attrs.append(name)
        return attrs

    def subscribe_context(self, req):
        body = req.json()
        if not isinstance(body, dict):
            raise model.NgsiError(400, "ParseError", "JSON Parse Error")
        raw_entities = body.get("entities")
        if not isinstance(raw_entities, list) or not raw_entities:
            raise bad_request("invalid payload: mandatory field missing: entities")
        selectors = []
        for raw in raw_entities:
            if not isinstance(raw, dict):
                raise bad_request("an entity must be a JSON object")
            entity_id = raw.get("id", "")
            selector = {"idPattern": entity_id} if _is_pattern(raw) else {"id": entity_id}
            if not _is_pattern(raw):
                model.check_identifier(entity_id, "entity id")
            if raw.get("type"):
                selector["type"] = model.check_identifier(raw["type"], "entity type")
            selectors.append(EntitySelector(selector))
        reference = body.get("reference")
        if not reference:
            raise bad_request("invalid payload: mandatory field missing: reference")
        if isinstance(reference, str) and "://" not in reference:
            reference = "http://" + reference  # Orion's default scheme
        sub = Subscription(new_subscription_id(), req.tenant, req.query_paths)
        sub.v1 = True
        sub.attrs_format = "legacy"
        sub.entities = selectors
        sub.url = check_url(reference)
        sub.notify_attrs = _string_list(body.get("attributes"), "attributes")
        sub.condition_attrs = self._conditions(body.get("notifyConditions"))
        duration = body.get("duration") or DEFAULT_DURATION
        sub.expires = time.time() + _duration(duration, "duration")
        sub.v1_duration = duration
        if body.get("throttling"):
            sub.throttling = _duration(body["throttling"], "throttling")
            sub.v1_throttling = body["throttling"]
        answer = {"subscriptionId": sub.id, "duration": duration}
        if sub.v1_throttling:
            answer["throttling"] = sub.v1_throttling
        with self.store.lock:
            tenant = self.store.tenant(req.tenant)
            tenant.subscriptions[sub.id] = sub
            if self.initial_notification:
                self._initial_notification(req, tenant, sub)
        return req.json_response(200, {"subscribeResponse": answer})

    def _initial_notification(self, req, tenant, sub):
        """Orion before 3.1 notified the current values right after subscribeContext."""
        matching = [entity.snapshot() for entity in tenant.entities.values() if sub.matches(entity)]
        matching = [e for e in matching if not sub.notify_attrs or model.select_attributes(e, sub.notify_attrs)]
        if matching:
            self.notifications.send(tenant, sub, matching[:DEFAULT_LIMIT], None, correlator=req.correlator)

    def _find_subscription(self, body):
        if not isinstance(body, dict):
            raise model.NgsiError(400, "ParseError", "JSON Parse Error")
        sub_id = body.get("subscriptionId")
        if not isinstance(sub_id, str) or not sub_id:
            raise bad_request("invalid payload: mandatory field missing: subscriptionId")
        return sub_id

    def update_context_subscription(self, req):
        body = req.json()
        sub_id = self._find_subscription(body)
        for forbidden in ("entities", "reference"):
            if forbidden in body:
                raise bad_request(f"invalid payload: {forbidden} cannot be changed by updateContextSubscription")
        conditions = self._conditions(body["notifyConditions"]) if "notifyConditions" in body else None
        attributes = _string_list(body["attributes"], "attributes") if "attributes" in body else None
        duration = body.get("duration")
        duration_seconds = _duration(duration, "duration") if duration else None
        throttling = body.get("throttling")
        throttling_seconds = _duration(throttling, "throttling") if throttling else None
        with self.store.lock:
            sub = self.store.tenant(req.tenant).subscriptions.get(sub_id)
            if sub is None:
                return req.json_response(200, {"subscribeError": {
                    "subscriptionId": sub_id, "errorCode": {"code": "404", "reasonPhrase": NOT_FOUND}}})
            if conditions is not None:
                sub.condition_attrs = conditions
            if attributes is not None:
                sub.notify_attrs = attributes
            if duration_seconds is not None:
                sub.expires = time.time() + duration_seconds
                sub.v1_duration = duration
            if throttling_seconds is not None:
                sub.throttling = throttling_seconds
                sub.v1_throttling = throttling
        answer = {"subscriptionId": sub_id}
        if duration:
            answer["duration"] = duration
        if throttling:
            answer["throttling"] = throttling
        return req.json_response(200, {"subscribeResponse": answer})

    def unsubscribe_context(self, req):
        sub_id = self._find_subscription(req.json())
        with self.store.lock:
            tenant = self.store.tenant(req.tenant)
            if tenant.subscriptions.pop(sub_id, None) is None:
                return req.json_response(200, {
                    "statusCode": {"code": "404", "reasonPhrase": NOT_FOUND,
                                   "details": f"subscriptionId: /{sub_id}/"},
                    "subscriptionId": sub_id})
        return req.json_response(200, {"statusCode": dict(OK), "subscriptionId": sub_id})

    # --- the convenience operations Orion 3.10+ kept ----------------------------------------------------
    def put_entity(self, req, entity_id):
        """``PUT /v1/contextEntities/{id}`` with ``{"attributes": [...]}``: an UPDATE of that entity."""
        body = req.json()
        if not isinstance(body, dict):
            raise model.NgsiError(400, "ParseError", "JSON Parse Error")
        _, _, attrs = _parse_element({"id": entity_id, "attributes": body.get("attributes", [])})
        with self.store.lock:
            status = self._update_one(req, self.store.tenant(req.tenant), "UPDATE", entity_id, "", attrs)
        return req.json_response(200, {"contextResponses": [{
            "attributes": [model.v1_attribute(name, attr, with_value=False) for name, attr in attrs.items()],
            "statusCode": status}]})

    def delete_entity(self, req, entity_id):
        """``DELETE /v1/contextEntities/{id}``: the entity and all its attributes."""
        model.check_identifier(entity_id, "entity id")
        with self.store.lock:
            status = self._update_one(req, self.store.tenant(req.tenant), "DELETE", entity_id, "", {})
        return req.json_response(200, status)

    def get_entity_attribute(self, req, entity_id, attr_name):
        """``GET /v1/contextEntities/{id}/attributes/{name}``."""
        model.check_identifier(entity_id, "entity id")
        with self.store.lock:
            found = self.store.tenant(req.tenant).find(entity_id, None, req.query_paths)
            attrs = [(name, dict(e.attrs[name])) for e in found[:1] for name in e.attrs if name == attr_name]
        if not found or not attrs:
            return req.json_response(200, {"statusCode": {"code": "404", "reasonPhrase": NOT_FOUND,
                                                          "details": f"Entity id: /{entity_id}/"}})
        return req.json_response(200, {"attributes": [model.v1_attribute(n, a) for n, a in attrs],
                                       "statusCode": dict(OK)})
