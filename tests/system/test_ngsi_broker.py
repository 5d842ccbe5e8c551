"""The stand-in broker's NGSI v2 side, through real HTTP against a real child process.

One broker child serves the whole module; every test works in its own tenant (``Fiware-Service``), so tests
cannot see each other's entities or subscriptions. Notifications go to real HTTP servers on loopback.
"""

import json
import re
import time
import uuid

import pytest

from tests.ngsi_broker.testing import BrokerClient, NotificationReceiver, start_broker
from tests.support.polling import wait_until
from tests.support.ports import free_port
from tests.support.processes import ProcessGroup

NOT_FOUND = {"error": "NotFound", "description": "The requested entity has not been found. Check type and id"}
BAD_VALUE = {"error": "BadRequest", "description": "Invalid characters in attribute value"}
PARSE_ERROR = {"error": "ParseError", "description": "Errors found in incoming JSON buffer"}


@pytest.fixture(scope="module")
def broker(tmp_path_factory):
    group = ProcessGroup(log_dir=str(tmp_path_factory.mktemp("ngsi-broker")))
    try:
        yield start_broker(group)
    finally:
        group.stop_all()


def new_tenant():
    return "t_" + uuid.uuid4().hex[:12]


@pytest.fixture
def client(broker):
    return BrokerClient(broker.url, service=new_tenant())


@pytest.fixture
def receiver():
    with NotificationReceiver() as server:
        yield server


def robot(entity_id="robot1", **attrs):
    body = {"id": entity_id, "type": "ROBOT"}
    body.update(attrs)
    return body


def create(client, body, **kwargs):
    reply = client.post("/v2/entities", body, **kwargs)
    assert reply.status == 201, reply
    return reply


def subscribe(client, url, entities=None, condition=None, attrs=None, **extra):
    body = {"subject": {"entities": entities or [{"id": "robot1", "type": "ROBOT"}]},
            "notification": {"http": {"url": url}}}
    if condition is not None:
        body["subject"]["condition"] = {"attrs": condition}
    if attrs is not None:
        body["notification"]["attrs"] = attrs
    for key, value in extra.items():
        if key == "attrsFormat":
            body["notification"]["attrsFormat"] = value
        else:
            body[key] = value
    reply = client.post("/v2/subscriptions", body)
    assert reply.status == 201, reply
    return reply.headers["Location"].rsplit("/", 1)[1]


# --- entities ---------------------------------------------------------------------------------------------

def test_create_then_read_in_every_format(client):
    reply = create(client, robot(pose={"type": "geometry_msgs.msg.Pose", "value": {"x": 1.5, "y": -2}},
                                 name={"value": "r1"}))
    assert reply.headers["Location"] == "/v2/entities/robot1?type=ROBOT"
    assert reply.body == b""

    normalized = client.get("/v2/entities/robot1")
    assert normalized.status == 200
    assert normalized.json == {"id": "robot1", "type": "ROBOT",
                               "pose": {"type": "geometry_msgs.msg.Pose", "value": {"x": 1.5, "y": -2},
                                        "metadata": {}},
                               "name": {"type": "Text", "value": "r1", "metadata": {}}}
    assert client.get("/v2/entities/robot1?options=keyValues").json == \
        {"id": "robot1", "type": "ROBOT", "pose": {"x": 1.5, "y": -2}, "name": "r1"}
    assert client.get("/v2/entities/robot1?options=values&attrs=name,pose").json == ["r1", {"x": 1.5, "y": -2}]
    assert client.get("/v2/entities/robot1/attrs?options=keyValues&attrs=name").json == {"name": "r1"}
    assert client.get("/v2/entities/robot1/attrs/name").json == {"type": "Text", "value": "r1", "metadata": {}}


def test_default_type_and_inferred_attribute_types(client):
    reply = create(client, {"id": "e1", "n": {"value": 3}, "b": {"value": True}, "s": {"value": "x"},
                            "o": {"value": [1]}, "z": {"value": None}})
    assert reply.headers["Location"] == "/v2/entities/e1?type=Thing"
    attrs = client.get("/v2/entities/e1").json
    assert attrs["type"] == "Thing"
    assert {name: attrs[name]["type"] for name in "nbsoz"} == {
        "n": "Number", "b": "Boolean", "s": "Text", "o": "StructuredValue", "z": "None"}


def test_create_with_key_values_option(client):
    reply = client.post("/v2/entities?options=keyValues", {"id": "kv", "type": "T", "speed": 12, "tags": ["a"]})
    assert reply.status == 201
    assert client.get("/v2/entities/kv").json["speed"] == {"type": "Number", "value": 12, "metadata": {}}


