"""The broker's data: tenants, entities and their attributes, Orion's syntax rules, errors and time formats.

One ``Store`` holds one ``Tenant`` per ``Fiware-Service`` (the default service is ``""``). A tenant keeps its
entities keyed by (service path, id, type) in creation order, as Orion returns them, and its subscriptions.
NGSI v1 and v2 work on the same entities. Every read and write happens under ``Store.lock``.

An attribute is a dict ``{"type": str, "value": any JSON, "metadata": {name: {"type", "value"}}}``.
``set_attributes`` applies new attributes to an entity and says which ones really changed (Orion notifies
only on real changes unless ``forcedUpdate`` is asked for).

``NgsiError`` carries Orion's HTTP status, error name and description; the API modules render it in the shape
of their NGSI version.
"""

import re
import threading
import time
from datetime import datetime, timezone

# Orion's forbidden characters (https://fiware-orion.readthedocs.io/en/master/user/forbidden_characters/)
FORBIDDEN_VALUE_CHARS = frozenset("<>\"'=;()")
# identifiers (entity id/type, attribute and metadata names/types) also refuse these, whitespace and controls
FORBIDDEN_ID_CHARS = FORBIDDEN_VALUE_CHARS | frozenset("&?/#")
MAX_ID_LENGTH = 256
UNRESTRICTED_TYPE = "TextUnrestricted"  # Orion skips the value check for attributes of this type

DEFAULT_ENTITY_TYPE = "Thing"
TENANT_RE = re.compile(r"^[A-Za-z0-9_]{1,50}$")
SERVICE_PATH_COMPONENT_RE = re.compile(r"^[A-Za-z0-9_]{1,50}$")
MAX_SERVICE_PATH_LEVELS = 10
MAX_SERVICE_PATHS_IN_QUERY = 10


class NgsiError(Exception):
    """A client mistake or a missing resource, with Orion's status, error name and description."""

    def __init__(self, status, error, description):
        super().__init__(description)
        self.status = status
        self.error = error
        self.description = description


def bad_request(description):
    return NgsiError(400, "BadRequest", description)


def entity_not_found():
    return NgsiError(404, "NotFound", "The requested entity has not been found. Check type and id")


# --- validation -----------------------------------------------------------------------------------------

def _has_forbidden_id_chars(text):
    """Plain printable ASCII only, without whitespace, ``&?/#`` or Orion's forbidden characters."""
    return any(ch in FORBIDDEN_ID_CHARS or not 32 < ord(ch) < 127 for ch in text)


def check_identifier(value, what):
    """Check an entity id/type or attribute/metadata name/type as Orion does; ``what`` names it."""
    if not isinstance(value, str):
        raise bad_request(f"Invalid JSON type for {what}")
    if len(value) == 0:
        raise bad_request(f"{what} length: 0, min length supported: 1")
    if len(value) > MAX_ID_LENGTH:
        raise bad_request(f"{what} length: {len(value)}, max length supported: {MAX_ID_LENGTH}")
    if _has_forbidden_id_chars(value):
        raise bad_request(f"Invalid characters in {what}")
    return value


def value_has_forbidden_chars(value):
    """True when a string anywhere inside ``value`` (nested lists and objects too) holds a forbidden character."""
    if isinstance(value, str):
        return any(ch in FORBIDDEN_VALUE_CHARS for ch in value)
    if isinstance(value, list):
        return any(value_has_forbidden_chars(item) for item in value)
    if isinstance(value, dict):
        return any(value_has_forbidden_chars(k) or value_has_forbidden_chars(v) for k, v in value.items())
    return False


def check_attribute_value(attr_type, value, description="Invalid characters in attribute value"):
    """Refuse a value holding a forbidden character (NGSI v1 words it "Illegal value for JSON field")."""
    if attr_type != UNRESTRICTED_TYPE and value_has_forbidden_chars(value):
        raise bad_request(description)


def default_type(value):
    """Orion's attribute type for a value given without a type (NGSI v2)."""
    if isinstance(value, bool):
        return "Boolean"
    if isinstance(value, (int, float)):
        return "Number"
    if isinstance(value, str):
        return "Text"
    if value is None:
        return "None"
    return "StructuredValue"


def compile_pattern(pattern, what="entity idPattern"):
    """Compile an Orion regular expression (matched unanchored, like MongoDB's ``$regex``)."""
    if not isinstance(pattern, str) or pattern == "":
        raise bad_request(f"Invalid regex for {what}")
    try:
        return re.compile(pattern)
    except re.error:
        raise bad_request(f"Invalid regex for {what}") from None


# --- tenants and service paths --------------------------------------------------------------------------

def parse_tenant(header_value):
    """``Fiware-Service`` → tenant name (Orion lowercases it); absent or empty → the default tenant ``""``."""
    if header_value is None or header_value.strip() == "":
        return ""
    name = header_value.strip()
    if not TENANT_RE.match(name):
        raise bad_request("bad character in tenant name")
    return name.lower()


