"""NGSI-LD (ETSI GS CIM 009) as Orion-LD answers it, under ``/ngsi-ld/v1/``: entities, attributes, batch upsert,
subscriptions and their notifications, with the ``@context`` rules and ProblemDetails errors.

``NgsiLd.handle`` takes one request (method, path, query, headers, body) and returns a ``LdResponse``; every
client mistake raises ``LdProblem``, rendered as ``{"type": "https://uri.etsi.org/ngsi-ld/errors/...", "title",
"detail"}`` with Content-Type ``application/json``, as Orion-LD does.

Names: entity types and attribute names are stored expanded (full IRIs), as Orion-LD stores them, and compacted
again with the context of each request, so a reader with another context sees other names. ``Context`` does the
expansion: the core context's few terms, the terms of inline (JSON object) contexts, and otherwise the core
context's ``@vocab`` (``https://uri.etsi.org/ngsi-ld/default-context/``). Context URLs other than the core one
are not downloaded (there is no network here); they add no terms.

NGSI-LD entities live in their own table of each tenant (``Tenant.ld_entities``, ``Tenant.ld_subscriptions``):
the stand-in does not show LD entities through v1/v2 or the other way round. Every write notifies: NGSI-LD
has no "value really changed" rule (an update always changes ``modifiedAt``), and there is no initial
notification (Orion-LD removed it for NGSI-LD).
"""

import json
import re
import secrets
import time
import uuid
from urllib.parse import unquote, urlsplit

from . import model

ERRORS = "https://uri.etsi.org/ngsi-ld/errors/"
NGSILD = "https://uri.etsi.org/ngsi-ld/"
CORE_CONTEXT = "https://uri.etsi.org/ngsi-ld/v1/ngsi-ld-core-context.jsonld"
_CORE_CONTEXT_RE = re.compile(r"^https://uri\.etsi\.org/ngsi-ld/v1/ngsi-ld-core-context(?:-v\d+\.\d+)?\.jsonld$")
DEFAULT_VOCAB = NGSILD + "default-context/"
JSONLD_REL = "http://www.w3.org/ns/json-ld#context"
# the core context's own terms that can name attributes; a user context cannot redefine them
CORE_TERMS = {name: NGSILD + name for name in ("location", "observationSpace", "operationSpace", "status")}
CORE_REVERSE = {iri: term for term, iri in CORE_TERMS.items()}

ATTRIBUTE_TYPES = ("Property", "Relationship", "GeoProperty", "LanguageProperty")
SYSTEM_MEMBERS = ("createdAt", "modifiedAt")
ATTRIBUTE_MEMBERS = {"type", "value", "object", "languageMap", "observedAt", "unitCode", "datasetId"}
NOTIFICATION_FORMATS = ("normalized", "keyValues", "simplified")
ACCEPT_TYPES = ("application/json", "application/ld+json")
FORBIDDEN_NAME_CHARS = frozenset("<>\"'=;()")
MAX_NESTING = 16  # sub-attributes inside sub-attributes
DEFAULT_LIMIT = 20
MAX_LIMIT = 1000
MAX_NAME = 512

_URI_RE = re.compile(r"^[A-Za-z][A-Za-z0-9+.\-]*:[^\s<>\"{}|\\^`]+$")


class LdProblem(Exception):
    """A ProblemDetails answer: HTTP status, NGSI-LD error type (the last part of its URI), title, detail."""

    def __init__(self, status, kind, title, detail=None):
        super().__init__(title)
        self.status = status
        self.kind = kind
        self.title = title
        self.detail = detail

    def body(self):
        body = {"type": ERRORS + self.kind, "title": self.title}
        if self.detail is not None:
            body["detail"] = self.detail
        return body


def bad_data(title, detail=None):
    return LdProblem(400, "BadRequestData", title, detail)


def not_found(title, detail):
    return LdProblem(404, "ResourceNotFound", title, detail)


class LdResponse:
    """What a handler answers (the same fields as ``server.Response``)."""

    def __init__(self, status, body=b"", content_type=None, headers=None):
        self.status = status
        self.body = body
        self.content_type = content_type
        self.headers = headers or {}


def problem_response(problem, headers=None):
    return LdResponse(problem.status, json.dumps(problem.body()).encode("utf-8"), "application/json", headers)


# --- syntax ---------------------------------------------------------------------------------------------

def is_uri(text):
    return isinstance(text, str) and len(text) <= 2048 and _URI_RE.match(text) is not None


def check_entity_id(entity_id):
    if entity_id is None:
        raise bad_data("Entity id is missing", "The 'id' field is mandatory")
    if not is_uri(entity_id):
        raise bad_data("Invalid Entity ID", "Not a URI")
    return entity_id


def check_name(name, what="attribute name"):
    if not isinstance(name, str) or not name or len(name) > MAX_NAME:
        raise bad_data(f"Invalid {what}", repr(name)[:300])
    if any(ch in FORBIDDEN_NAME_CHARS or ord(ch) <= 32 or ord(ch) == 127 for ch in name):
        raise bad_data(f"Invalid {what}", name[:300])
    return name