def test_duplicate_create_is_422_already_exists_and_upsert_appends(client):
    create(client, robot(a={"value": 1}))
    reply = client.post("/v2/entities", robot(a={"value": 2}))
    assert (reply.status, reply.json) == (422, {"error": "Unprocessable", "description": "Already Exists"})
    assert client.get("/v2/entities/robot1?options=keyValues").json["a"] == 1
    reply = client.post("/v2/entities?options=upsert", robot(b={"value": 3}))
    assert reply.status == 204
    assert client.get("/v2/entities/robot1?options=keyValues").json == {"id": "robot1", "type": "ROBOT",
                                                                        "a": 1, "b": 3}


def test_unknown_entity_and_attribute_answers(client):
    for method, path in [("GET", "/v2/entities/ghost"), ("DELETE", "/v2/entities/ghost"),
                         ("GET", "/v2/entities/ghost/attrs"), ("GET", "/v2/entities/ghost/attrs/a/value")]:
        reply = client.request(method, path)
        assert (reply.status, reply.json) == (404, NOT_FOUND), (method, path)
    reply = client.patch("/v2/entities/ghost/attrs", {"a": {"value": 1}})
    assert (reply.status, reply.json) == (404, NOT_FOUND)
    create(client, robot(a={"value": 1}))
    reply = client.get("/v2/entities/robot1?type=OTHER")
    assert (reply.status, reply.json) == (404, NOT_FOUND)
    reply = client.get("/v2/entities/robot1/attrs/nope")
    assert (reply.status, reply.json) == (404, {"error": "NotFound",
                                                "description": "The entity does not have such an attribute"})


def test_same_id_with_two_types_needs_the_type(client):
    create(client, {"id": "x", "type": "A"})
    create(client, {"id": "x", "type": "B"})
    reply = client.get("/v2/entities/x")
    assert (reply.status, reply.json["error"]) == (409, "TooManyResults")
    assert client.get("/v2/entities/x?type=B").json == {"id": "x", "type": "B"}


@pytest.mark.parametrize("char", list("<>\"'=;()"))
def test_forbidden_characters_in_values_are_refused(client, char):
    reply = client.post("/v2/entities", robot(a={"value": f"bad{char}value"}))
    assert (reply.status, reply.json) == (400, BAD_VALUE)
    reply = client.post("/v2/entities", robot(a={"value": {"nested": [f"x{char}"]}}))
    assert (reply.status, reply.json) == (400, BAD_VALUE)
    assert client.get("/v2/entities/robot1").status == 404  # nothing was created


def test_forbidden_characters_in_updates_change_nothing(client):
    create(client, robot(a={"value": "good"}))
    for method, path, body in [("PATCH", "/v2/entities/robot1/attrs", {"a": {"value": "(bad)"}}),
                               ("POST", "/v2/entities/robot1/attrs", {"b": {"value": "<b>"}}),
                               ("PUT", "/v2/entities/robot1/attrs", {"a": {"value": "a=b"}}),
                               ("POST", "/v2/op/update", {"actionType": "append",
                                                          "entities": [robot(a={"value": "x;y"})]})]:
        reply = client.request(method, path, body)
        assert (reply.status, reply.json) == (400, BAD_VALUE), (method, path)
    assert client.get("/v2/entities/robot1?options=keyValues").json == {"id": "robot1", "type": "ROBOT",
                                                                        "a": "good"}


def test_forbidden_characters_in_ids_names_and_types(client):
    cases = [({"id": "bad id", "type": "T"}, "Invalid characters in entity id"),
             ({"id": "a(b)", "type": "T"}, "Invalid characters in entity id"),
             ({"id": "ok", "type": "T<"}, "Invalid characters in entity type"),
             ({"id": "ok", "type": "T", "a/b": {"value": 1}}, "Invalid characters in attribute name"),
             ({"id": "ok", "type": "T", "a": {"type": "x y", "value": 1}}, "Invalid characters in attribute type"),
             ({"type": "T"}, "entity id length: 0, min length supported: 1")]
    for body, description in cases:
        reply = client.post("/v2/entities", body)
        assert (reply.status, reply.json) == (400, {"error": "BadRequest", "description": description}), body


def test_text_unrestricted_skips_the_value_check(client):
    create(client, robot(note={"type": "TextUnrestricted", "value": "a 'quoted' (value)"}))
    assert client.get("/v2/entities/robot1/attrs/note").json["value"] == "a 'quoted' (value)"


def test_bad_json_empty_body_and_content_type(client):
    reply = client.post("/v2/entities", raw=b'{"id": "x",')
    assert (reply.status, reply.json) == (400, PARSE_ERROR)
    reply = client.post("/v2/entities", raw=b"[1, 2")
    assert (reply.status, reply.json) == (400, PARSE_ERROR)
    reply = client.post("/v2/op/update", raw=b"")
    assert (reply.status, reply.json["error"]) == (411, "ContentLengthRequired")
    reply = client.post("/v2/entities", raw=b'{"id": "x"}', content_type="text/xml")
    assert (reply.status, reply.json) == (415, {"error": "UnsupportedMediaType",
                                                "description": "not supported content type: text/xml"})
    reply = client.post("/v2/entities", raw=b'{"id": "x"}', content_type=None)
    assert (reply.status, reply.json["error"]) == (415, "UnsupportedMediaType")
    reply = client.post("/v2/entities", ["not", "an", "object"])
    assert (reply.status, reply.json) == (400, PARSE_ERROR)
    reply = client.post("/v2/entities", robot(a=5))
    assert (reply.status, reply.json["error"]) == (400, "BadRequest")
    assert client.get("/v2/entities").json == []


