"""FIROS's `include/ngsi_client.py` (what every version's client shares) and `include/ngsi_versions.py` (the one
choice of version), against the stand-in broker in-process: one client class per configured version, and
"already gone" told by the HTTP status the broker answers, never by the text of its answer."""

import pytest

from include import config as cfg
from include.ngsi_client import BrokerError, NgsiClient
from include.ngsi_ld import NgsiLdClient
from include.ngsi_v1 import NgsiV1Client
from include.ngsi_v2 import NgsiV2Client
from include.ngsi_versions import CLIENTS, client_for
from tests.support.firos import RecordingBroker, request, settings_for

# the request each version sends to delete an entity, as a fault path of the stand-in broker
DELETE_PATHS = {"v1": ("POST", "^/v1/updateContext$"), "v2": ("DELETE", "^/v2/entities/"),
                "ld": ("DELETE", "^/ngsi-ld/v1/entities/")}
READ_PATHS = {"v1": ("POST", "^/v1/queryContext$"), "v2": ("GET", "^/v2/entities/"),
              "ld": ("GET", "^/ngsi-ld/v1/entities/")}


def test_every_configurable_version_has_its_client_class():
    assert set(CLIENTS) == set(cfg.NGSI_VERSIONS)
    for version, cls in CLIENTS.items():
        assert issubclass(cls, NgsiClient) and cls.version == version


@pytest.mark.parametrize("version,cls", [("v1", NgsiV1Client), ("v2", NgsiV2Client), ("ld", NgsiLdClient)])
def test_the_configured_version_chooses_the_client_once(tmp_path, version, cls):
    client = client_for(settings_for(tmp_path, 1026, version=version, fiware_service="robots"))
    assert type(client) is cls
    assert client.watches_command is (version == "v1")
    tenant = "NGSILD-Tenant" if version == "ld" else "Fiware-Service"
    assert client.headers[tenant] == "robots" and ("Link" in client.headers) is (version == "ld")


def _fault(broker, method, path, status):
    assert request(broker.port, "POST", "/_standin/faults",
                   {"status": status, "count": 1, "method": method, "path": path})[0] == 201


@pytest.mark.parametrize("version", ["v1", "v2", "ld"])
def test_gone_is_the_status_404_not_a_404_in_the_text(tmp_path, broker, version):
    client = client_for(settings_for(tmp_path, broker.port, version=version))
    client.update({"bot404": {"a": ("std_msgs.msg.Int32", {"data": 1})}})
    _fault(broker, *DELETE_PATHS[version], 404)
    client.delete_entity("bot404")                       # the broker says 404: already gone, fine
    _fault(broker, *DELETE_PATHS[version], 400)
    with pytest.raises(BrokerError) as info:             # a 400 about an entity whose name holds "404"
        client.delete_entity("bot404")
    assert info.value.status == 400
    _fault(broker, *READ_PATHS[version], 404)
    assert client.get_entity("bot404") is None
    _fault(broker, *READ_PATHS[version], 409)
    with pytest.raises(BrokerError) as info:
        client.get_entity("bot404")
    assert info.value.status == 409
    assert client.get_entity("bot404")["a"]["value"] == {"data": 1}
    client.delete_entity("bot404")
    assert client.get_entity("bot404") is None
    client.delete_entity("bot404")                       # gone for real: the broker's own 404


# a refusal whose text names "404" (the entity is called bot404) in each version's error shape: still a refusal
REFUSALS = {
    "v1": (200, {"orionError": {"code": "400", "reasonPhrase": "Bad Request", "details": "bad id bot404"}}),
    "v2": (400, {"error": "BadRequest", "description": "entity bot404: 404 is not a good name"}),
    "ld": (400, {"type": "https://uri.etsi.org/ngsi-ld/errors/BadRequestData", "title": "Bad Request",
                 "detail": "urn:ngsi-ld:ROBOT:bot404 (404)"}),
}


@pytest.mark.parametrize("version", ["v1", "v2", "ld"])
def test_a_refusal_mentioning_404_is_not_taken_for_gone(tmp_path, version):
    server = RecordingBroker(answer=lambda index, method, path, body: REFUSALS[version])
    try:
        client = client_for(settings_for(tmp_path, server.port, version=version))
        for call in (client.delete_entity, client.get_entity, client.unsubscribe):
            with pytest.raises(BrokerError) as info:
                call("bot404")
            assert info.value.status == 400 and "404" in str(info.value)
    finally:
        server.close()