def parse_datetime(text, what):
    """An NGSI-LD DateTime (ISO 8601 with date and time, ``Z`` allowed) → epoch seconds; BadRequestData if not."""
    if not isinstance(text, str) or "T" not in text:
        raise bad_data("Invalid DateTime", f"{what}: {str(text)[:100]}")
    try:
        return model.parse_iso_time(text[:-1] + "+00:00" if text.endswith("Z") else text)
    except ValueError:
        raise bad_data("Invalid DateTime", f"{what}: {text[:100]}") from None


def iso_now(epoch=None):
    return model.iso_time(time.time() if epoch is None else epoch)


# --- @context ---------------------------------------------------------------------------------------------

class Context:
    """One request's ``@context``: expands terms to IRIs and compacts IRIs back to terms."""

    def __init__(self, raw=None):
        self.raw = raw
        self.terms = {}
        items = raw if isinstance(raw, list) else [] if raw is None else [raw]
        if isinstance(raw, list) and not raw:
            raise bad_data("Invalid @context", "an empty array")
        for item in items:
            if isinstance(item, str):
                if not is_uri(item):
                    raise bad_data("Invalid @context", f"not a URI: {item[:200]}")
            elif isinstance(item, dict):
                for term, definition in item.items():
                    if term.startswith("@"):
                        continue
                    if isinstance(definition, dict):
                        definition = definition.get("@id")
                    if not isinstance(definition, str) or not definition:
                        raise bad_data("Invalid @context", f"bad definition of the term {term[:100]}")
                    self.terms[term] = definition
            else:
                raise bad_data("Invalid @context", "an @context is a URI, an object or an array of them")
        self.reverse = {iri: term for term, iri in self.terms.items()}

    def expand(self, term):
        if term in CORE_TERMS:
            return CORE_TERMS[term]
        if term in self.terms:
            return self.terms[term]
        if ":" in term:  # already an IRI (or a compact IRI): kept as it is
            return term
        return DEFAULT_VOCAB + term

    def compact(self, iri):
        if iri in CORE_REVERSE:
            return CORE_REVERSE[iri]
        if iri in self.reverse:
            return self.reverse[iri]
        if iri.startswith(DEFAULT_VOCAB):
            return iri[len(DEFAULT_VOCAB):]
        return iri

    def link_url(self):
        """The URL to put in a ``Link`` header: the context when it is one URL, else the core context."""
        return self.raw if isinstance(self.raw, str) else CORE_CONTEXT

    def body_value(self):
        return self.raw if self.raw is not None else CORE_CONTEXT


def link_header(url):
    return f'<{url}>; rel="{JSONLD_REL}"; type="application/ld+json"'


_LINK_RE = re.compile(r'^\s*<([^>]*)>\s*((?:;\s*[A-Za-z]+\s*=\s*(?:"[^"]*"|[^;,"\s]+)\s*)*)$')
_LINK_PARAM_RE = re.compile(r';\s*([A-Za-z]+)\s*=\s*(?:"([^"]*)"|([^;,"\s]+))')


def parse_link(value):
    """The context URL of a ``Link`` header (``<url>; rel="http://www.w3.org/ns/json-ld#context"``)."""
    match = _LINK_RE.match(value)
    if not match:
        raise bad_data("Invalid Link HTTP header", value[:200])
    params = {m.group(1).lower(): m.group(2) if m.group(2) is not None else m.group(3)
              for m in _LINK_PARAM_RE.finditer(match.group(2))}
    if params.get("rel") != JSONLD_REL:
        raise bad_data("Invalid Link HTTP header", f"rel must be {JSONLD_REL}")
    if not is_uri(match.group(1)):
        raise bad_data("Invalid Link HTTP header", "the context is not a URI")
    return match.group(1)


# --- entities and attributes ------------------------------------------------------------------------------

class LdEntity:
    """An NGSI-LD entity: id, expanded type, attributes by expanded name (normalized form), system times."""

    def __init__(self, entity_id, type_iri):
        self.id = entity_id
        self.type = type_iri
        self.attrs = {}
        self.attr_times = {}      # name -> (createdAt, modifiedAt)
        self.created = self.modified = time.time()