def test_body_over_one_megabyte_is_413_and_the_broker_keeps_serving(client):
    big = json.dumps(robot(blob={"value": "x" * (1024 * 1024)})).encode()
    reply = client.post("/v2/entities", raw=big)
    assert reply.status == 413
    assert reply.json == {"error": "RequestEntityTooLarge",
                          "description": f"payload size: {len(big)}, max size supported: 1048576"}
    create(client, robot(blob={"value": "x" * (1024 * 1000)}))  # just under the limit is fine
    assert len(client.get("/v2/entities/robot1?options=keyValues").json["blob"]) == 1024 * 1000


def test_unknown_url_and_wrong_method(client):
    reply = client.get("/v2/nothing")
    assert reply.status == 400
    assert reply.json == {"orionError": {"code": "400", "reasonPhrase": "Bad Request",
                                         "details": "Service not found. Check your URL as probably it is wrong."}}
    reply = client.delete("/v2/op/update")
    assert (reply.status, reply.headers["Allow"], reply.body) == (405, "POST", b"")


def test_list_filters_and_pagination(client):
    for i in range(5):
        create(client, {"id": f"robot{i}", "type": "ROBOT", "n": {"value": i}})
    create(client, {"id": "cam1", "type": "CAMERA", "n": {"value": 9}, "fps": {"value": 30}})

    def ids(query):
        reply = client.get("/v2/entities" + query)
        assert reply.status == 200, reply
        return [e["id"] if isinstance(e, dict) else e for e in reply.json]

    assert ids("") == ["robot0", "robot1", "robot2", "robot3", "robot4", "cam1"]
    assert ids("?type=CAMERA") == ["cam1"]
    assert ids("?type=CAMERA,ROBOT&limit=2") == ["robot0", "robot1"]
    assert ids("?idPattern=^robot[13]") == ["robot1", "robot3"]
    assert ids("?idPattern=bot") == ["robot0", "robot1", "robot2", "robot3", "robot4"]  # unanchored, as Orion
    assert ids("?id=robot4,cam1") == ["robot4", "cam1"]
    assert ids("?limit=2&offset=4") == ["robot4", "cam1"]
    projected = client.get("/v2/entities?attrs=fps&options=keyValues").json   # a projection, not a filter
    assert [len(e) for e in projected] == [2, 2, 2, 2, 2, 3] and projected[-1]["fps"] == 30
    reply = client.get("/v2/entities?options=count&limit=1")
    assert reply.headers["Fiware-Total-Count"] == "6"
    assert client.get("/v2/entities?id=cam1&options=keyValues&attrs=fps").json == \
        [{"id": "cam1", "type": "CAMERA", "fps": 30}]
    for bad in ("?idPattern=(", "?id=a&idPattern=b", "?limit=0", "?limit=abc", "?options=nonsense", "?q=n==1"):
        reply = client.get("/v2/entities" + bad)
        assert (reply.status, reply.json["error"]) == (400, "BadRequest"), bad


def test_attribute_operations(client):
    create(client, robot(a={"value": 1}, b={"value": 2}))
    assert client.post("/v2/entities/robot1/attrs", {"c": {"value": 3}}).status == 204
    reply = client.post("/v2/entities/robot1/attrs?options=append", {"c": {"value": 4}})
    assert (reply.status, reply.json["error"]) == (422, "Unprocessable")
    assert client.patch("/v2/entities/robot1/attrs", {"a": {"value": 10}}).status == 204
    reply = client.patch("/v2/entities/robot1/attrs", {"zz": {"value": 1}})
    assert (reply.status, reply.json["error"]) == (422, "Unprocessable")
    assert "zz" in reply.json["description"]
    assert client.get("/v2/entities/robot1?options=keyValues").json == \
        {"id": "robot1", "type": "ROBOT", "a": 10, "b": 2, "c": 3}
    assert client.put("/v2/entities/robot1/attrs", {"only": {"value": "x"}}).status == 204
    assert client.get("/v2/entities/robot1?options=keyValues").json == {"id": "robot1", "type": "ROBOT",
                                                                        "only": "x"}
    assert client.put("/v2/entities/robot1/attrs/only", {"type": "Label", "value": "y"}).status == 204
    assert client.get("/v2/entities/robot1/attrs/only").json == {"type": "Label", "value": "y", "metadata": {}}
    assert client.delete("/v2/entities/robot1/attrs/only").status == 204
    assert client.get("/v2/entities/robot1").json == {"id": "robot1", "type": "ROBOT"}
    assert client.delete("/v2/entities/robot1").status == 204
    assert client.get("/v2/entities/robot1").status == 404


