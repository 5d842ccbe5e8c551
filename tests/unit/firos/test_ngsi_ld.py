"""FIROS's `include/ngsi_ld.py` against the stand-in broker (in-process): batch upsert, Properties with
`observedAt` and `messageType`, reading back, ProblemDetails in errors, deletes of what is gone."""

import pytest

from include.ngsi_versions import client_for
from tests.support.firos import settings_for


def test_ld_client_writes_by_batch_upsert_and_reports_problem_details(tmp_path, broker):
    from include.ngsi_client import BrokerError
    settings = settings_for(tmp_path, broker.port, version="ld")
    client = client_for(settings)
    assert client.headers["Link"].startswith("<https://uri.etsi.org/ngsi-ld/v1/ngsi-ld-core-context.jsonld>; rel=")
    client.update({"bot": {"COMMAND": ("COMMAND", []), "descriptions": ("DescriptionData", "http://a||http://b")},
                   "bot2": {"pose": ("geometry_msgs.msg.Pose2D", {"firosstamp": 1000.25, "x": 1.0})}})
    _, _, raw = client.request("GET", "/ngsi-ld/v1/entities/urn:ngsi-ld:ROBOT:bot2")
    assert raw["pose"] == {"type": "Property", "value": {"firosstamp": 1000.25, "x": 1.0},
                           "observedAt": "1970-01-01T00:16:40.250Z",
                           "messageType": {"type": "Property", "value": "geometry_msgs.msg.Pose2D"}}
    assert client.get_entity("bot")["descriptions"] == {"type": "Property", "value": "http://a||http://b"}
    assert client.get_entity("bot2")["pose"]["type"] == "geometry_msgs.msg.Pose2D"
    assert client.get_entity("nobody") is None
    # a refused entity in the batch: the broker's ProblemDetails in the error text
    with pytest.raises(BrokerError) as info:
        client.update({"bot": {"a(b": ("std_msgs.msg.Int32", {"data": 1})}})
    assert "urn:ngsi-ld:ROBOT:bot" in str(info.value) and "BadRequestData" in str(info.value), str(info.value)
    with pytest.raises(BrokerError) as info:
        client.request("GET", "/ngsi-ld/v1/entities/not-a-uri")
    assert info.value.status == 400 and "BadRequestData" in str(info.value), str(info.value)
    client.delete_entity("bot2")
    client.delete_entity("bot2")                     # already gone: fine
    assert client.get_entity("bot2") is None