def parse_attribute(name, raw, ctx, depth=0):
    """One attribute (or sub-attribute) of a request → its stored form (sub-attribute names expanded)."""
    check_name(name)
    if depth > MAX_NESTING:
        raise bad_data("Invalid attribute", f"{name}: sub-attributes nested too deeply")
    if not isinstance(raw, dict):
        raise bad_data("Invalid attribute", f"{name}: an attribute must be a JSON object")
    attr_type = raw.get("type")
    if attr_type is None:
        raise bad_data("Attribute type missing", name)
    if attr_type not in ATTRIBUTE_TYPES:
        raise bad_data("Invalid type for attribute", f"{name}: {str(attr_type)[:100]}")
    stored = {"type": attr_type}
    if attr_type in ("Property", "GeoProperty"):
        if raw.get("value") is None:
            raise bad_data("Attribute value missing", f"{name}: a {attr_type} needs a value")
        value = raw["value"]
        if attr_type == "GeoProperty" and not (isinstance(value, dict) and isinstance(value.get("type"), str)
                                               and "coordinates" in value):
            raise bad_data("Invalid GeoJSON", f"{name}: a GeoProperty's value is a GeoJSON geometry")
        stored["value"] = value
    elif attr_type == "Relationship":
        if not is_uri(raw.get("object")):
            raise bad_data("Invalid Relationship object", f"{name}: Relationship object must be a valid URI")
        stored["object"] = raw["object"]
    else:  # LanguageProperty
        language_map = raw.get("languageMap")
        if not isinstance(language_map, dict) or not language_map or not all(
                isinstance(v, (str, list)) for v in language_map.values()):
            raise bad_data("Invalid languageMap", f"{name}: a LanguageProperty needs a languageMap object")
        stored["languageMap"] = language_map
    for member in ("value", "object", "languageMap"):
        if member in raw and member not in stored:
            raise bad_data("Invalid attribute", f"{name}: a {attr_type} has no {member}")
    if "observedAt" in raw:
        parse_datetime(raw["observedAt"], f"{name}.observedAt")
        stored["observedAt"] = raw["observedAt"]
    if "unitCode" in raw:
        if not isinstance(raw["unitCode"], str) or not raw["unitCode"]:
            raise bad_data("Invalid unitCode", name)
        stored["unitCode"] = raw["unitCode"]
    if "datasetId" in raw:
        if not is_uri(raw["datasetId"]):
            raise bad_data("Invalid datasetId", f"{name}: not a URI")
        stored["datasetId"] = raw["datasetId"]
    for sub_name, sub_raw in raw.items():
        if sub_name in ATTRIBUTE_MEMBERS or sub_name in SYSTEM_MEMBERS:
            continue
        stored[ctx.expand(sub_name)] = parse_attribute(sub_name, sub_raw, ctx, depth + 1)
    return stored


def parse_attributes(body, ctx, skip=("id", "type", "@context")):
    """An object of attributes → {expanded name: stored attribute}; system members are ignored."""
    if not isinstance(body, dict):
        raise bad_data("Invalid payload", "Not a JSON Object")
    attrs = {}
    for name, raw in body.items():
        if name in skip or name in SYSTEM_MEMBERS:
            continue
        attrs[ctx.expand(check_name(name))] = parse_attribute(name, raw, ctx)
    return attrs


def parse_entity(body, ctx):
    """An entity of a request body → (id, expanded type, attributes)."""
    if not isinstance(body, dict):
        raise bad_data("Invalid payload", "Not a JSON Object")
    entity_id = check_entity_id(body.get("id"))
    entity_type = body.get("type")
    if entity_type is None:
        raise bad_data("Entity type missing", "The type field is mandatory")
    if not isinstance(entity_type, str):
        raise bad_data("Invalid entity type name", "the entity type must be a string")
    check_name(entity_type, "entity type name")
    return entity_id, ctx.expand(entity_type), parse_attributes(body, ctx)


def render_attribute(attr, ctx, key_values, sys_times=None):
    if key_values:
        if attr["type"] == "Relationship":
            return attr["object"]
        if attr["type"] == "LanguageProperty":
            return {"languageMap": attr["languageMap"]}
        return attr["value"]
    rendered = {}
    for member, value in attr.items():
        if member in ATTRIBUTE_MEMBERS:
            rendered[member] = value
        else:
            rendered[ctx.compact(member)] = render_attribute(value, ctx, False)
    if sys_times is not None:
        rendered["createdAt"], rendered["modifiedAt"] = (iso_now(t) for t in sys_times)
    return rendered


def render_entity(entity, ctx, names=None, key_values=False, sys_attrs=False, with_context=False):
    """An entity as a reader with ``ctx`` sees it; ``names`` (expanded) projects the attributes."""
    body = {"id": entity.id, "type": ctx.compact(entity.type)}
    for name, attr in entity.attrs.items():
        if names and name not in names:
            continue
        times = entity.attr_times.get(name) if sys_attrs else None
        body[ctx.compact(name)] = render_attribute(attr, ctx, key_values, times)
    if sys_attrs:
        body["createdAt"], body["modifiedAt"] = iso_now(entity.created), iso_now(entity.modified)
    if with_context:
        body["@context"] = ctx.body_value()
    return body


def write_attributes(entity, attrs, replace=False):
    """Apply attributes (expanded names) to ``entity``; returns the names written."""
    now = time.time()
    if replace:
        entity.attrs = {}
        entity.attr_times = {}
    for name, attr in attrs.items():
        created = entity.attr_times.get(name, (now, now))[0]
        entity.attrs[name] = attr
        entity.attr_times[name] = (created, now)
    entity.modified = now
    return list(attrs)


# --- subscriptions ----------------------------------------------------------------------------------------

def new_subscription_id():
    return "urn:ngsi-ld:Subscription:" + secrets.token_hex(12)