def _check_service_path(path):
    if not path.startswith("/"):
        raise bad_request("Only /absolute/ Service Paths allowed [a service path must begin with /]")
    if path == "/":
        return path
    components = path[1:].split("/")
    if len(components) > MAX_SERVICE_PATH_LEVELS:
        raise bad_request("too many components in ServicePath")
    for component in components:
        if not SERVICE_PATH_COMPONENT_RE.match(component):
            raise bad_request("a component of ServicePath contains an illegal character")
    return path


def parse_update_service_path(header_value):
    """``Fiware-ServicePath`` for a write: one absolute path, default ``/``."""
    if header_value is None or header_value.strip() == "":
        return "/"
    path = header_value.strip()
    if "," in path:
        raise bad_request("more than one service path in context update request")
    if path.endswith("/#"):
        raise bad_request("service path must not end with /# in an update")
    return _check_service_path(path.rstrip("/") or "/")


def parse_query_service_paths(header_value):
    """``Fiware-ServicePath`` for a read or a subscription: up to 10 paths, ``/#`` suffix recursive.

    Returns a list of (path, recursive) pairs; the default is everything (``/#``).
    """
    if header_value is None or header_value.strip() == "":
        return [("/", True)]
    paths = [p.strip() for p in header_value.split(",")]
    if len(paths) > MAX_SERVICE_PATHS_IN_QUERY:
        raise bad_request("too many service paths - a maximum of ten service paths is allowed")
    result = []
    for path in paths:
        recursive = path.endswith("/#")
        if recursive:
            path = path[:-2] or "/"
        result.append((_check_service_path(path.rstrip("/") or "/"), recursive))
    return result


def service_path_matches(entity_path, query_paths):
    for path, recursive in query_paths:
        if entity_path == path:
            return True
        if recursive and (path == "/" or entity_path.startswith(path + "/")):
            return True
    return False


# --- time -----------------------------------------------------------------------------------------------

def iso_time(epoch):
    """Orion's rendering of a time: ``2040-01-01T14:00:00.000Z``."""
    moment = datetime.fromtimestamp(epoch, tz=timezone.utc)
    return moment.strftime("%Y-%m-%dT%H:%M:%S.") + f"{moment.microsecond // 1000:03d}Z"


_ISO_FRACTION = re.compile(r"T\d\d:\d\d:\d\d\.(\d+)")


def parse_iso_time(text):
    """An ISO 8601 date or date-time (naive means UTC) → seconds since the epoch; ValueError if malformed."""
    if not isinstance(text, str) or not text:
        raise ValueError("not a date")
    # Python 3.11 reads any ISO 8601 date-time; earlier ones no "Z" suffix and only 3 or 6 digits of fraction
    if text[-1] in "Zz":
        text = text[:-1] + "+00:00"
    fraction = _ISO_FRACTION.search(text)
    if fraction:
        text = text[:fraction.start(1)] + (fraction.group(1) + "000000")[:6] + text[fraction.end(1):]
    moment = datetime.fromisoformat(text)
    if moment.tzinfo is None:
        moment = moment.replace(tzinfo=timezone.utc)
    return moment.timestamp()


_DURATION_RE = re.compile(
    r"^P(?:(?P<years>\d+(?:\.\d+)?)Y)?(?:(?P<months>\d+(?:\.\d+)?)M)?(?:(?P<weeks>\d+(?:\.\d+)?)W)?"
    r"(?:(?P<days>\d+(?:\.\d+)?)D)?"
    r"(?:T(?:(?P<hours>\d+(?:\.\d+)?)H)?(?:(?P<minutes>\d+(?:\.\d+)?)M)?(?:(?P<seconds>\d+(?:\.\d+)?)S)?)?$")
_DURATION_SECONDS = {"years": 365 * 86400, "months": 30 * 86400, "weeks": 7 * 86400, "days": 86400,
                     "hours": 3600, "minutes": 60, "seconds": 1}


def parse_duration(text):
    """An ISO 8601 duration (``P1M``, ``PT5S``, ``P1DT2H``) → seconds; ValueError if malformed."""
    match = _DURATION_RE.match(text) if isinstance(text, str) else None
    if not match or text in ("P", "PT") or text.endswith("T"):
        raise ValueError(f"invalid ISO 8601 duration: {text!r}")
    return sum(float(v) * _DURATION_SECONDS[k] for k, v in match.groupdict().items() if v is not None)


# --- entities -------------------------------------------------------------------------------------------

class Entity:
    """One entity of one tenant: id, type, service path and its attributes in insertion order."""

    def __init__(self, entity_id, entity_type, service_path):
        self.id = entity_id
        self.type = entity_type
        self.service_path = service_path
        self.attrs = {}
        self.created = self.modified = time.time()

    def snapshot(self):
        """A deep-enough copy for rendering outside the lock."""
        copy = Entity(self.id, self.type, self.service_path)
        copy.attrs = {name: {"type": a["type"], "value": a["value"], "metadata": dict(a["metadata"])}
                      for name, a in self.attrs.items()}
        copy.created, copy.modified = self.created, self.modified
        return copy