def test_attribute_value_endpoint(client):
    create(client, robot(n={"value": 42}, s={"value": "hi"}, o={"value": {"data": "x"}}))
    reply = client.get("/v2/entities/robot1/attrs/n/value")
    assert (reply.status, reply.headers["Content-Type"], reply.body) == (200, "text/plain", b"42")
    assert client.get("/v2/entities/robot1/attrs/s/value").body == b'"hi"'
    reply = client.get("/v2/entities/robot1/attrs/o/value")
    assert (reply.headers["Content-Type"], reply.json) == ("application/json", {"data": "x"})
    reply = client.get("/v2/entities/robot1/attrs/s/value", headers={"Accept": "application/json"})
    assert (reply.status, reply.json["error"]) == (406, "NotAcceptable")
    assert client.put("/v2/entities/robot1/attrs/n/value", raw=b"43", content_type="text/plain").status == 204
    assert client.put("/v2/entities/robot1/attrs/o/value", {"data": "y"}).status == 204
    assert client.get("/v2/entities/robot1?options=keyValues").json["n"] == 43
    assert client.get("/v2/entities/robot1/attrs/o").json["value"] == {"data": "y"}


def test_op_update_every_action_type(client):
    def op(action, *entities, query=""):
        return client.post("/v2/op/update" + query, {"actionType": action, "entities": list(entities)})

    def state():
        reply = client.get("/v2/entities?options=keyValues")
        return {e["id"]: {k: v for k, v in e.items() if k not in ("id", "type")} for e in reply.json}

    assert op("append", robot("r1", a={"value": 1}), robot("r2", b={"value": 2})).status == 204
    assert state() == {"r1": {"a": 1}, "r2": {"b": 2}}
    assert op("append", robot("r1", c={"value": 3})).status == 204
    reply = op("appendStrict", robot("r1", a={"value": 9}))
    assert (reply.status, reply.json["error"]) == (422, "Unprocessable")
    assert op("appendStrict", robot("r1", d={"value": 4})).status == 204
    assert op("update", robot("r1", a={"value": 11})).status == 204
    reply = op("update", robot("ghost", a={"value": 1}))
    assert (reply.status, reply.json) == (404, NOT_FOUND)
    reply = op("update", robot("r1", nope={"value": 1}))
    assert (reply.status, reply.json["error"]) == (422, "Unprocessable")
    assert op("replace", robot("r2", z={"value": 26})).status == 204
    assert state() == {"r1": {"a": 11, "c": 3, "d": 4}, "r2": {"z": 26}}
    assert op("delete", robot("r1", c={"value": ""})).status == 204
    assert op("delete", robot("r2")).status == 204
    assert state() == {"r1": {"a": 11, "d": 4}}
    assert op("update", {"id": "r1", "type": "ROBOT", "a": 12}, query="?options=keyValues").status == 204
    assert state() == {"r1": {"a": 12, "d": 4}}
    reply = op("upsert", robot("r1"))
    assert (reply.status, reply.json["error"]) == (400, "BadRequest")
    reply = client.post("/v2/op/update", {"actionType": "append", "entities": []})
    assert (reply.status, reply.json["error"]) == (400, "BadRequest")


def test_op_update_checks_every_entity_before_changing_any(client):
    reply = client.post("/v2/op/update", {"actionType": "append", "entities": [
        robot("good", a={"value": 1}), robot("bad", a={"value": "<script>"})]})
    assert (reply.status, reply.json) == (400, BAD_VALUE)
    assert client.get("/v2/entities").json == []


# --- tenants ----------------------------------------------------------------------------------------------

def test_tenants_and_service_paths_are_kept_apart(broker):
    tenant_a, tenant_b = new_tenant(), new_tenant()
    a = BrokerClient(broker.url, service=tenant_a, service_path="/robots")
    create(a, robot(a={"value": 1}))
    assert BrokerClient(broker.url, service=tenant_b).get("/v2/entities").json == []
    assert BrokerClient(broker.url, service_path="/robots").get("/v2/entities/robot1").status == 404
    assert [e["id"] for e in BrokerClient(broker.url, service=tenant_a).get("/v2/entities").json] == ["robot1"]
    assert [e["id"] for e in BrokerClient(broker.url, service=tenant_a, service_path="/#").get(
        "/v2/entities").json] == ["robot1"]
    assert BrokerClient(broker.url, service=tenant_a, service_path="/other").get("/v2/entities").json == []
    # the tenant name is case-insensitive, as in Orion
    assert BrokerClient(broker.url, service=tenant_a.upper(), service_path="/robots").get(
        "/v2/entities/robot1").status == 200
    # a write without a path goes to "/", another entity than the one in /robots
    create(BrokerClient(broker.url, service=tenant_a), robot(b={"value": 2}))
    assert len(BrokerClient(broker.url, service=tenant_a).get("/v2/entities").json) == 2


