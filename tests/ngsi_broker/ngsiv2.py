"""NGSI v2 as Orion 4 answers it: entities, attributes, attribute values, ``op/update`` and subscriptions.

Each handler takes the parsed ``server.Request`` (tenant and service paths already read from the headers) and
returns a ``server.Response``; client mistakes raise ``model.NgsiError``, which the server renders as Orion's
``{"error", "description"}``. Writes go through ``_write`` so that every change notifies the subscribers.
"""

import json
import time

from . import model
from .model import NgsiError, bad_request
from .subscriptions import Subscription, apply_v2_fields, new_subscription_id

DEFAULT_LIMIT = 20
MAX_LIMIT = 1000
ENTITY_OPTIONS = {"keyValues", "values", "count", "unique", "upsert", "append", "forcedUpdate",
                  "skipForwarding", "overwrite"}
ACTION_TYPES = {"append": "append", "APPEND": "append", "appendStrict": "appendStrict",
                "APPEND_STRICT": "appendStrict", "update": "update", "UPDATE": "update",
                "delete": "delete", "DELETE": "delete", "replace": "replace", "REPLACE": "replace"}
UNSUPPORTED_QUERY_PARAMS = ("q", "mq", "georel", "geometry", "coords", "orderBy")


def _csv(text):
    return [item for item in (text or "").split(",") if item != ""]


def _options(req):
    options = set(_csv(req.param("options")))
    unknown = options - ENTITY_OPTIONS
    if unknown:
        raise bad_request("Invalid value for URI param /options/")
    return options


def _render_format(options):
    if "keyValues" in options and "values" in options:
        raise bad_request("Invalid value for URI param /options/")
    if "keyValues" in options:
        return "keyValues"
    if "values" in options or "unique" in options:
        return "values"
    return "normalized"


def _pagination(req):
    def number(name, default, minimum, maximum=None):
        text = req.param(name)
        if text is None:
            return default
        if not text.isdigit() or int(text) < minimum or (maximum is not None and int(text) > maximum):
            raise bad_request(f"Bad pagination {name}: /{text}/ [a whole number"
                              + (f" from {minimum} to {maximum}" if maximum else f" >= {minimum}") + "]")
        return int(text)
    return number("limit", DEFAULT_LIMIT, 1, MAX_LIMIT), number("offset", 0, 0)


def parse_attribute(name, raw, key_values):
    """One attribute of a request body → the stored form; Orion's checks on name, type, value, metadata."""
    model.check_identifier(name, "attribute name")
    if key_values:
        value, attr_type, metadata = raw, model.default_type(raw), {}
    else:
        if not isinstance(raw, dict):
            raise bad_request("attribute must be a JSON object, unless keyValues option is used")
        unknown = set(raw) - {"type", "value", "metadata"}
        if unknown:
            raise bad_request(f"unrecognized property for context attribute: {sorted(unknown)[0]}")
        value = raw.get("value")
        attr_type = raw.get("type")
        if attr_type is None:
            attr_type = model.default_type(value)
        model.check_identifier(attr_type, "attribute type")
        metadata = parse_metadata(raw.get("metadata", {}))
    model.check_attribute_value(attr_type, value)
    return {"type": attr_type, "value": value, "metadata": metadata}


def parse_metadata(raw):
    if not isinstance(raw, dict):
        raise bad_request("metadata must be a JSON object")
    metadata = {}
    for name, md in raw.items():
        model.check_identifier(name, "metadata name")
        if not isinstance(md, dict):
            raise bad_request("metadata must be a JSON object with type and value")
        value = md.get("value")
        md_type = md.get("type", model.default_type(value))
        model.check_identifier(md_type, "metadata type")
        model.check_attribute_value(md_type, value)
        metadata[name] = {"type": md_type, "value": value}
    return metadata


def parse_attributes(body, key_values, skip=("id", "type")):
    if not isinstance(body, dict):
        raise NgsiError(400, "ParseError", "Errors found in incoming JSON buffer")
    return {name: parse_attribute(name, raw, key_values) for name, raw in body.items() if name not in skip}


def _entity_body(body, key_values):
    """An entity of a request body → (id, type or None, attributes)."""
    if not isinstance(body, dict):
        raise NgsiError(400, "ParseError", "Errors found in incoming JSON buffer")
    entity_id = body.get("id", "")
    model.check_identifier(entity_id, "entity id")
    entity_type = body.get("type")
    if entity_type is not None:
        model.check_identifier(entity_type, "entity type")
    return entity_id, entity_type, parse_attributes(body, key_values)


def _attr_names(names):
    return "[ " + ", ".join(names) + " ]"