class LdSubscription:
    """An NGSI-LD subscription; names and types expanded with the context it was created with."""

    def __init__(self, sub_id, tenant, ctx):
        self.id = sub_id
        self.tenant = tenant
        self.ctx = ctx
        self.description = None
        self.name = None
        self.entities = []            # [{"id"| "idPattern" (compiled in "_regex"), "type": iri}]
        self.watched = []             # expanded names
        self.notify_attrs = []        # expanded names
        self.format = "normalized"
        self.uri = None
        self.accept = "application/json"
        self.expires = None
        self.throttling = 0.0
        self.active = True
        self.times_sent = 0
        self.last_notification = self.last_success = self.last_failure = None
        self.last_failure_reason = None
        self._last_sent_monotonic = None

    def status(self, now):
        if self.expires is not None and now >= self.expires:
            return "expired"
        return "active" if self.active else "paused"

    def matches(self, entity):
        if not self.entities:
            return True
        for selector in self.entities:
            if selector.get("type") is not None and selector["type"] != entity.type:
                continue
            if "id" in selector and selector["id"] != entity.id:
                continue
            if "_regex" in selector and not selector["_regex"].search(entity.id):
                continue
            return True
        return False

    def render(self, ctx, now):
        body = {"id": self.id, "type": "Subscription"}
        if self.name is not None:
            body["subscriptionName"] = self.name
        if self.description is not None:
            body["description"] = self.description
        if self.entities:
            body["entities"] = [{k: (ctx.compact(v) if k == "type" else v) for k, v in s.items() if k != "_regex"}
                                for s in self.entities]
        if self.watched:
            body["watchedAttributes"] = [ctx.compact(n) for n in self.watched]
        notification = {}
        if self.notify_attrs:
            notification["attributes"] = [ctx.compact(n) for n in self.notify_attrs]
        notification["format"] = self.format
        notification["endpoint"] = {"uri": self.uri, "accept": self.accept}
        notification["status"] = "failed" if (self.last_failure or 0) > (self.last_success or 0) else "ok"
        if self.times_sent:
            notification["timesSent"] = self.times_sent
        for key, value in (("lastNotification", self.last_notification), ("lastSuccess", self.last_success),
                           ("lastFailure", self.last_failure)):
            if value is not None:
                notification[key] = iso_now(value)
        body["notification"] = notification
        if self.expires is not None:
            body["expiresAt"] = iso_now(self.expires)
        if self.throttling:
            body["throttling"] = int(self.throttling) if float(self.throttling).is_integer() else self.throttling
        body["isActive"] = self.active
        body["status"] = self.status(now)
        body["jsonldContext"] = self.ctx.link_url()
        return body


def _string_list(value, what, allow_empty=False):
    if not isinstance(value, list) or (not value and not allow_empty) \
            or not all(isinstance(item, str) and item for item in value):
        raise bad_data(f"Invalid {what}", f"{what} must be a non-empty array of strings")
    return value


def subscription_changes(body, ctx, creating):
    """Check a subscription body (POST or PATCH) and return the fields to set; nothing is set on error."""
    if not isinstance(body, dict):
        raise bad_data("Invalid payload", "Not a JSON Object")
    known = {"id", "type", "@context", "subscriptionName", "name", "description", "entities",
             "watchedAttributes", "notification", "expiresAt", "throttling", "isActive", "q", "geoQ",
             "timeInterval", "csf", "scopeQ", "lang"}
    unknown = sorted(set(body) - known)
    if unknown:
        raise bad_data("Invalid Subscription", f"unknown field: {unknown[0][:100]}")
    for unsupported in ("q", "geoQ", "timeInterval", "csf", "scopeQ", "lang"):
        if unsupported in body:
            raise bad_data("Not supported", f"the stand-in broker does not support {unsupported} in subscriptions")
    if "type" in body or creating:
        if body.get("type") != "Subscription":
            raise bad_data("Invalid Subscription", "the type of a subscription is 'Subscription'")
    changes = {}
    for field, attr in (("subscriptionName", "name"), ("name", "name"), ("description", "description")):
        if field in body:
            if not isinstance(body[field], str):
                raise bad_data("Invalid Subscription", f"{field} must be a string")
            changes[attr] = body[field]
    if "entities" in body:
        raw_entities = body["entities"]
        if not isinstance(raw_entities, list) or not raw_entities:
            raise bad_data("Invalid Subscription", "entities must be a non-empty array")
        selectors = []
        for raw in raw_entities:
            if not isinstance(raw, dict) or not isinstance(raw.get("type"), str):
                raise bad_data("Invalid Subscription", "every item of entities needs a type")
            unknown = set(raw) - {"id", "idPattern", "type"}
            if unknown:
                raise bad_data("Invalid Subscription", f"unknown field in entities: {sorted(unknown)[0][:100]}")
            selector = {"type": ctx.expand(check_name(raw["type"], "entity type name"))}
            if "id" in raw and "idPattern" in raw:
                raise bad_data("Invalid Subscription", "an item of entities has both id and idPattern")
            if "id" in raw:
                selector["id"] = check_entity_id(raw["id"])
            if "idPattern" in raw:
                selector["idPattern"] = raw["idPattern"]
                try:
                    selector["_regex"] = re.compile(raw["idPattern"])
                except (re.error, TypeError):
                    raise bad_data("Invalid idPattern", str(raw["idPattern"])[:200]) from None
            selectors.append(selector)
        changes["entities"] = selectors
    if "watchedAttributes" in body:
        changes["watched"] = [ctx.expand(check_name(n)) for n in _string_list(body["watchedAttributes"],
                                                                              "watchedAttributes")]
    if creating and not changes.get("entities") and not changes.get("watched"):
        raise bad_data("Invalid Subscription", "At least one of 'entities' and 'watchedAttributes' must be present")
    if "notification" in body:
        notification = body["notification"]
        if not isinstance(notification, dict):
            raise bad_data("Invalid Subscription", "notification must be a JSON object")
        endpoint = notification.get("endpoint")
        if not isinstance(endpoint, dict):
            raise bad_data("Invalid Subscription", "Mandatory field missing: notification.endpoint")
        uri = endpoint.get("uri")
        parts = urlsplit(uri) if isinstance(uri, str) else None
        if parts is None or parts.scheme not in ("http", "https") or not parts.hostname:
            raise bad_data("Invalid Subscription", "notification.endpoint.uri must be an http or https URL")
        try:
            parts.port  # noqa: B018 - raises ValueError on a bad port
        except ValueError:
            raise bad_data("Invalid Subscription", "notification.endpoint.uri has a bad port") from None
        changes["uri"] = uri
        accept = endpoint.get("accept", "application/json")
        if accept not in ACCEPT_TYPES:
            raise bad_data("Invalid Subscription", "notification.endpoint.accept must be application/json or "
                                                   "application/ld+json")
        changes["accept"] = accept
        fmt = notification.get("format", "normalized")
        if fmt not in NOTIFICATION_FORMATS:
            raise bad_data("Invalid Subscription", "notification.format must be one of "
                           + ", ".join(NOTIFICATION_FORMATS))
        changes["format"] = fmt
        if "attributes" in notification:
            changes["notify_attrs"] = [ctx.expand(check_name(n)) for n in _string_list(
                notification["attributes"], "notification.attributes")]
        else:
            changes["notify_attrs"] = []
    elif creating:
        raise bad_data("Invalid Subscription", "Mandatory field missing: notification")
    if "expiresAt" in body:
        expires = parse_datetime(body["expiresAt"], "expiresAt")
        if expires <= time.time():
            raise bad_data("Invalid Subscription", "expiresAt is in the past")
        changes["expires"] = expires
    if "throttling" in body:
        throttling = body["throttling"]
        if isinstance(throttling, bool) or not isinstance(throttling, (int, float)) or throttling < 0:
            raise bad_data("Invalid Subscription", "throttling must be a number >= 0")
        changes["throttling"] = float(throttling)
    if "isActive" in body:
        if not isinstance(body["isActive"], bool):
            raise bad_data("Invalid Subscription", "isActive must be true or false")
        changes["active"] = body["isActive"]
    return changes


