"""FIROS's `include/ngsi_orion.py`: Orion's notifications in v1 and v2 format (either read by a v1 or a v2
client), values decoded, malformed bodies refused."""

import pytest

from include.ngsi_client import NotificationError
from include.ngsi_orion import parse_orion_notification as parse_notification


def test_parse_v1_notification_with_the_seed_value():
    body = {"subscriptionId": "abc", "originator": "localhost", "contextResponses": [{"contextElement": {
        "type": "ROBOT", "isPattern": "false", "id": "end_end_test", "attributes": [
            {"name": "p1", "type": "std_msgs.msg.String", "value": "{%27data%27: %2712345%27}"},
            {"name": "COMMAND", "type": "COMMAND", "value": ["p1"]}]},
        "statusCode": {"code": "200", "reasonPhrase": "OK"}}]}
    ((eid, etype, attrs),) = parse_notification(body)
    assert (eid, etype) == ("end_end_test", "ROBOT")
    assert attrs == {"p1": ("std_msgs.msg.String", {"data": "12345"}), "COMMAND": ("COMMAND", ["p1"])}


def test_parse_v2_notification_decodes_forbidden_characters():
    body = {"subscriptionId": "x", "data": [{"id": "bot", "type": "ROBOT",
                                             "say": {"type": "std_msgs.msg.String",
                                                     "value": {"data": "a%3Cb%3E %22q%22 %28x%29%3B y%3Dz"},
                                                     "metadata": {}}}]}
    ((_, _, attrs),) = parse_notification(body)
    assert attrs["say"][1] == {"data": "a<b> \"q\" (x); y=z"}


@pytest.mark.parametrize("body", [[], "x", {}, {"data": 1}, {"data": [{"id": 3}]},
                                  {"data": [{"id": "a", "p": 1}]}, {"contextResponses": [{}]},
                                  {"contextResponses": [{"contextElement": {"id": "a", "attributes": [{}]}}]}])
def test_bad_notifications(body):
    with pytest.raises(NotificationError):
        parse_notification(body)