def test_bad_tenant_headers(broker):
    reply = BrokerClient(broker.url, service="bad-name!").get("/v2/entities")
    assert (reply.status, reply.json) == (400, {"error": "BadRequest", "description": "bad character in tenant name"})
    reply = BrokerClient(broker.url, service=new_tenant(), service_path="relative").get("/v2/entities")
    assert (reply.status, reply.json["error"]) == (400, "BadRequest")
    reply = BrokerClient(broker.url, service=new_tenant(), service_path="/a,/b").post("/v2/entities", robot())
    assert (reply.status, reply.json["error"]) == (400, "BadRequest")


def test_version(broker):
    reply = BrokerClient(broker.url).get("/version")
    assert reply.status == 200
    assert re.match(r"^\d+\.\d+\.\d+$", reply.json["orion"]["version"])
    assert "uptime" in reply.json["orion"]


# --- subscriptions ----------------------------------------------------------------------------------------

def test_subscription_crud(client, receiver):
    sub_id = subscribe(client, receiver.url, condition=["cmd"], attrs=["cmd", "COMMAND"],
                       expires="2040-01-01T14:00:00.00Z", throttling=5, description="firos robot1")
    assert re.fullmatch(r"[0-9a-f]{24}", sub_id)
    reply = client.get(f"/v2/subscriptions/{sub_id}")
    assert reply.status == 200
    assert reply.json == {
        "id": sub_id, "description": "firos robot1",
        "subject": {"entities": [{"id": "robot1", "type": "ROBOT"}], "condition": {"attrs": ["cmd"]}},
        "notification": {"attrs": ["cmd", "COMMAND"], "onlyChangedAttrs": False, "attrsFormat": "normalized",
                         "http": {"url": receiver.url}, "covered": False},
        "expires": "2040-01-01T14:00:00.000Z", "status": "active", "throttling": 5}
    assert [s["id"] for s in client.get("/v2/subscriptions").json] == [sub_id]
    assert client.patch(f"/v2/subscriptions/{sub_id}", {"expires": "2041-01-01T00:00:00Z",
                                                        "throttling": 0.5}).status == 204
    updated = client.get(f"/v2/subscriptions/{sub_id}").json
    assert (updated["expires"], updated["throttling"]) == ("2041-01-01T00:00:00.000Z", 0.5)
    assert client.delete(f"/v2/subscriptions/{sub_id}").status == 204
    for method in ("GET", "DELETE", "PATCH"):
        reply = client.request(method, f"/v2/subscriptions/{sub_id}", {"throttling": 1} if method == "PATCH" else None)
        assert (reply.status, reply.json) == (404, {
            "error": "NotFound", "description": "The requested subscription has not been found. Check id"})
    assert client.get("/v2/subscriptions").json == []


def test_subscription_validation(client, receiver):
    good = {"subject": {"entities": [{"id": "robot1"}]}, "notification": {"http": {"url": receiver.url}}}
    bad_bodies = [
        {"notification": good["notification"]},
        {"subject": good["subject"]},
        {"subject": {"entities": []}, "notification": good["notification"]},
        {"subject": {"entities": [{"type": "ROBOT"}]}, "notification": good["notification"]},
        {"subject": {"entities": [{"idPattern": "("}]}, "notification": good["notification"]},
        {"subject": good["subject"], "notification": {"http": {"url": "not a url"}}},
        {"subject": good["subject"], "notification": {"http": {"url": "ftp://127.0.0.1/x"}}},
        {"subject": good["subject"], "notification": {"http": {}}},
        {"subject": good["subject"], "notification": {"http": {"url": receiver.url}, "attrs": ["a"],
                                                      "exceptAttrs": ["b"]}},
        {"subject": good["subject"], "notification": {"http": {"url": receiver.url}, "attrsFormat": "xml"}},
        dict(good, throttling=-1), dict(good, throttling="5"), dict(good, expires="tomorrow"),
        dict(good, status="sleeping"), dict(good, unknownField=1),
    ]
    for body in bad_bodies:
        reply = client.post("/v2/subscriptions", body)
        assert (reply.status, reply.json["error"]) == (400, "BadRequest"), body
    reply = client.post("/v2/subscriptions", raw=b"{nope")
    assert (reply.status, reply.json) == (400, PARSE_ERROR)
    assert client.get("/v2/subscriptions").json == []
    sub_id = subscribe(client, receiver.url)
    reply = client.patch(f"/v2/subscriptions/{sub_id}", {"throttling": -3})
    assert reply.status == 400
    assert "throttling" not in client.get(f"/v2/subscriptions/{sub_id}").json  # nothing changed