# --- the request side -------------------------------------------------------------------------------------

class LdRequest:
    """One NGSI-LD request: tenant, content type, the JSON body and the ``@context`` it comes with."""

    def __init__(self, method, query, headers, body):
        self.method = method
        self.query = query
        self.headers = headers
        self.raw_body = body
        content_type = headers.get("Content-Type")
        self.content_type = content_type.split(";")[0].strip().lower() if content_type else None
        tenant_header = headers.get("NGSILD-Tenant") or headers.get("Fiware-Service")
        try:
            self.tenant = model.parse_tenant(tenant_header)
        except model.NgsiError:
            raise bad_data("Invalid tenant name", str(tenant_header)[:100]) from None
        self.link = headers.get("Link")
        self.link_context = parse_link(self.link) if self.link else None
        self._body = None
        if body:
            if self.content_type not in ("application/json", "application/ld+json"):
                raise LdProblem(415, "BadRequestData", "Unsupported Media Type",
                                f"Content-Type {self.content_type or '(none)'}: only application/json and "
                                "application/ld+json are supported")
            if self.content_type == "application/ld+json" and self.link:
                raise bad_data("@context in Link header not allowed",
                               "with Content-Type application/ld+json the @context is in the payload")
            try:
                self._body = json.loads(body.decode("utf-8"))
            except (ValueError, UnicodeDecodeError, RecursionError):
                raise LdProblem(400, "InvalidRequest", "JSON Parse Error",
                                "the request body is not valid JSON") from None
        self.accept_ld = self._accepts_ld(headers.get("Accept"))

    @staticmethod
    def _accepts_ld(accept):
        """True for application/ld+json answers; application/json whenever the client takes it (Orion-LD)."""
        if not accept:
            return False
        types = [part.split(";")[0].strip().lower() for part in accept.split(",")]
        if any(t in ("application/json", "*/*", "application/*") for t in types):
            return False
        if "application/ld+json" in types:
            return True
        raise LdProblem(406, "BadRequestData", "Not Acceptable",
                        "the Accept header must allow application/json or application/ld+json")

    def param(self, name):
        values = self.query.get(name)
        return values[-1] if values else None

    def options(self, allowed):
        options = {o for o in (self.param("options") or "").split(",") if o}
        unknown = options - set(allowed)
        if unknown:
            raise bad_data("Invalid value for URI param 'options'", sorted(unknown)[0][:100])
        return options

    def json(self):
        if self._body is None:
            raise bad_data("Payload body missing", "this request needs a JSON payload")
        return self._body

    def context_of(self, item):
        """The context an item of the body is written in: its ``@context`` (application/ld+json), the Link
        header (application/json) or the core context."""
        if self.content_type == "application/ld+json":
            if not isinstance(item, dict) or "@context" not in item:
                raise bad_data("@context missing in JSON payload",
                               "with Content-Type application/ld+json the payload must hold an @context")
            return Context(item["@context"])
        if isinstance(item, dict) and "@context" in item:
            raise bad_data("Mismatch between Content-Type and payload",
                           "with Content-Type application/json the payload must not hold an @context "
                           "(use application/ld+json or a Link header)")
        return self.request_context()

    def request_context(self):
        """The context of a request without a body (or whose body is not an entity): the Link header's."""
        return Context(self.link_context)

    def entity_response(self, status, body, ctx, headers=None):
        """A JSON answer; application/ld+json with the context in the body, else a Link header."""
        headers = dict(headers or {})
        if self.accept_ld:
            if isinstance(body, list):
                for item in body:
                    item["@context"] = ctx.body_value()
            elif isinstance(body, dict):
                body["@context"] = ctx.body_value()
            content_type = "application/ld+json"
        else:
            headers["Link"] = link_header(ctx.link_url())
            content_type = "application/json"
        return LdResponse(status, json.dumps(body).encode("utf-8"), content_type, headers)


