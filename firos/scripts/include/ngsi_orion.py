"""What Orion's two APIs (NGSI v1 and NGSI v2) share, for the clients of `ngsi_v1` and `ngsi_v2`.

Owns `OrionClient`: the tenant headers (`Fiware-Service`, `Fiware-ServicePath`), entity ids that are the robot
names, reading values back (a v1 `%27` JSON text or a v2 percent-encoded value, told apart by their shape), and
notifications in either API's format: Orion notifies in the format of the subscription, whichever API made it, so
a v2 FIROS still reads a v1 notification and the other way round.
"""

from include import ngsi_encoding
from include.ngsi_client import NgsiClient, NotificationError, notified_entities


def decode_value(value):
    """A value as Orion gives it back: a v1 text holding a %27 JSON object becomes that object; anything else is
    v2-decoded (a v1 text that is not such an object stays a decoded string)."""
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


def parse_v2_notification(body):
    """[(entity id, entity type, {attr: (type, decoded value)})] of an NGSI v2 notification ({"data": [...]})."""
    result = []
    for entity in notified_entities(body["data"]):
        attrs = {}
        for name, attr in entity.items():
            if name in ("id", "type"):
                continue
            if not isinstance(attr, dict) or "value" not in attr:
                raise NotificationError(f"attribute \"{name}\" of \"{entity['id']}\" needs a \"value\"")
            attrs[name] = (attr.get("type"), decode_value(attr["value"]))
        result.append((entity["id"], entity.get("type"), attrs))
    return result


def parse_v1_notification(body):
    """The same from an NGSI v1 notification ({"contextResponses": [{"contextElement": ...}]})."""
    responses = body["contextResponses"]
    if not isinstance(responses, list):
        raise NotificationError("\"contextResponses\" must be a list")
    result = []
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
            attrs[attr["name"]] = (attr.get("type"), decode_value(attr["value"]))
        result.append((element["id"], element.get("type"), attrs))
    return result


def parse_orion_notification(body):
    """An Orion notification of either API, told apart by its shape; NotificationError when it is neither."""
    if not isinstance(body, dict):
        raise NotificationError("a notification must be a JSON object")
    if "data" in body:
        return parse_v2_notification(body)
    if "contextResponses" in body:
        return parse_v1_notification(body)
    raise NotificationError("not an NGSI notification: expected \"data\" (v2) or \"contextResponses\" (v1)")


class OrionClient(NgsiClient):
    """The part of a v1 or v2 client that is Orion's whichever API it speaks."""

    def version_headers(self, settings):
        headers = {}
        if settings.fiware_service:
            headers["Fiware-Service"] = settings.fiware_service
        if settings.fiware_servicepath:
            headers["Fiware-ServicePath"] = settings.fiware_servicepath
        return headers

    def parse_notification(self, body):
        return parse_orion_notification(body)
