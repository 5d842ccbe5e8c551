"""NGSI v1 (Orion before 4.0; before 3.10 for subscriptions): the requests FIROS makes and the answers it reads.

Owns the v1 shapes: `updateContext` APPEND (message values as the seed's `%27` JSON text, `ngsi_encoding.encode_v1`;
other values as in v2) and DELETE, `queryContext`, `subscribeContext` ONCHANGE with an ISO 8601 `duration`,
`updateContextSubscription`, `unsubscribeContext`; and v1's way of reporting errors: HTTP 200 with an
`errorCode`, `statusCode`, `orionError` or `subscribeError` inside the body, whose code becomes the
`BrokerError`'s status. Orion v1 notifies only real changes and has no forcedUpdate, so FIROS's v1 subscriptions
also watch `COMMAND` (`watches_command`): a repeated command changes it from `[]` back to the attribute's name.
"""

import json

from include import ngsi_encoding
from include.ngsi_client import BrokerError, json_string, strict_json
from include.ngsi_orion import OrionClient, decode_value


def iso_duration(seconds):
    return f"PT{int(round(seconds))}S"


def encode_value(value):
    """A v1 attribute value: a message object as %27 JSON text, anything else as v2 writes it."""
    if isinstance(value, dict):
        return ngsi_encoding.encode_v1(value)
    return ngsi_encoding.encode_v2(value)


def _code(error):
    """The HTTP status a v1 error object names (400 when it names none that is a number)."""
    code = str(error.get("code", ""))
    return int(code) if code.isdigit() else 400


def raise_v1_error(answer):
    """NGSI v1 reports errors with HTTP 200 and an errorCode / statusCode inside the body: a BrokerError with that
    code as its status."""
    error = answer.get("errorCode")
    for wrapper in ("subscribeError", "orionError"):      # updateContextSubscription / parse errors
        inner = answer.get(wrapper)
        if isinstance(inner, dict):
            error = inner.get("errorCode", inner)
    if isinstance(error, dict) and str(error.get("code", "200")) != "200":
        raise BrokerError(_code(error), json.dumps(answer))
    for response in answer.get("contextResponses", []) or []:
        status = (response or {}).get("statusCode") or {}
        if str(status.get("code", "200")) != "200":
            raise BrokerError(_code(status), json.dumps(answer))
    status = answer.get("statusCode")
    if isinstance(status, dict) and str(status.get("code", "200")) != "200":
        raise BrokerError(_code(status), json.dumps(answer))


class NgsiV1Client(OrionClient):
    version = "v1"
    watches_command = True

    def check_answer(self, parsed):
        if isinstance(parsed, dict):
            raise_v1_error(parsed)

    def _element(self, robot, attributes=None):
        element = {"type": self.type, "isPattern": "false", "id": robot}
        if attributes is not None:
            element["attributes"] = attributes
        return element

    def encode_attribute(self, name, atype, value):
        return strict_json({"name": name, "type": atype, "value": encode_value(value)})

    def update_body(self, encoded):
        elements = ",".join("{\"type\":%s,\"isPattern\":\"false\",\"id\":%s,\"attributes\":[%s]}"
                            % (json_string(self.type), json_string(robot), ",".join(attrs))
                            for robot, attrs in encoded.items())
        return ("{\"contextElements\":[%s],\"updateAction\":\"APPEND\"}" % elements).encode("utf-8")

    def _send_update(self, body):
        self.request("POST", "/v1/updateContext", data=body)

    def _delete_entity(self, robot):
        self.request("POST", "/v1/updateContext", {"contextElements": [self._element(robot)],
                                                   "updateAction": "DELETE"})

    def _get_entity(self, robot):
        _, _, body = self.request("POST", "/v1/queryContext", {"entities": [self._element(robot)]})
        for response in (body or {}).get("contextResponses", []):
            element = response.get("contextElement", {})
            if element.get("id") == robot:
                return {a.get("name"): {"type": a.get("type"), "value": decode_value(a.get("value"))}
                        for a in element.get("attributes", []) if isinstance(a, dict)}
        return None

    def subscribe(self, robot, url, length, throttling, now, attrs=()):
        body = {"entities": [self._element(robot)], "attributes": [],
                "reference": url, "duration": iso_duration(length),
                "notifyConditions": [{"type": "ONCHANGE", "condValues": list(attrs)}],
                "throttling": iso_duration(throttling)}
        _, _, answer = self.request("POST", "/v1/subscribeContext", body)
        sub_id = ((answer or {}).get("subscribeResponse") or {}).get("subscriptionId")
        if not sub_id:
            raise BrokerError(200, f"subscribeContext answered without a subscriptionId: {answer}")
        return sub_id

    def refresh(self, sub_id, length, now):
        self.request("POST", "/v1/updateContextSubscription",
                     {"subscriptionId": sub_id, "duration": iso_duration(length)})

    def _unsubscribe(self, sub_id):
        self.request("POST", "/v1/unsubscribeContext", {"subscriptionId": sub_id})
