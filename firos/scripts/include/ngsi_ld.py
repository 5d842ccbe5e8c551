"""NGSI-LD (ETSI GS CIM 009, as Orion-LD, Scorpio and Stellio serve it under `/ngsi-ld/v1/`): the requests FIROS
makes and the answers and notifications it reads.

Owns the NGSI-LD shapes: entity ids `urn:ngsi-ld:<type>:<robot>` (the rule is `ngsi_encoding`'s), the `@context`
named in a `Link` header and the tenant in `NGSILD-Tenant`, attributes as Properties (a message value with
`observedAt` and its message type as the sub-Property `messageType`), batch upsert with `options=update` (a 207
naming refused entities is a `BrokerError`), entity read and delete, subscriptions (`watchedAttributes`,
`notification.endpoint.uri`, `expiresAt`; id from `Location`), and notifications ({"type": "Notification",
"data": [entities]}; an attribute given as several instances counts by its default instance).
"""

import json
import urllib.parse

from include import ngsi_encoding
from include.ngsi_client import COMMAND, BrokerError, NgsiClient, NotificationError, iso_utc, notified_entities, \
    json_member, json_string, problem_text, quote

LD_BASE = "/ngsi-ld/v1"
LD_CONTEXT_REL = "http://www.w3.org/ns/json-ld#context"
LD_MESSAGE_TYPE = "messageType"     # the sub-Property carrying an attribute's message type
LD_PLAIN_TYPES = (COMMAND, "DescriptionData")   # attribute types FIROS does not write as messageType
LD_ATTRIBUTE_TYPES = ("Property", "Relationship", "GeoProperty", "LanguageProperty", "JsonProperty",
                      "VocabProperty", "ListProperty", "ListRelationship")
LD_NOT_ATTRIBUTES = ("id", "type", "@context", "scope", "createdAt", "modifiedAt", "deletedAt", "location",
                     "observationSpace", "operationSpace")
LD_VALUE_KEYS = ("value", "json", "vocab", "languageMap", "valueList", "objectList")


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
        elif not any(key in attr for key in LD_VALUE_KEYS):
            problem = f"{attr['type']} \"{name}\" of \"{eid}\" needs a \"value\""
        if problem:
            if strict:
                raise NotificationError(problem)
            continue
        if attr["type"] == "Relationship":
            value = attr["object"]
        else:
            value = next(attr[key] for key in LD_VALUE_KEYS if key in attr)
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
    return [(entity["id"], entity.get("type"), ld_attributes(entity)) for entity in notified_entities(body["data"])]


class NgsiLdClient(NgsiClient):
    version = "ld"

    def version_headers(self, settings):
        # NGSI-LD names the @context of a JSON body (and of the terms in a query) in a Link header
        headers = {"Link": f'<{settings.ld_context}>; rel="{LD_CONTEXT_REL}"; type="application/ld+json"'}
        if settings.fiware_service:
            headers["NGSILD-Tenant"] = settings.fiware_service
        return headers

    def entity_id(self, robot):
        return ngsi_encoding.ld_entity_id(self.type, robot)

    def robot_of(self, entity_id):
        try:
            return ngsi_encoding.robot_from_ld_entity_id(entity_id, self.type)
        except ngsi_encoding.NgsiEncodingError:
            return None

    def encode_attribute(self, name, atype, value):
        return json_member(name, ld_property(atype, value))

    def update_body(self, encoded):
        entities = ",".join("{\"id\":%s,\"type\":%s%s}" % (json_string(self.entity_id(robot)),
                                                           json_string(self.type),
                                                           "".join("," + text for text in attrs))
                            for robot, attrs in encoded.items())
        return ("[%s]" % entities).encode("utf-8")

    def _send_update(self, body):
        """NGSI-LD batch upsert with options=update: entities are created when missing, otherwise the given
        attributes are replaced and the others kept (ETSI GS CIM 009 5.6.8 / 6.15.3.1). A 207 answer lists the
        entities the broker refused: that is a BrokerError naming them."""
        status, _, answer = self.request("POST", f"{LD_BASE}/entityOperations/upsert?options=update", data=body,
                                         ok=(200, 201, 204, 207))
        if status == 207:
            errors = answer.get("errors") if isinstance(answer, dict) else None
            if errors:
                text = "; ".join(f"{e.get('entityId')}: {problem_text(e.get('error'), json.dumps(e.get('error')))}"
                                 for e in errors if isinstance(e, dict))
                raise BrokerError(207, f"batch upsert refused for {text}")

    def _delete_entity(self, robot):
        self.request("DELETE", f"{LD_BASE}/entities/{quote(self.entity_id(robot))}")

    def _get_entity(self, robot):
        _, _, body = self.request("GET", f"{LD_BASE}/entities/{quote(self.entity_id(robot))}")
        if not isinstance(body, dict):
            return None
        # the message type where FIROS wrote one, else the NGSI-LD attribute type ("Property")
        return {name: {"type": atype or _ld_kind(body[name]), "value": value}
                for name, (atype, value) in ld_attributes(body, strict=False).items()}

    def subscribe(self, robot, url, length, throttling, now, attrs=()):
        body = {"type": "Subscription", "description": f"FIROS commands for {robot}",
                "entities": [{"id": self.entity_id(robot), "type": self.type}],
                "notification": {"format": "normalized", "endpoint": {"uri": url, "accept": "application/json"}},
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

    def refresh(self, sub_id, length, now):
        self.request("PATCH", f"{LD_BASE}/subscriptions/{quote(sub_id)}", {"expiresAt": iso_utc(now + length)})

    def _unsubscribe(self, sub_id):
        self.request("DELETE", f"{LD_BASE}/subscriptions/{quote(sub_id)}")

    def parse_notification(self, body):
        return parse_ld_notification(body)