def test_notification_body_and_headers(broker, receiver):
    client = BrokerClient(broker.url, service=new_tenant(), service_path="/robots")
    sub_id = subscribe(client, receiver.url, condition=["cmd"], attrs=["cmd", "COMMAND"])
    create(client, robot(cmd={"type": "std_msgs.msg.String", "value": {"data": "go"}},
                         COMMAND={"type": "COMMAND", "value": ["cmd"]}, other={"value": 1}))
    [note] = receiver.wait_for(1)
    assert note.path == "/notify"
    assert note.json == {"subscriptionId": sub_id, "data": [{
        "id": "robot1", "type": "ROBOT",
        "cmd": {"type": "std_msgs.msg.String", "value": {"data": "go"}, "metadata": {}},
        "COMMAND": {"type": "COMMAND", "value": ["cmd"], "metadata": {}}}]}
    assert note.headers["Content-Type"].startswith("application/json")
    assert note.headers["Ngsiv2-AttrsFormat"] == "normalized"
    assert note.headers["Fiware-Service"] == client.service
    assert note.headers["Fiware-ServicePath"] == "/robots"
    assert note.headers["Fiware-Correlator"]
    stats = wait_until(lambda: (lambda s: s if "lastSuccess" in s["notification"] else None)(
        client.get(f"/v2/subscriptions/{sub_id}").json), message="lastSuccess")
    assert stats["notification"]["timesSent"] == 1
    assert stats["notification"]["lastSuccessCode"] == 200
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z", stats["notification"]["lastNotification"])


def test_default_tenant_notifications_carry_no_service_header(broker, receiver):
    client = BrokerClient(broker.url)
    entity_id = "r_" + uuid.uuid4().hex[:8]
    sub_id = subscribe(client, receiver.url, entities=[{"id": entity_id}])
    create(client, {"id": entity_id, "type": "ROBOT", "a": {"value": 1}})
    [note] = receiver.wait_for(1)
    assert "Fiware-Service" not in note.headers
    assert note.headers["Fiware-ServicePath"] == "/"
    client.delete(f"/v2/subscriptions/{sub_id}")
    client.delete(f"/v2/entities/{entity_id}")


def test_only_condition_attributes_and_real_changes_notify(client, receiver):
    subscribe(client, receiver.url, condition=["cmd"])
    create(client, robot(cmd={"value": 1}, pose={"value": 0}))
    receiver.wait_for(1)
    client.patch("/v2/entities/robot1/attrs", {"pose": {"value": 5}})          # not a condition attribute
    client.patch("/v2/entities/robot1/attrs", {"cmd": {"value": 1}})           # same value: no change
    client.patch("/v2/entities/robot1/attrs?options=forcedUpdate", {"cmd": {"value": 1}})  # forced: notifies
    client.patch("/v2/entities/robot1/attrs", {"cmd": {"value": 2}})           # a real change
    receiver.wait_for(3)
    # one more change through op/update: notifications to one receiver keep their order, so once this one
    # is in, anything the ignored updates had caused would be in too
    fence = client.post("/v2/op/update", {"actionType": "update", "entities": [robot(cmd={"value": 3})]})
    assert fence.status == 204
    notes = receiver.wait_for(4)
    values = [(n.json["data"][0]["cmd"]["value"], n.json["data"][0]["pose"]["value"]) for n in notes]
    assert values == [(1, 0), (1, 5), (2, 5), (3, 5)]


def test_subject_patterns_types_and_formats(client, receiver):
    subscribe(client, receiver.url + "?which=pattern", entities=[{"idPattern": "^robot[0-9]+$", "type": "ROBOT"}],
              attrsFormat="keyValues")
    subscribe(client, receiver.url + "?which=values", entities=[{"id": "robot2"}], attrs=["a"],
              attrsFormat="values")
    create(client, {"id": "robot1", "type": "CAMERA", "a": {"value": 0}})     # wrong type
    create(client, {"id": "robotX", "type": "ROBOT", "a": {"value": 0}})      # id does not match
    create(client, robot("robot2", a={"value": 7}, b={"value": 8}))
    notes = receiver.wait_for(2)
    by_path = {n.path: n for n in notes}
    assert set(by_path) == {"/notify?which=pattern", "/notify?which=values"}
    pattern = by_path["/notify?which=pattern"]
    assert pattern.json["data"] == [{"id": "robot2", "type": "ROBOT", "a": 7, "b": 8}]
    assert pattern.headers["Ngsiv2-AttrsFormat"] == "keyValues"
    assert by_path["/notify?which=values"].json["data"] == [[7]]


def test_except_attrs_and_only_changed_attrs(client, receiver):
    client.post("/v2/subscriptions", {"subject": {"entities": [{"id": "robot1"}]},
                                      "notification": {"http": {"url": receiver.url}, "exceptAttrs": ["secret"],
                                                       "onlyChangedAttrs": True}})
    create(client, robot(a={"value": 1}, b={"value": 2}, secret={"value": 3}))
    client.patch("/v2/entities/robot1/attrs", {"b": {"value": 20}, "secret": {"value": 30}})
    first, second = receiver.wait_for(2)
    assert set(first.json["data"][0]) == {"id", "type", "a", "b"}
    assert set(second.json["data"][0]) == {"id", "type", "b"}