class NgsiV2:
    """The NGSI v2 handlers over one store."""

    def __init__(self, store, notifications):
        self.store = store
        self.notifications = notifications

    # --- helpers ------------------------------------------------------------------------------------------
    def _write(self, req, tenant, entity, attrs, replace=False, created=False, forced=False):
        changed = model.set_attributes(entity, attrs, replace=replace)
        if forced:
            changed = list(attrs)
        self.notifications.entity_changed(tenant, entity, changed, created=created, correlator=req.correlator)

    def _entity(self, req, tenant, entity_id):
        model.check_identifier(entity_id, "entity id")
        entity_type = req.param("type")
        return tenant.find_one(entity_id, entity_type or None, req.query_paths)

    # --- entities -----------------------------------------------------------------------------------------
    def list_entities(self, req):
        for name in UNSUPPORTED_QUERY_PARAMS:
            if req.param(name) is not None:
                raise bad_request(f"the stand-in broker does not support the {name} parameter")
        options = _options(req)
        fmt = _render_format(options)
        limit, offset = _pagination(req)
        ids, id_pattern = _csv(req.param("id")), req.param("idPattern")
        types, type_pattern = _csv(req.param("type")), req.param("typePattern")
        if ids and id_pattern is not None:
            raise bad_request("Incompatible parameters: id, IdPattern")
        if types and type_pattern is not None:
            raise bad_request("Incompatible parameters: type, typePattern")
        id_matchers = []
        if ids:
            wanted = set(ids)
            id_matchers.append(lambda eid, etype: eid in wanted)
        elif id_pattern is not None:
            regex = model.compile_pattern(id_pattern)
            id_matchers.append(lambda eid, etype: regex.search(eid) is not None)
        type_matcher = None
        if types:
            wanted_types = set(types)
            type_matcher = lambda etype: etype in wanted_types  # noqa: E731
        elif type_pattern is not None:
            type_regex = model.compile_pattern(type_pattern, "entity typePattern")
            type_matcher = lambda etype: type_regex.search(etype) is not None  # noqa: E731
        attrs = _csv(req.param("attrs"))
        with self.store.lock:
            # attrs is a projection in v2 (an entity without them is listed with id and type only)
            found = self.store.tenant(req.tenant).query(id_matchers, type_matcher, req.query_paths)
            page = found[offset:offset + limit]
            body = [model.v2_entity(e, model.select_attributes(e, attrs), fmt) for e in page]
        headers = {"Fiware-Total-Count": str(len(found))} if "count" in options else {}
        return req.json_response(200, body, headers)

    def create_entity(self, req):
        options = _options(req)
        entity_id, entity_type, attrs = _entity_body(req.json(), "keyValues" in options)
        entity_type = entity_type or model.DEFAULT_ENTITY_TYPE
        with self.store.lock:
            tenant = self.store.tenant(req.tenant)
            entity = tenant.get_exact(req.update_path, entity_id, entity_type)
            if entity is not None:
                if "upsert" not in options:
                    raise NgsiError(422, "Unprocessable", "Already Exists")
                self._write(req, tenant, entity, attrs, forced="forcedUpdate" in options)
                return req.empty_response(204)
            entity = model.Entity(entity_id, entity_type, req.update_path)
            tenant.add(entity)
            self._write(req, tenant, entity, attrs, created=True)
        return req.empty_response(201, {"Location": f"/v2/entities/{entity_id}?type={entity_type}"})

    def get_entity(self, req, entity_id):
        options = _options(req)
        fmt = _render_format(options)
        attrs = _csv(req.param("attrs"))
        with self.store.lock:
            entity = self._entity(req, self.store.tenant(req.tenant), entity_id)
            body = model.v2_entity(entity, model.select_attributes(entity, attrs), fmt)
        return req.json_response(200, body)

    def delete_entity(self, req, entity_id):
        with self.store.lock:
            tenant = self.store.tenant(req.tenant)
            tenant.remove(self._entity(req, tenant, entity_id))
        return req.empty_response(204)

    # --- attributes ---------------------------------------------------------------------------------------
    def get_attrs(self, req, entity_id):
        options = _options(req)
        fmt = _render_format(options)
        attrs = _csv(req.param("attrs"))
        with self.store.lock:
            entity = self._entity(req, self.store.tenant(req.tenant), entity_id)
            body = model.v2_entity(entity, model.select_attributes(entity, attrs), fmt)
        if isinstance(body, dict):
            body.pop("id")
            body.pop("type")
        return req.json_response(200, body)

    def post_attrs(self, req, entity_id):
        options = _options(req)
        attrs = parse_attributes(req.json(), "keyValues" in options)
        with self.store.lock:
            tenant = self.store.tenant(req.tenant)
            entity = self._entity(req, tenant, entity_id)
            if "append" in options:
                existing = [name for name in attrs if name in entity.attrs]
                if existing:
                    raise NgsiError(422, "Unprocessable", "one or more of the attributes in the request already "
                                    f"exist: {entity.id} - {_attr_names(existing)}")
            self._write(req, tenant, entity, attrs, forced="forcedUpdate" in options)
        return req.empty_response(204)

    def patch_attrs(self, req, entity_id):
        options = _options(req)
        attrs = parse_attributes(req.json(), "keyValues" in options)
        with self.store.lock:
            tenant = self.store.tenant(req.tenant)
            entity = self._entity(req, tenant, entity_id)
            missing = [name for name in attrs if name not in entity.attrs]
            if missing:
                raise NgsiError(422, "Unprocessable", f"do not exist: {entity.id} - {_attr_names(missing)}")
            self._write(req, tenant, entity, attrs, forced="forcedUpdate" in options)
        return req.empty_response(204)

    def put_attrs(self, req, entity_id):
        options = _options(req)
        attrs = parse_attributes(req.json(), "keyValues" in options)
        with self.store.lock:
            tenant = self.store.tenant(req.tenant)
            entity = self._entity(req, tenant, entity_id)
            self._write(req, tenant, entity, attrs, replace=True, forced="forcedUpdate" in options)
        return req.empty_response(204)

    def _existing_attr(self, req, tenant, entity_id, attr_name):
        model.check_identifier(attr_name, "attribute name")
        entity = self._entity(req, tenant, entity_id)
        if attr_name not in entity.attrs:
            raise NgsiError(404, "NotFound", "The entity does not have such an attribute")
        return entity

    def get_attr(self, req, entity_id, attr_name):
        with self.store.lock:
            entity = self._existing_attr(req, self.store.tenant(req.tenant), entity_id, attr_name)
            attr = entity.attrs[attr_name]
            body = {"type": attr["type"], "value": attr["value"], "metadata": dict(attr["metadata"])}
        return req.json_response(200, body)

    def put_attr(self, req, entity_id, attr_name):
        attr = parse_attribute(attr_name, req.json(), False)
        with self.store.lock:
            tenant = self.store.tenant(req.tenant)
            entity = self._existing_attr(req, tenant, entity_id, attr_name)
            self._write(req, tenant, entity, {attr_name: attr})
        return req.empty_response(204)

    def delete_attr(self, req, entity_id, attr_name):
        with self.store.lock:
            tenant = self.store.tenant(req.tenant)
            entity = self._existing_attr(req, tenant, entity_id, attr_name)
            del entity.attrs[attr_name]
        return req.empty_response(204)

    def get_attr_value(self, req, entity_id, attr_name):
        with self.store.lock:
            entity = self._existing_attr(req, self.store.tenant(req.tenant), entity_id, attr_name)
            value = entity.attrs[attr_name]["value"]
        if isinstance(value, (dict, list)):
            return req.json_response(200, value)
        accept = req.header("Accept") or "*/*"
        if "text/plain" not in accept and "*/*" not in accept:
            raise NgsiError(406, "NotAcceptable", "accepted MIME types: text/plain")
        return req.raw_response(200, json.dumps(value).encode("utf-8"), "text/plain")

    def put_attr_value(self, req, entity_id, attr_name):
        if req.content_type == "text/plain":
            try:
                value = json.loads(req.body.decode("utf-8"))
            except (ValueError, UnicodeDecodeError):
                raise bad_request("Wrong syntax in text/plain value") from None
            if isinstance(value, (dict, list)):
                raise bad_request("Wrong syntax in text/plain value")
        else:
            value = req.json()
        with self.store.lock:
            tenant = self.store.tenant(req.tenant)
            entity = self._existing_attr(req, tenant, entity_id, attr_name)
            old = entity.attrs[attr_name]
            model.check_attribute_value(old["type"], value)
            self._write(req, tenant, entity, {attr_name: {"type": old["type"], "value": value,
                                                          "metadata": dict(old["metadata"])}})
        return req.empty_response(204)

    # --- batch --------------------------------------------------------------------------------------------
    def op_update(self, req):
        options = _options(req)
        body = req.json()
        if not isinstance(body, dict):
            raise NgsiError(400, "ParseError", "Errors found in incoming JSON buffer")
        action = ACTION_TYPES.get(body.get("actionType"))
        if action is None:
            raise bad_request("invalid update action type: right ones are: append, appendStrict, delete, "
                              "replace, update")
        raw_entities = body.get("entities")
        if not isinstance(raw_entities, list) or not raw_entities:
            raise bad_request("empty entities")
        key_values = "keyValues" in options
        parsed = [_entity_body(raw, key_values) for raw in raw_entities]  # all checked before any change
        failures, successes = [], 0
        with self.store.lock:
            tenant = self.store.tenant(req.tenant)
            for entity_id, entity_type, attrs in parsed:
                try:
                    self._batch_one(req, tenant, action, entity_id, entity_type, attrs, options)
                    successes += 1
                except NgsiError as exc:
                    failures.append((entity_id, entity_type, exc))
        if failures and not successes and len(failures) == 1:
            raise failures[0][2]
        if failures:
            detail = ", ".join(f"{eid}{'/' + etype if etype else ''} - {exc.description}"
                               for eid, etype, exc in failures)
            if not successes and all(exc.status == 404 for _, _, exc in failures):
                raise model.entity_not_found()
            raise NgsiError(422, "PartialUpdate", detail)
        return req.empty_response(204)

    def _batch_one(self, req, tenant, action, entity_id, entity_type, attrs, options):
        found = tenant.find(entity_id, entity_type, [(req.update_path, False)])
        entity = found[0] if found else None
        forced = "forcedUpdate" in options
        if action in ("append", "appendStrict"):
            if entity is None:
                entity = model.Entity(entity_id, entity_type or model.DEFAULT_ENTITY_TYPE, req.update_path)
                tenant.add(entity)
                self._write(req, tenant, entity, attrs, created=True)
                return
            if action == "appendStrict":
                existing = [name for name in attrs if name in entity.attrs]
                if existing:
                    raise NgsiError(422, "Unprocessable", "one or more of the attributes in the request already "
                                    f"exist: {entity.id} - {_attr_names(existing)}")
            self._write(req, tenant, entity, attrs, forced=forced)
            return
        if entity is None:
            raise model.entity_not_found()
        if action == "update":
            missing = [name for name in attrs if name not in entity.attrs]
            if missing:
                raise NgsiError(422, "Unprocessable", f"do not exist: {entity.id} - {_attr_names(missing)}")
            self._write(req, tenant, entity, attrs, forced=forced)
        elif action == "replace":
            self._write(req, tenant, entity, attrs, replace=True, forced=forced)
        else:  # delete: the named attributes, or the whole entity when none is named
            if not attrs:
                tenant.remove(entity)
                return
            missing = [name for name in attrs if name not in entity.attrs]
            if missing:
                raise NgsiError(422, "Unprocessable", f"do not exist: {entity.id} - {_attr_names(missing)}")
            for name in attrs:
                del entity.attrs[name]

    # --- subscriptions ------------------------------------------------------------------------------------
    def _subscription(self, tenant, sub_id):
        sub = tenant.subscriptions.get(sub_id)
        if sub is None:
            raise NgsiError(404, "NotFound", "The requested subscription has not been found. Check id")
        return sub

    def create_subscription(self, req):
        body = req.json()
        sub = Subscription(new_subscription_id(), req.tenant, req.query_paths)
        apply_v2_fields(sub, body, creating=True)
        with self.store.lock:
            self.store.tenant(req.tenant).subscriptions[sub.id] = sub
        return req.empty_response(201, {"Location": f"/v2/subscriptions/{sub.id}"})

    def list_subscriptions(self, req):
        options = _options(req)
        limit, offset = _pagination(req)
        now = time.time()
        with self.store.lock:
            subs = list(self.store.tenant(req.tenant).subscriptions.values())
            if req.header("Fiware-ServicePath"):  # Orion lists those whose query uses exactly this path
                subs = [sub for sub in subs if sub.query_paths == req.query_paths]
            body = [sub.render(now) for sub in subs[offset:offset + limit]]
        headers = {"Fiware-Total-Count": str(len(subs))} if "count" in options else {}
        return req.json_response(200, body, headers)

    def get_subscription(self, req, sub_id):
        now = time.time()
        with self.store.lock:
            body = self._subscription(self.store.tenant(req.tenant), sub_id).render(now)
        return req.json_response(200, body)

    def patch_subscription(self, req, sub_id):
        body = req.json()
        if isinstance(body, dict) and not body:
            raise bad_request("empty payload")
        with self.store.lock:
            sub = self._subscription(self.store.tenant(req.tenant), sub_id)
            apply_v2_fields(sub, body, creating=False)
        return req.empty_response(204)

    def delete_subscription(self, req, sub_id):
        with self.store.lock:
            tenant = self.store.tenant(req.tenant)
            self._subscription(tenant, sub_id)
            del tenant.subscriptions[sub_id]
        return req.empty_response(204)

    def root(self, req):
        return req.json_response(200, {"entities_url": "/v2/entities", "types_url": "/v2/types",
                                        "subscriptions_url": "/v2/subscriptions",
                                        "registrations_url": "/v2/registrations"})