def set_attributes(entity, attrs, replace=False):
    """Apply ``attrs`` ({name: attribute}) to ``entity``; with ``replace`` drop the others first.

    Returns the names whose type, value or metadata changed (new attributes count as changed).
    """
    changed = []
    if replace:
        for name in list(entity.attrs):
            if name not in attrs:
                del entity.attrs[name]
    for name, attr in attrs.items():
        old = entity.attrs.get(name)
        if old is None or old["type"] != attr["type"] or old["value"] != attr["value"] \
                or old["metadata"] != attr["metadata"] or type(old["value"]) is not type(attr["value"]):
            changed.append(name)
        entity.attrs[name] = attr
    if changed or replace:
        entity.modified = time.time()
    return changed


class Tenant:
    """The entities and subscriptions of one ``Fiware-Service``."""

    def __init__(self, name):
        self.name = name
        self.entities = {}        # (service_path, id, type) -> Entity, in creation order
        self.subscriptions = {}   # id -> subscriptions.Subscription, in creation order
        self.ld_entities = {}     # NGSI-LD entities apart (ngsild.LdEntity by id, in creation order)
        self.ld_subscriptions = {}  # id -> ngsild.LdSubscription

    def find(self, entity_id, entity_type=None, query_paths=(("/", True),)):
        """Entities with this id (and type, when given) under the query's service paths."""
        return [e for e in self.entities.values()
                if e.id == entity_id and (entity_type is None or e.type == entity_type)
                and service_path_matches(e.service_path, query_paths)]

    def find_one(self, entity_id, entity_type, query_paths):
        """The single entity an id (and optional type) names; NotFound or Orion's TooManyResults conflict."""
        found = self.find(entity_id, entity_type, query_paths)
        if not found:
            raise entity_not_found()
        if len(found) > 1:
            raise NgsiError(409, "TooManyResults", "More than one matching entity. Please refine your query")
        return found[0]

    def get_exact(self, service_path, entity_id, entity_type):
        return self.entities.get((service_path, entity_id, entity_type))

    def add(self, entity):
        self.entities[(entity.service_path, entity.id, entity.type)] = entity

    def remove(self, entity):
        self.entities.pop((entity.service_path, entity.id, entity.type), None)

    def query(self, id_matchers, type_matcher, query_paths):
        """Entities in creation order whose id matches one of ``id_matchers`` (callables; none = any) and type."""
        result = []
        for entity in self.entities.values():
            if not service_path_matches(entity.service_path, query_paths):
                continue
            if id_matchers and not any(m(entity.id, entity.type) for m in id_matchers):
                continue
            if type_matcher and not type_matcher(entity.type):
                continue
            result.append(entity)
        return result


class Store:
    """Every tenant of the broker, behind one lock (the HTTP server runs one thread per connection)."""

    def __init__(self):
        self.lock = threading.RLock()
        self.tenants = {}
        self.started = time.time()

    def tenant(self, name):
        tenant = self.tenants.get(name)
        if tenant is None:
            tenant = self.tenants[name] = Tenant(name)
        return tenant


# --- rendering ------------------------------------------------------------------------------------------

def select_attributes(entity, attrs=None, except_attrs=None):
    """The attribute names to render: ``attrs`` (in that order, ``*`` = all) or all but ``except_attrs``."""
    if attrs and "*" not in attrs:
        return [name for name in attrs if name in entity.attrs]
    names = list(entity.attrs)
    if except_attrs:
        names = [name for name in names if name not in except_attrs]
    return names


def v2_entity(entity, names, fmt="normalized"):
    """An entity in NGSI v2 form: ``normalized`` (type/value/metadata), ``keyValues`` or ``values``."""
    if fmt == "values":
        return [entity.attrs[name]["value"] for name in names]
    body = {"id": entity.id, "type": entity.type}
    for name in names:
        attr = entity.attrs[name]
        if fmt == "keyValues":
            body[name] = attr["value"]
        else:
            body[name] = {"type": attr["type"], "value": attr["value"], "metadata": dict(attr["metadata"])}
    return body


def v1_attribute(name, attr, with_value=True):
    """One attribute in NGSI v1 form: name, type, value, plus ``metadatas`` when it has any."""
    rendered = {"name": name, "type": attr["type"], "value": attr["value"] if with_value else ""}
    if attr["metadata"]:
        rendered["metadatas"] = [{"name": md_name, "type": md["type"], "value": md["value"]}
                                 for md_name, md in attr["metadata"].items()]
    return rendered


def v1_context_element_response(entity, names):
    """A ``contextResponses`` item of NGSI v1 (queryContext answers, notifyContextRequest)."""
    return {
        "contextElement": {
            "attributes": [v1_attribute(name, entity.attrs[name]) for name in names],
            "id": entity.id,
            "isPattern": "false",
            "type": entity.type,
        },
        "statusCode": {"code": "200", "reasonPhrase": "OK"},
    }
