"""NGSI v2 (Orion 4.x, and Orion 1.x to 3.x beside v1): the requests FIROS makes and the answers it reads.

Owns the v2 shapes: batch updates (`POST /v2/op/update`, actionType append; values percent-encoded by
`ngsi_encoding.encode_v2`), entity read and delete (`/v2/entities/{id}?type=`), subscriptions (`POST
/v2/subscriptions` with `expires` and `throttling`, id from `Location`; refreshed by `PATCH` of `expires`; removed
by `DELETE`).
"""

from include import ngsi_encoding
from include.ngsi_client import BrokerError, iso_utc, json_member, json_string, quote
from include.ngsi_orion import OrionClient, decode_value


class NgsiV2Client(OrionClient):
    version = "v2"

    def encode_attribute(self, name, atype, value):
        return json_member(name, {"type": atype, "value": ngsi_encoding.encode_v2(value)})

    def update_body(self, encoded):
        entities = ",".join("{\"id\":%s,\"type\":%s%s}" % (json_string(robot), json_string(self.type),
                                                           "".join("," + text for text in attrs))
                            for robot, attrs in encoded.items())
        return ("{\"actionType\":\"append\",\"entities\":[%s]}" % entities).encode("utf-8")

    def _send_update(self, body):
        self.request("POST", "/v2/op/update", data=body)

    def _delete_entity(self, robot):
        self.request("DELETE", f"/v2/entities/{quote(robot)}?type={quote(self.type)}")

    def _get_entity(self, robot):
        _, _, body = self.request("GET", f"/v2/entities/{quote(robot)}?type={quote(self.type)}")
        if not isinstance(body, dict):
            return None
        return {name: {"type": attr.get("type"), "value": decode_value(attr.get("value"))}
                for name, attr in body.items() if isinstance(attr, dict)}

    def subscribe(self, robot, url, length, throttling, now, attrs=()):
        body = {"description": f"FIROS commands for {robot}",
                "subject": {"entities": [{"id": robot, "type": self.type}], "condition": {"attrs": list(attrs)}},
                "notification": {"http": {"url": url}, "attrs": [], "attrsFormat": "normalized"},
                "expires": iso_utc(now + length), "throttling": int(round(throttling))}
        _, headers, _ = self.request("POST", "/v2/subscriptions", body)
        sub_id = headers.get("location", "").rstrip("/").rsplit("/", 1)[-1]
        if not sub_id:
            raise BrokerError(201, "subscription created without a Location header")
        return sub_id

    def refresh(self, sub_id, length, now):
        self.request("PATCH", f"/v2/subscriptions/{quote(sub_id)}", {"expires": iso_utc(now + length)})

    def _unsubscribe(self, sub_id):
        self.request("DELETE", f"/v2/subscriptions/{quote(sub_id)}")