def test_delete_then_recreate_notifies_again(client, receiver):
    subscribe(client, receiver.url)
    create(client, robot(a={"value": 1}))
    assert client.delete("/v2/entities/robot1").status == 204
    create(client, robot(a={"value": 1}))
    notes = receiver.wait_for(2)
    assert [n.json["data"][0]["a"]["value"] for n in notes] == [1, 1]


def test_throttling_drops_notifications_inside_the_window(client, receiver):
    throttling = 1
    subscribe(client, receiver.url, throttling=throttling)
    create(client, robot(n={"value": 0}))
    receiver.wait_for(1)
    client.patch("/v2/entities/robot1/attrs", {"n": {"value": 1}})   # inside the window: dropped
    counter = iter(range(2, 10000))

    def second_notification_arrived():
        client.patch("/v2/entities/robot1/attrs", {"n": {"value": next(counter)}})
        return len(receiver.notifications()) >= 2

    wait_until(second_notification_arrived, timeout=10, interval=0.05, message="a notification after throttling")
    first, second = receiver.notifications()[:2]
    assert second.received_at - first.received_at >= throttling - 0.25
    assert second.json["data"][0]["n"]["value"] >= 2   # the update inside the window was never notified


def test_expiry_and_status(client, receiver):
    expiring = subscribe(client, receiver.url + "?which=expiring", expires=_iso_in(1.5))
    fence = subscribe(client, receiver.url + "?which=fence")
    create(client, robot(n={"value": 0}))
    assert {n.path for n in receiver.wait_for(2)} == {"/notify?which=expiring", "/notify?which=fence"}
    wait_until(lambda: client.get(f"/v2/subscriptions/{expiring}").json["status"] == "expired", timeout=5,
               message="the subscription to expire")
    client.patch("/v2/entities/robot1/attrs", {"n": {"value": 1}})
    notes = receiver.wait_for(3)
    # both go through one ordered worker: had the expired one been sent, it would have arrived first
    assert [n.path for n in notes[2:]] == ["/notify?which=fence"]
    # inactive: no notifications; active again: notifications
    assert client.patch(f"/v2/subscriptions/{fence}", {"status": "inactive"}).status == 204
    assert client.get(f"/v2/subscriptions/{fence}").json["status"] == "inactive"
    revived = subscribe(client, receiver.url + "?which=revived")
    client.patch("/v2/entities/robot1/attrs", {"n": {"value": 2}})
    notes = receiver.wait_for(4)
    assert [n.path for n in notes[3:]] == ["/notify?which=revived"]


def test_subscription_created_already_expired(client, receiver):
    sub_id = subscribe(client, receiver.url, expires="2001-01-01T00:00:00Z")
    assert client.get(f"/v2/subscriptions/{sub_id}").json["status"] == "expired"


def test_dead_subscriber_never_blocks_the_broker(client, receiver):
    dead_url = f"http://127.0.0.1:{free_port()}/nobody"
    dead = subscribe(client, dead_url)
    subscribe(client, receiver.url)
    started = time.monotonic()
    create(client, robot(n={"value": 0}))
    for i in range(1, 6):
        assert client.patch("/v2/entities/robot1/attrs", {"n": {"value": i}}).status == 204
    assert time.monotonic() - started < 2.0
    notes = receiver.wait_for(6)
    assert [n.json["data"][0]["n"]["value"] for n in notes] == [0, 1, 2, 3, 4, 5]
    stats = wait_until(lambda: (lambda s: s if s.get("failsCounter", 0) >= 6 else None)(
        client.get(f"/v2/subscriptions/{dead}").json["notification"]), message="failures recorded")
    assert stats["timesSent"] == 6 and "lastFailure" in stats and "lastSuccess" not in stats


def test_receiver_answering_errors_counts_as_failure(client):
    with NotificationReceiver(status=500) as failing:
        sub_id = subscribe(client, failing.url)
        create(client, robot(n={"value": 0}))
        failing.wait_for(1)
        stats = wait_until(lambda: (lambda s: s if "lastFailure" in s else None)(
            client.get(f"/v2/subscriptions/{sub_id}").json["notification"]), message="lastFailure")
        assert stats["failsCounter"] == 1


def test_subscriptions_of_other_tenants_are_not_notified(broker, receiver):
    a = BrokerClient(broker.url, service=new_tenant())
    b = BrokerClient(broker.url, service=new_tenant())
    subscribe(a, receiver.url + "?tenant=a")
    subscribe(b, receiver.url + "?tenant=b")
    create(b, robot(n={"value": 1}))
    create(a, robot(n={"value": 2}))
    notes = receiver.wait_for(2)
    assert sorted((n.path, n.json["data"][0]["n"]["value"]) for n in notes) == [
        ("/notify?tenant=a", 2), ("/notify?tenant=b", 1)]
    assert [n.headers["Fiware-Service"] for n in sorted(notes, key=lambda n: n.path)] == [a.service, b.service]