def _json_response(status, body, headers=None):
    return LdResponse(status, json.dumps(body).encode("utf-8"), "application/json", headers)


def _csv(text):
    return [item for item in (text or "").split(",") if item != ""]


def _pagination(req):
    def number(name, default, minimum, maximum=None):
        text = req.param(name)
        if text is None:
            return default
        if not text.isdigit() or int(text) < minimum or (maximum is not None and int(text) > maximum):
            raise bad_data(f"Invalid value for URI param '{name}'", text[:50])
        return int(text)
    return number("limit", DEFAULT_LIMIT, 1, MAX_LIMIT), number("offset", 0, 0)


_ID = r"(?P<eid>[^/]+)"
_ATTR = r"(?P<attr>[^/]+)"
_SUB = r"(?P<sid>[^/]+)"
ROUTES = [(re.compile("^/ngsi-ld/v1" + pattern + "$"), methods) for pattern, methods in [
    (r"/entities/?", {"GET": "query_entities", "POST": "create_entity"}),
    (rf"/entities/{_ID}", {"GET": "get_entity", "DELETE": "delete_entity"}),
    (rf"/entities/{_ID}/attrs/?", {"POST": "append_attrs", "PATCH": "update_attrs"}),
    (rf"/entities/{_ID}/attrs/{_ATTR}", {"PATCH": "patch_attr", "DELETE": "delete_attr"}),
    (r"/entityOperations/upsert/?", {"POST": "upsert"}),
    (r"/subscriptions/?", {"GET": "list_subscriptions", "POST": "create_subscription"}),
    (rf"/subscriptions/{_SUB}", {"GET": "get_subscription", "PATCH": "patch_subscription",
                                 "DELETE": "delete_subscription"}),
]]


def match_route(path):
    """({method: handler name}, [path arguments]) for an NGSI-LD path, or None."""
    for regex, methods in ROUTES:
        match = regex.match(path)
        if match:
            return methods, [unquote(v) for v in match.groups()]
    return None


