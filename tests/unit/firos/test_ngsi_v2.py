"""FIROS's `include/ngsi_v2.py` (and the connection of `ngsi_client.py` under it) against a recording HTTP
server: batches go to `/v2/op/update` over one kept-alive connection."""

from include.ngsi_versions import client_for
from tests.support.firos import RecordingBroker, settings_for


def test_client_reuses_one_connection(tmp_path):
    server = RecordingBroker()
    try:
        client = client_for(settings_for(tmp_path, server.port))
        for i in range(5):
            client.update({"bot": {"a": ("std_msgs.msg.Int32", {"data": i})}})
        assert len(server.requests) == 5
        assert len({port for port, _, _ in server.requests}) == 1       # HTTP/1.1 keep-alive
        assert server.requests[-1][1] == "/v2/op/update"
        assert server.requests[-1][2]["entities"][0]["a"] == {"type": "std_msgs.msg.Int32", "value": {"data": 4}}
    finally:
        server.close()