def _iso_in(seconds):
    from datetime import datetime, timedelta, timezone
    return (datetime.now(timezone.utc) + timedelta(seconds=seconds)).strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"


def test_connections_are_kept_alive_across_answers_of_every_kind(broker):
    import http.client
    service = new_tenant()
    conn = http.client.HTTPConnection("127.0.0.1", broker.port, timeout=5)
    try:
        statuses = []
        for method, path, body in [("POST", "/v2/entities", robot(a={"value": 1})),
                                   ("GET", "/v2/entities/ghost", None),
                                   ("POST", "/v2/entities", b'{"broken'),
                                   ("PATCH", "/v2/entities/robot1/attrs", {"a": {"value": 2}}),
                                   ("GET", "/v2/entities/robot1?options=keyValues", None)]:
            data = body if isinstance(body, bytes) else (json.dumps(body).encode() if body else None)
            headers = {"Fiware-Service": service}
            if data:
                headers["Content-Type"] = "application/json"
            conn.request(method, path, body=data, headers=headers)
            response = conn.getresponse()
            payload = response.read()
            statuses.append(response.status)
        assert statuses == [201, 404, 400, 204, 200]
        assert json.loads(payload)["a"] == 2
    finally:
        conn.close()


def test_chunked_body_is_411_as_orion(client):
    import http.client
    conn = http.client.HTTPConnection("127.0.0.1", client.port, timeout=5)
    try:
        conn.request("POST", "/v2/entities", body=iter([b'{"id": "x", "type": "T"}']),
                     headers={"Content-Type": "application/json", "Fiware-Service": client.service},
                     encode_chunked=True)
        response = conn.getresponse()
        assert (response.status, json.loads(response.read())["error"]) == (411, "ContentLengthRequired")
    finally:
        conn.close()
    assert client.get("/v2/entities").json == []


def test_list_subscriptions_by_service_path(broker, receiver):
    service = new_tenant()
    robots = BrokerClient(broker.url, service=service, service_path="/robots")
    other = BrokerClient(broker.url, service=service, service_path="/cameras")
    sub_id = subscribe(robots, receiver.url)
    subscribe(other, receiver.url)
    assert [s["id"] for s in robots.get("/v2/subscriptions").json] == [sub_id]
    assert len(BrokerClient(broker.url, service=service).get("/v2/subscriptions").json) == 2
    # the subscription only sees its own path
    create(other, robot(a={"value": 1}))
    create(robots, robot(a={"value": 2}))
    notes = receiver.wait_for(2)
    by_id = {n.json["subscriptionId"]: n.json["data"][0]["a"]["value"] for n in notes}
    assert by_id[sub_id] == 2


def test_fault_injection_for_error_path_tests(broker):
    client = BrokerClient(broker.url, service=new_tenant())
    admin = BrokerClient(broker.url)
    create(client, robot(a={"value": 1}))
    try:
        assert admin.post("/_standin/faults", {"status": 503, "count": 2, "path": "^/v2/op/update",
                                               "method": "POST"}).status == 201
        assert admin.get("/_standin/faults").json == [{"status": 503, "count": 2, "path": "^/v2/op/update",
                                                       "method": "POST"}]
        update = {"actionType": "append", "entities": [robot(a={"value": 2})]}
        assert client.get("/v2/entities/robot1").status == 200          # other paths are not affected
        for _ in range(2):
            reply = client.post("/v2/op/update", update)
            assert (reply.status, reply.json["error"]) == (503, "ServiceUnavailable")
        assert client.get("/v2/entities/robot1?options=keyValues").json["a"] == 1   # the failed ones changed nothing
        assert client.post("/v2/op/update", update).status == 204      # the faults are used up
        assert admin.get("/_standin/faults").json == []
        # status 0: the connection is closed without an answer
        assert admin.post("/_standin/faults", {"status": 0, "path": "^/v1/"}).status == 201
        import http.client
        with pytest.raises((http.client.RemoteDisconnected, ConnectionResetError)):
            client.post("/v1/queryContext", {"entities": [{"id": "robot1"}]})
        assert client.post("/v1/queryContext", {"entities": [{"id": "robot1"}]}).status == 200
        assert admin.post("/_standin/faults", {"status": 500, "count": 5}).status == 201
        assert admin.delete("/_standin/faults").status == 204
        assert client.get("/v2/entities/robot1").status == 200
        for bad in ({"status": 200}, {"count": 0}, {"path": "("}, {"method": "BREW"}):
            assert admin.post("/_standin/faults", bad).status == 400, bad
    finally:
        admin.delete("/_standin/faults")  # faults are broker-wide: never leave one behind
