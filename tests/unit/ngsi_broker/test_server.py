"""The stand-in broker's server in this process: it starts, serves and shuts down."""

import pytest


# --- the command line -------------------------------------------------------------------------------------


def test_in_process_broker_starts_serves_and_shuts_down():
    from tests.ngsi_broker.server import BrokerServer
    from tests.ngsi_broker.testing import BrokerClient
    broker = BrokerServer(port=0, quiet=True).start()
    try:
        client = BrokerClient(broker.url)
        assert client.post("/v2/entities", {"id": "r1", "type": "ROBOT"}).status == 201
        assert client.get("/v2/entities/r1").json == {"id": "r1", "type": "ROBOT"}
    finally:
        broker.shutdown()
    with pytest.raises(OSError):
        BrokerClient(broker.url, timeout=1).get("/version")
    BrokerServer(port=0, quiet=True).shutdown()   # never started: shutting down does not hang
