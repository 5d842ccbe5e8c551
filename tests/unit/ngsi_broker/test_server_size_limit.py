"""The stand-in broker's request size limit at its edge, in-process (real HTTP on loopback): Orion's
1,048,576 bytes are accepted, one byte more is a 413 with Orion's wording in each API's error shape (its own
acceptance tests expect "payload size: 1048577, max size supported: 1048576"), and the connection's next
request is served."""

import json

import pytest

from tests.ngsi_broker.server import MAX_BODY, BrokerServer
from tests.ngsi_broker.testing import BrokerClient

LD_LINK = '<https://uri.etsi.org/ngsi-ld/v1/ngsi-ld-core-context.jsonld>; rel="http://www.w3.org/ns/json-ld#context"'


@pytest.fixture
def client():
    server = BrokerServer(port=0, quiet=True).start()
    try:
        yield BrokerClient(server.url)
    finally:
        server.shutdown()


def padded(body, size):
    """``body`` as JSON text of exactly ``size`` bytes (spaces before the closing brace or bracket)."""
    text = json.dumps(body)
    return (text[:-1] + " " * (size - len(text)) + text[-1]).encode()


def test_the_limit_is_orions_1048576_bytes():
    assert MAX_BODY == 1048576


@pytest.mark.parametrize("path,body,headers,refusal", [
    ("/v2/op/update", {"actionType": "append", "entities": [{"id": "r1", "type": "ROBOT", "a": {"value": 1}}]},
     {}, {"error": "RequestEntityTooLarge", "description": "payload size: 1048577, max size supported: 1048576"}),
    ("/v1/updateContext", {"contextElements": [{"id": "r1", "type": "ROBOT", "isPattern": "false", "attributes": [
        {"name": "a", "type": "T", "value": "1"}]}], "updateAction": "APPEND"}, {},
     {"errorCode": {"code": "413", "reasonPhrase": "Request Entity Too Large",
                    "details": "payload size: 1048577, max size supported: 1048576"}}),
    ("/ngsi-ld/v1/entityOperations/upsert", [{"id": "urn:ngsi-ld:ROBOT:r1", "type": "ROBOT",
                                              "a": {"type": "Property", "value": 1}}], {"Link": LD_LINK},
     {"type": "https://uri.etsi.org/ngsi-ld/errors/RequestEntityTooLarge", "title": "Request Entity Too Large",
      "detail": "payload size: 1048577, max size supported: 1048576"}),
])
def test_one_byte_over_is_413_and_the_limit_itself_is_taken(client, path, body, headers, refusal):
    reply = client.post(path, raw=padded(body, MAX_BODY + 1), headers=headers)
    assert (reply.status, reply.json) == (413, refusal)
    reply = client.post(path, raw=padded(body, MAX_BODY), headers=headers)
    assert reply.status in (200, 201, 204), reply.body[:300]