class NgsiLd:
    """The NGSI-LD handlers over one store; notifications leave through the broker's ``Notifier``."""

    def __init__(self, store, notifier):
        self.store = store
        self.notifier = notifier

    def handle(self, method, path, query, headers, body):
        """Answer one request under ``/ngsi-ld/``; never raises."""
        route = match_route(path)
        if route is None:
            return problem_response(not_found("Service Not Found", path[:300]))
        methods, args = route
        if method not in methods:
            return problem_response(LdProblem(405, "BadRequestData", "Method Not Allowed",
                                              f"{method} {path[:300]}"), {"Allow": ", ".join(sorted(methods))})
        try:
            req = LdRequest(method, query, headers, body)
            return getattr(self, methods[method])(req, *args)
        except LdProblem as problem:
            return problem_response(problem)

    # --- helpers ------------------------------------------------------------------------------------------
    def _tenant(self, req):
        return self.store.tenant(req.tenant)

    @staticmethod
    def _entity(tenant, entity_id):
        check_entity_id(entity_id)
        entity = tenant.ld_entities.get(entity_id)
        if entity is None:
            raise not_found("Entity Not Found", entity_id)
        return entity

    def _changed(self, tenant, entity, names):
        """Notify the subscriptions that watch ``names`` of ``entity`` (under the store lock)."""
        now, monotonic_now = time.time(), time.monotonic()
        for sub in tenant.ld_subscriptions.values():
            if sub.status(now) != "active" or not sub.matches(entity):
                continue
            if sub.watched and not set(sub.watched) & set(names):
                continue
            if sub.throttling and sub._last_sent_monotonic is not None \
                    and monotonic_now - sub._last_sent_monotonic < sub.throttling:
                continue
            self._send(sub, entity, now, monotonic_now)

    def _send(self, sub, entity, now, monotonic_now):
        key_values = sub.format in ("keyValues", "simplified")
        data = render_entity(entity, sub.ctx, set(sub.notify_attrs) or None, key_values)
        notification = {"id": "urn:ngsi-ld:Notification:" + secrets.token_hex(12), "type": "Notification",
                        "subscriptionId": sub.id, "notifiedAt": iso_now(now), "data": [data]}
        headers = {"Accept": "application/json", "User-Agent": "orion-ld (ngsi stand-in broker for tests)",
                   "Fiware-Correlator": str(uuid.uuid1())}
        if sub.accept == "application/ld+json":
            notification["@context"] = sub.ctx.body_value()
            headers["Content-Type"] = "application/ld+json"
        else:
            headers["Content-Type"] = "application/json"
            headers["Link"] = link_header(sub.ctx.link_url())
        if sub.tenant:
            headers["NGSILD-Tenant"] = sub.tenant
        sub.times_sent += 1
        sub.last_notification = now
        sub._last_sent_monotonic = monotonic_now
        self.notifier.post(sub.uri, json.dumps(notification).encode("utf-8"), headers,
                           lambda ok, code, reason: self._done(sub, ok, reason))

    def _done(self, sub, ok, reason):
        with self.store.lock:
            if ok:
                sub.last_success = time.time()
            else:
                sub.last_failure = time.time()
                sub.last_failure_reason = reason

    # --- entities -----------------------------------------------------------------------------------------
    def create_entity(self, req):
        body = req.json()
        ctx = req.context_of(body)
        entity_id, type_iri, attrs = parse_entity(body, ctx)
        with self.store.lock:
            tenant = self._tenant(req)
            if entity_id in tenant.ld_entities:
                raise LdProblem(409, "AlreadyExists", "Entity already exists", entity_id)
            entity = tenant.ld_entities[entity_id] = LdEntity(entity_id, type_iri)
            self._changed(tenant, entity, write_attributes(entity, attrs))
        return LdResponse(201, headers={"Location": f"/ngsi-ld/v1/entities/{entity_id}"})

    def get_entity(self, req, entity_id):
        options = req.options(("keyValues", "simplified", "sysAttrs", "normalized"))
        ctx = req.request_context()
        names = {ctx.expand(check_name(n)) for n in _csv(req.param("attrs"))}
        wanted_type = req.param("type")
        with self.store.lock:
            entity = self._entity(self._tenant(req), entity_id)
            if wanted_type is not None and ctx.expand(wanted_type) != entity.type:
                raise not_found("Entity Not Found", entity_id)
            body = render_entity(entity, ctx, names or None, bool(options & {"keyValues", "simplified"}),
                                 "sysAttrs" in options)
        return req.entity_response(200, body, ctx)

    def query_entities(self, req):
        options = req.options(("keyValues", "simplified", "sysAttrs", "normalized", "count"))
        ctx = req.request_context()
        for unsupported in ("q", "georel", "geometry", "coordinates", "geoproperty", "csf", "scopeQ"):
            if req.param(unsupported) is not None:
                raise bad_data("Not supported", f"the stand-in broker does not support the {unsupported} parameter")
        types = {ctx.expand(check_name(t, "entity type name")) for t in _csv(req.param("type"))}
        ids = {check_entity_id(i) for i in _csv(req.param("id"))}
        id_pattern = req.param("idPattern")
        names = {ctx.expand(check_name(n)) for n in _csv(req.param("attrs"))}
        if not (types or ids or id_pattern is not None or names):
            raise bad_data("Too broad query", "Need at least one of: entity ids, entity types, attribute list")
        regex = None
        if id_pattern is not None:
            try:
                regex = re.compile(id_pattern)
            except re.error:
                raise bad_data("Invalid idPattern", id_pattern[:200]) from None
        limit, offset = _pagination(req)
        count = req.param("count") == "true" or "count" in options
        with self.store.lock:
            found = [e for e in self._tenant(req).ld_entities.values()
                     if (not types or e.type in types) and (not ids or e.id in ids)
                     and (regex is None or regex.search(e.id)) and (not names or set(e.attrs) & names)]
            body = [render_entity(e, ctx, names or None, bool(options & {"keyValues", "simplified"}),
                                  "sysAttrs" in options) for e in found[offset:offset + limit]]
        headers = {"NGSILD-Results-Count": str(len(found))} if count else {}
        return req.entity_response(200, body, ctx, headers)

    def delete_entity(self, req, entity_id):
        with self.store.lock:
            tenant = self._tenant(req)
            self._entity(tenant, entity_id)
            del tenant.ld_entities[entity_id]
        return LdResponse(204)

    # --- attributes ---------------------------------------------------------------------------------------
    def _write_some(self, req, entity_id, overwrite_existing, only_existing):
        body = req.json()
        ctx = req.context_of(body)
        attrs = parse_attributes(body, ctx)
        if not attrs:
            raise bad_data("Invalid payload", "no attributes in the payload")
        with self.store.lock:
            tenant = self._tenant(req)
            entity = self._entity(tenant, entity_id)
            written, not_written = {}, []
            for name, attr in attrs.items():
                exists = name in entity.attrs
                if only_existing and not exists:
                    not_written.append({"attributeName": ctx.compact(name), "reason": "attribute not found"})
                elif exists and not overwrite_existing:
                    not_written.append({"attributeName": ctx.compact(name),
                                        "reason": "attribute exists and options=noOverwrite was given"})
                else:
                    written[name] = attr
            if written:
                self._changed(tenant, entity, write_attributes(entity, written))
        if not_written:
            return _json_response(207, {"updated": [ctx.compact(n) for n in written], "notUpdated": not_written})
        return LdResponse(204)

    def append_attrs(self, req, entity_id):
        options = req.options(("noOverwrite",))
        return self._write_some(req, entity_id, overwrite_existing="noOverwrite" not in options,
                                only_existing=False)

    def update_attrs(self, req, entity_id):
        return self._write_some(req, entity_id, overwrite_existing=True, only_existing=True)

    def patch_attr(self, req, entity_id, attr_name):
        body = req.json()
        ctx = req.context_of(body)
        if not isinstance(body, dict) or not body:
            raise bad_data("Invalid payload", "a non-empty JSON object is needed")
        name = ctx.expand(check_name(attr_name))
        with self.store.lock:
            tenant = self._tenant(req)
            entity = self._entity(tenant, entity_id)
            old = entity.attrs.get(name)
            if old is None:
                raise not_found("Attribute Not Found", attr_name)
            merged = render_attribute(old, ctx, False)
            merged.update({k: v for k, v in body.items() if k != "@context"})
            if merged.get("type") != old["type"]:
                raise bad_data("Invalid attribute", f"{attr_name}: the type of an attribute cannot change here")
            self._changed(tenant, entity, write_attributes(entity, {name: parse_attribute(attr_name, merged,
                                                                                           ctx)}))
        return LdResponse(204)

    def delete_attr(self, req, entity_id, attr_name):
        ctx = req.request_context()
        name = ctx.expand(check_name(attr_name))
        with self.store.lock:
            entity = self._entity(self._tenant(req), entity_id)
            if name not in entity.attrs:
                raise not_found("Attribute Not Found", attr_name)
            del entity.attrs[name]
            entity.attr_times.pop(name, None)
            entity.modified = time.time()
        return LdResponse(204)

    # --- batch --------------------------------------------------------------------------------------------
    def upsert(self, req):
        options = req.options(("update", "replace"))
        if options == {"update", "replace"}:
            raise bad_data("Invalid value for URI param 'options'", "update and replace together")
        body = req.json()
        if not isinstance(body, list) or not body:
            raise bad_data("Invalid payload", "Not a JSON Array (or an empty one)")
        parsed, errors = [], []
        for raw in body:
            try:
                parsed.append(parse_entity(raw, req.context_of(raw)))
            except LdProblem as problem:
                entity_id = raw.get("id") if isinstance(raw, dict) and isinstance(raw.get("id"), str) else None
                errors.append({"entityId": entity_id, "error": dict(problem.body(), status=problem.status)})
        created, success = [], []
        with self.store.lock:
            tenant = self._tenant(req)
            for entity_id, type_iri, attrs in parsed:
                entity = tenant.ld_entities.get(entity_id)
                if entity is None:
                    entity = tenant.ld_entities[entity_id] = LdEntity(entity_id, type_iri)
                    created.append(entity_id)
                    written = write_attributes(entity, attrs)
                else:
                    entity.type = type_iri
                    written = write_attributes(entity, attrs, replace="update" not in options)
                success.append(entity_id)
                self._changed(tenant, entity, written)
        if errors:
            return _json_response(207, {"success": success, "errors": errors})
        if created:
            return _json_response(201, created)
        return LdResponse(204)

    # --- subscriptions ------------------------------------------------------------------------------------
    def create_subscription(self, req):
        body = req.json()
        ctx = req.context_of(body)
        changes = subscription_changes(body, ctx, creating=True)
        sub_id = body.get("id")
        if sub_id is not None:
            if not is_uri(sub_id):
                raise bad_data("Invalid Subscription id", "Not a URI")
        else:
            sub_id = new_subscription_id()
        sub = LdSubscription(sub_id, req.tenant, ctx)
        for field, value in changes.items():
            setattr(sub, field, value)
        with self.store.lock:
            tenant = self._tenant(req)
            if sub_id in tenant.ld_subscriptions:
                raise LdProblem(409, "AlreadyExists", "Subscription already exists", sub_id)
            tenant.ld_subscriptions[sub_id] = sub
        return LdResponse(201, headers={"Location": f"/ngsi-ld/v1/subscriptions/{sub_id}"})

    def _subscription(self, tenant, sub_id):
        if not is_uri(sub_id):
            raise bad_data("Invalid Subscription id", "Not a URI")
        sub = tenant.ld_subscriptions.get(sub_id)
        if sub is None:
            raise not_found("Subscription Not Found", sub_id)
        return sub

    def get_subscription(self, req, sub_id):
        ctx = req.request_context()
        with self.store.lock:
            body = self._subscription(self._tenant(req), sub_id).render(ctx, time.time())
        return req.entity_response(200, body, ctx)

    def list_subscriptions(self, req):
        ctx = req.request_context()
        limit, offset = _pagination(req)
        now = time.time()
        with self.store.lock:
            subs = list(self._tenant(req).ld_subscriptions.values())
            body = [sub.render(ctx, now) for sub in subs[offset:offset + limit]]
        return req.entity_response(200, body, ctx)

    def patch_subscription(self, req, sub_id):
        body = req.json()
        ctx = req.context_of(body)
        if isinstance(body, dict) and not body:
            raise bad_data("Invalid payload", "empty payload")
        if isinstance(body, dict) and "id" in body and body["id"] != sub_id:
            raise bad_data("Invalid Subscription", "the id of a subscription cannot change")
        changes = subscription_changes(body, ctx, creating=False)
        with self.store.lock:
            sub = self._subscription(self._tenant(req), sub_id)
            for field, value in changes.items():
                setattr(sub, field, value)
        return LdResponse(204)

    def delete_subscription(self, req, sub_id):
        with self.store.lock:
            tenant = self._tenant(req)
            self._subscription(tenant, sub_id)
            del tenant.ld_subscriptions[sub_id]
        return LdResponse(204)
