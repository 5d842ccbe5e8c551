"""The stand-in broker's NGSI-LD side (``/ngsi-ld/v1/``), through real HTTP against a real child process.

One broker child serves the module; every test has its own tenant (``NGSILD-Tenant``). Notifications go to real
HTTP servers on loopback. What is checked is what Orion-LD answers (docs/STANDIN_BROKER.md, "NGSI-LD").
"""

import json
import time
import uuid

import pytest

from tests.ngsi_broker.testing import BrokerClient, NotificationReceiver, start_broker
from tests.support.polling import wait_until
from tests.support.processes import ProcessGroup

CORE = "https://uri.etsi.org/ngsi-ld/v1/ngsi-ld-core-context.jsonld"
ERR = "https://uri.etsi.org/ngsi-ld/errors/"
LINK_REL = 'rel="http://www.w3.org/ns/json-ld#context"'


@pytest.fixture(scope="module")
def broker(tmp_path_factory):
    group = ProcessGroup(log_dir=str(tmp_path_factory.mktemp("ngsi-broker-ld")))
    try:
        yield start_broker(group, extra_args=["--quiet"])
    finally:
        group.stop_all()


class LdClient(BrokerClient):
    """BrokerClient with an NGSI-LD tenant header instead of Fiware-Service."""

    def __init__(self, url, tenant):
        super().__init__(url)
        self.tenant = tenant

    def request(self, method, path, body=None, headers=None, **kwargs):
        all_headers = {"NGSILD-Tenant": self.tenant}
        all_headers.update(headers or {})
        return super().request(method, path, body, headers=all_headers, **kwargs)


@pytest.fixture
def client(broker):
    return LdClient(broker.url, "ld_" + uuid.uuid4().hex[:12])


@pytest.fixture
def receiver():
    with NotificationReceiver() as server:
        yield server


def robot(name="robot1", **attrs):
    body = {"id": f"urn:ngsi-ld:ROBOT:{name}", "type": "ROBOT"}
    body.update(attrs)
    return body


def prop(value, **extra):
    return dict({"type": "Property", "value": value}, **extra)


def create(client, body, **kwargs):
    reply = client.post("/ngsi-ld/v1/entities", body, **kwargs)
    assert reply.status == 201, reply
    return reply


def assert_problem(reply, status, kind, title=None):
    assert reply.status == status, reply
    assert reply.headers["Content-Type"].startswith("application/json"), reply.headers
    assert reply.json["type"] == ERR + kind, reply.json
    assert isinstance(reply.json["title"], str) and reply.json["title"], reply.json
    if title is not None:
        assert reply.json["title"] == title, reply.json


def subscribe(client, url, **fields):
    body = {"type": "Subscription", "entities": [{"type": "ROBOT"}], "notification": {"endpoint": {"uri": url}}}
    body.update(fields)
    reply = client.post("/ngsi-ld/v1/subscriptions", body)
    assert reply.status == 201, reply
    return reply.headers["Location"].rsplit("/", 1)[1]


# --- entities -----------------------------------------------------------------------------------------------

def test_create_then_read_back_with_link_header_or_body_context(client):
    reply = create(client, robot(COMMAND=prop(["move.goal"]),
                                 **{"move.goal": prop({"x": 1, "text": "a<b>'c'"},
                                                      observedAt="2026-11-23T10:00:00.000Z")}))
    assert reply.headers["Location"] == "/ngsi-ld/v1/entities/urn:ngsi-ld:ROBOT:robot1"

    got = client.get("/ngsi-ld/v1/entities/urn:ngsi-ld:ROBOT:robot1")
    assert got.status == 200
    assert got.headers["Content-Type"] == "application/json"
    assert got.headers["Link"] == f'<{CORE}>; {LINK_REL}; type="application/ld+json"'
    assert got.json == {"id": "urn:ngsi-ld:ROBOT:robot1", "type": "ROBOT",
                        "COMMAND": {"type": "Property", "value": ["move.goal"]},
                        "move.goal": {"type": "Property", "value": {"x": 1, "text": "a<b>'c'"},
                                      "observedAt": "2026-11-23T10:00:00.000Z"}}

    ld = client.get("/ngsi-ld/v1/entities/urn:ngsi-ld:ROBOT:robot1", headers={"Accept": "application/ld+json"})
    assert ld.headers["Content-Type"] == "application/ld+json"
    assert "Link" not in ld.headers
    assert ld.json["@context"] == CORE

    kv = client.get("/ngsi-ld/v1/entities/urn:ngsi-ld:ROBOT:robot1?options=keyValues&attrs=move.goal")
    assert kv.json == {"id": "urn:ngsi-ld:ROBOT:robot1", "type": "ROBOT", "move.goal": {"x": 1, "text": "a<b>'c'"}}


def test_duplicate_create_is_409_already_exists(client):
    create(client, robot())
    assert_problem(client.post("/ngsi-ld/v1/entities", robot()), 409, "AlreadyExists")


@pytest.mark.parametrize("body, title", [
    ({"id": "robot1", "type": "ROBOT"}, "Invalid Entity ID"),
    ({"id": "urn:ngsi-ld:ROBOT:with space", "type": "ROBOT"}, "Invalid Entity ID"),
    ({"type": "ROBOT"}, "Entity id is missing"),
    ({"id": "urn:ngsi-ld:ROBOT:r"}, "Entity type missing"),
    (robot(speed=5), "Invalid attribute"),
    (robot(speed={"value": 5}), "Attribute type missing"),
    (robot(speed={"type": "Number", "value": 5}), "Invalid type for attribute"),
    (robot(speed={"type": "Property"}), "Attribute value missing"),
    (robot(speed={"type": "Property", "value": None}), "Attribute value missing"),
    (robot(owner={"type": "Relationship", "object": "not a uri"}), "Invalid Relationship object"),
    (robot(speed=prop(5, observedAt="yesterday")), "Invalid DateTime"),
    (robot(speed=prop(5, accuracy={"type": "Property"})), "Attribute value missing"),
    (robot(**{"bad name": prop(1)}), "Invalid attribute name"),
    (robot(**{"a=b": prop(1)}), "Invalid attribute name"),
    (robot(where={"type": "GeoProperty", "value": [1, 2]}), "Invalid GeoJSON"),
    ([robot()], "Invalid payload"),
])
def test_bad_entities_are_refused_with_problem_details_and_nothing_is_stored(client, body, title):
    assert_problem(client.post("/ngsi-ld/v1/entities", body), 400, "BadRequestData", title)
    assert client.get("/ngsi-ld/v1/entities?type=ROBOT").json == []


def test_content_types_and_context_placement(client):
    entity = robot(speed=prop(1))
    reply = client.post("/ngsi-ld/v1/entities", raw=json.dumps(entity).encode(), content_type="text/plain")
    assert_problem(reply, 415, "BadRequestData")
    reply = client.post("/ngsi-ld/v1/entities", raw=json.dumps(entity).encode(), content_type=None)
    assert reply.status == 415, reply
    # application/ld+json: the @context must be in the payload, and no Link header beside it
    assert_problem(client.post("/ngsi-ld/v1/entities", entity, content_type="application/ld+json"), 400,
                   "BadRequestData", "@context missing in JSON payload")
    with_context = dict(entity, **{"@context": CORE})
    assert_problem(client.post("/ngsi-ld/v1/entities", with_context, content_type="application/ld+json",
                               headers={"Link": f'<{CORE}>; {LINK_REL}'}), 400, "BadRequestData")
    # application/json: no @context in the payload
    assert_problem(client.post("/ngsi-ld/v1/entities", with_context), 400, "BadRequestData")
    assert client.get("/ngsi-ld/v1/entities?type=ROBOT").json == []
    create(client, with_context, content_type="application/ld+json")
    assert client.get("/ngsi-ld/v1/entities?type=ROBOT").json[0]["speed"] == prop(1)


def test_a_link_header_with_the_wrong_rel_is_refused(client):
    reply = client.post("/ngsi-ld/v1/entities", robot(), headers={"Link": f'<{CORE}>; rel="stylesheet"'})
    assert_problem(reply, 400, "BadRequestData", "Invalid Link HTTP header")


def test_an_inline_context_expands_names_and_readers_see_them_with_their_own_context(client):
    ctx = {"speed": "http://example.org/robots#speed", "ROBOT": "http://example.org/robots#Robot"}
    create(client, dict(robot(speed=prop(3), other=prop(4)), **{"@context": [ctx, CORE]}),
           content_type="application/ld+json")
    # without that context the expanded names show as full IRIs; default-vocabulary names stay short
    plain = client.get("/ngsi-ld/v1/entities/urn:ngsi-ld:ROBOT:robot1").json
    assert plain["type"] == "http://example.org/robots#Robot"
    assert plain["http://example.org/robots#speed"] == prop(3)
    assert plain["other"] == prop(4)
    assert client.get("/ngsi-ld/v1/entities?type=ROBOT").json == []
    assert len(client.get("/ngsi-ld/v1/entities?type=http://example.org/robots%23Robot").json) == 1


def test_query_by_type_id_pattern_and_attrs_with_pagination_and_count(client):
    for name in ("a1", "a2", "b1"):
        create(client, robot(name, speed=prop(1)) if name != "b1" else robot(name))
    create(client, {"id": "urn:ngsi-ld:Other:x", "type": "Other", "speed": prop(2)})

    def ids(query, **kwargs):
        reply = client.get("/ngsi-ld/v1/entities?" + query, **kwargs)
        assert reply.status == 200, reply
        return [e["id"].rsplit(":", 1)[1] for e in reply.json]

    assert ids("type=ROBOT") == ["a1", "a2", "b1"]
    assert ids("id=urn:ngsi-ld:ROBOT:a2,urn:ngsi-ld:Other:x") == ["a2", "x"]
    assert ids("type=ROBOT&idPattern=:a") == ["a1", "a2"]
    assert ids("attrs=speed") == ["a1", "a2", "x"]
    assert ids("type=ROBOT&limit=1&offset=1") == ["a2"]
    counted = client.get("/ngsi-ld/v1/entities?type=ROBOT&count=true&limit=1")
    assert counted.headers["NGSILD-Results-Count"] == "3"
    assert_problem(client.get("/ngsi-ld/v1/entities"), 400, "BadRequestData", "Too broad query")
    assert_problem(client.get("/ngsi-ld/v1/entities?id=notauri"), 400, "BadRequestData", "Invalid Entity ID")
    assert_problem(client.get("/ngsi-ld/v1/entities?type=ROBOT&limit=0"), 400, "BadRequestData")
    assert_problem(client.get("/ngsi-ld/v1/entities?type=ROBOT&q=speed==1"), 400, "BadRequestData")


def test_get_and_delete_unknown_or_bad_ids(client):
    assert_problem(client.get("/ngsi-ld/v1/entities/urn:ngsi-ld:ROBOT:none"), 404, "ResourceNotFound")
    assert_problem(client.get("/ngsi-ld/v1/entities/robot1"), 400, "BadRequestData", "Invalid Entity ID")
    assert_problem(client.delete("/ngsi-ld/v1/entities/urn:ngsi-ld:ROBOT:none"), 404, "ResourceNotFound")
    create(client, robot())
    assert client.delete("/ngsi-ld/v1/entities/urn:ngsi-ld:ROBOT:robot1").status == 204
    assert_problem(client.get("/ngsi-ld/v1/entities/urn:ngsi-ld:ROBOT:robot1"), 404, "ResourceNotFound")


def test_update_append_patch_and_delete_attributes(client):
    create(client, robot(speed=prop(1), mode=prop("auto")))
    base = "/ngsi-ld/v1/entities/urn:ngsi-ld:ROBOT:robot1"
    assert client.patch(base + "/attrs", {"speed": prop(2)}).status == 204
    partial = client.patch(base + "/attrs", {"speed": prop(3), "nothere": prop(0)})
    assert partial.status == 207, partial
    assert partial.json["updated"] == ["speed"]
    assert partial.json["notUpdated"][0]["attributeName"] == "nothere"
    assert client.post(base + "/attrs", {"battery": prop(90)}).status == 204
    kept = client.post(base + "/attrs?options=noOverwrite", {"battery": prop(10), "arm": prop("up")})
    assert kept.status == 207 and kept.json["notUpdated"][0]["attributeName"] == "battery", kept
    assert client.patch(base + "/attrs/mode", {"value": "manual"}).status == 204
    assert_problem(client.patch(base + "/attrs/mode", {"type": "Relationship", "object": "urn:x:y"}), 400,
                   "BadRequestData")
    assert_problem(client.patch(base + "/attrs/absent", {"value": 1}), 404, "ResourceNotFound")
    assert_problem(client.patch(base + "/attrs", {"speed": 7}), 400, "BadRequestData")
    assert client.delete(base + "/attrs/arm").status == 204
    assert_problem(client.delete(base + "/attrs/arm"), 404, "ResourceNotFound")
    assert client.get(base + "?options=keyValues").json == {
        "id": "urn:ngsi-ld:ROBOT:robot1", "type": "ROBOT", "speed": 3, "mode": "manual", "battery": 90}


def test_sys_attrs_show_creation_and_modification_times(client):
    create(client, robot(speed=prop(1)))
    got = client.get("/ngsi-ld/v1/entities/urn:ngsi-ld:ROBOT:robot1?options=sysAttrs").json
    assert got["createdAt"].endswith("Z") and got["speed"]["modifiedAt"].endswith("Z")


# --- batch upsert ---------------------------------------------------------------------------------------------

def test_upsert_creates_then_replaces_or_updates(client):
    path = "/ngsi-ld/v1/entityOperations/upsert"
    reply = client.post(path, [robot("r1", a=prop(1), b=prop(2)), robot("r2", a=prop(1))])
    assert reply.status == 201 and reply.json == ["urn:ngsi-ld:ROBOT:r1", "urn:ngsi-ld:ROBOT:r2"], reply
    assert client.post(path + "?options=update", [robot("r1", a=prop(5))]).status == 204
    assert client.get("/ngsi-ld/v1/entities/urn:ngsi-ld:ROBOT:r1?options=keyValues").json == {
        "id": "urn:ngsi-ld:ROBOT:r1", "type": "ROBOT", "a": 5, "b": 2}
    assert client.post(path, [robot("r1", c=prop(9))]).status == 204  # default: replace
    assert client.get("/ngsi-ld/v1/entities/urn:ngsi-ld:ROBOT:r1?options=keyValues").json == {
        "id": "urn:ngsi-ld:ROBOT:r1", "type": "ROBOT", "c": 9}


def test_upsert_with_bad_entities_answers_207_and_applies_the_good_ones(client):
    reply = client.post("/ngsi-ld/v1/entityOperations/upsert",
                        [robot("ok", a=prop(1)), {"id": "nouri", "type": "ROBOT"}, robot("bad", a=3)])
    assert reply.status == 207, reply
    assert reply.json["success"] == ["urn:ngsi-ld:ROBOT:ok"]
    assert [e["entityId"] for e in reply.json["errors"]] == ["nouri", "urn:ngsi-ld:ROBOT:bad"]
    assert reply.json["errors"][0]["error"]["type"] == ERR + "BadRequestData"
    assert [e["id"] for e in client.get("/ngsi-ld/v1/entities?type=ROBOT").json] == ["urn:ngsi-ld:ROBOT:ok"]
    assert_problem(client.post("/ngsi-ld/v1/entityOperations/upsert", []), 400, "BadRequestData")
    assert_problem(client.post("/ngsi-ld/v1/entityOperations/upsert", robot()), 400, "BadRequestData")


# --- subscriptions and notifications ------------------------------------------------------------------------

def test_subscription_notifies_every_update_in_ngsi_ld_format_with_a_link_header(client, receiver):
    create(client, robot(COMMAND=prop([]), speed=prop(1)))
    sub_id = subscribe(client, receiver.url, watchedAttributes=["COMMAND"],
                       notification={"endpoint": {"uri": receiver.url}, "attributes": ["COMMAND", "speed"]})
    assert sub_id.startswith("urn:ngsi-ld:Subscription:")
    base = "/ngsi-ld/v1/entities/urn:ngsi-ld:ROBOT:robot1/attrs"
    client.patch(base, {"speed": prop(2)})              # not watched: no notification
    client.patch(base, {"COMMAND": prop(["speed"])})
    client.patch(base, {"COMMAND": prop(["speed"])})   # the same value again: notified again
    notes = receiver.wait_for(2)
    note = notes[0]
    assert note.headers["Content-Type"] == "application/json"
    assert note.headers["Link"] == f'<{CORE}>; {LINK_REL}; type="application/ld+json"'
    assert note.headers["NGSILD-Tenant"] == client.tenant
    assert note.json["type"] == "Notification" and note.json["id"].startswith("urn:ngsi-ld:Notification:")
    assert note.json["subscriptionId"] == sub_id and note.json["notifiedAt"].endswith("Z")
    assert note.json["data"] == [{"id": "urn:ngsi-ld:ROBOT:robot1", "type": "ROBOT",
                                  "COMMAND": prop(["speed"]), "speed": prop(2)}]
    assert "@context" not in note.json
    shown = wait_until(lambda: (lambda s: s if s["notification"].get("timesSent") == 2
                                and "lastSuccess" in s["notification"] else None)(
        client.get(f"/ngsi-ld/v1/subscriptions/{sub_id}").json), timeout=10, message="subscription statistics")
    assert shown["watchedAttributes"] == ["COMMAND"] and shown["status"] == "active"
    assert shown["notification"]["endpoint"] == {"uri": receiver.url, "accept": "application/json"}
    assert len(receiver.notifications()) == 2


def test_ld_json_notification_carries_the_subscription_context_in_the_body(client, receiver):
    ctx = {"speed": "http://example.org/robots#speed"}
    body = {"type": "Subscription", "entities": [{"type": "ROBOT"}], "@context": [ctx, CORE],
            "notification": {"format": "keyValues",
                             "endpoint": {"uri": receiver.url, "accept": "application/ld+json"}}}
    assert client.post("/ngsi-ld/v1/subscriptions", body, content_type="application/ld+json").status == 201
    create(client, dict(robot(speed=prop(7)), **{"@context": [ctx, CORE]}), content_type="application/ld+json")
    note = receiver.wait_for(1)[0]
    assert note.headers["Content-Type"] == "application/ld+json"
    assert note.json["@context"] == [ctx, CORE]
    assert note.json["data"] == [{"id": "urn:ngsi-ld:ROBOT:robot1", "type": "ROBOT", "speed": 7}]


def test_subscription_matches_by_id_and_id_pattern_only(client, receiver):
    subscribe(client, receiver.url, entities=[{"type": "ROBOT", "id": "urn:ngsi-ld:ROBOT:a"},
                                              {"type": "ROBOT", "idPattern": "^urn:ngsi-ld:ROBOT:p"}])
    for name in ("b", "a", "p1"):
        create(client, robot(name))
    create(client, {"id": "urn:ngsi-ld:Other:a", "type": "Other"})
    notes = receiver.wait_for(2)
    assert sorted(n.json["data"][0]["id"] for n in notes) == ["urn:ngsi-ld:ROBOT:a", "urn:ngsi-ld:ROBOT:p1"]
    assert len(receiver.notifications()) == 2


def test_throttling_drops_notifications_inside_the_window(client, receiver):
    create(client, robot(speed=prop(0)))
    subscribe(client, receiver.url, throttling=60)
    for value in (1, 2, 3):
        assert client.patch("/ngsi-ld/v1/entities/urn:ngsi-ld:ROBOT:robot1/attrs", {"speed": prop(value)}).status \
            == 204
    note = receiver.wait_for(1)[0]
    assert note.json["data"][0]["speed"]["value"] == 1
    # the later two were dropped, not delayed: another update in another entity still goes through untouched
    other = subscribe(client, receiver.url, entities=[{"type": "Marker"}])
    create(client, {"id": "urn:x:m", "type": "Marker"})
    notes = receiver.wait_for(2)
    assert [n.json["subscriptionId"] for n in notes][-1] == other
    assert len(notes) == 2


def test_expired_and_paused_subscriptions_notify_no_one(client, receiver):
    create(client, robot(speed=prop(0)))
    expiring = subscribe(client, receiver.url, expiresAt=_iso(time.time() + 1.0))
    paused = subscribe(client, receiver.url)
    assert client.patch(f"/ngsi-ld/v1/subscriptions/{paused}", {"isActive": False}).status == 204
    wait_until(lambda: client.get(f"/ngsi-ld/v1/subscriptions/{expiring}").json["status"] == "expired",
               timeout=10, message="the subscription to expire")
    assert client.get(f"/ngsi-ld/v1/subscriptions/{paused}").json["status"] == "paused"
    client.patch("/ngsi-ld/v1/entities/urn:ngsi-ld:ROBOT:robot1/attrs", {"speed": prop(1)})
    witness = subscribe(client, receiver.url, entities=[{"type": "Marker"}])
    create(client, {"id": "urn:x:m", "type": "Marker"})
    notes = receiver.wait_for(1)
    assert [n.json["subscriptionId"] for n in notes] == [witness]
    # renewing (PATCH expiresAt) brings it back
    assert client.patch(f"/ngsi-ld/v1/subscriptions/{expiring}", {"expiresAt": _iso(time.time() + 600)}).status \
        == 204
    client.patch("/ngsi-ld/v1/entities/urn:ngsi-ld:ROBOT:robot1/attrs", {"speed": prop(2)})
    assert receiver.wait_for(2)[-1].json["subscriptionId"] == expiring


def _iso(epoch):
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(epoch)) + f".{int(epoch % 1 * 1000):03d}Z"


@pytest.mark.parametrize("change, title", [
    ({"type": "Sub"}, "Invalid Subscription"),
    ({"entities": []}, "Invalid Subscription"),
    ({"entities": [{"id": "urn:x:y"}]}, "Invalid Subscription"),
    ({"entities": [{"type": "ROBOT", "id": "nouri"}]}, "Invalid Entity ID"),
    ({"notification": {"endpoint": {"uri": "ftp://x/"}}}, "Invalid Subscription"),
    ({"notification": {"endpoint": {"uri": "http://127.0.0.1:9/", "accept": "text/plain"}}},
     "Invalid Subscription"),
    ({"notification": {}}, "Invalid Subscription"),
    ({"expiresAt": "2000-01-01T00:00:00Z"}, "Invalid Subscription"),
    ({"expiresAt": "soon"}, "Invalid DateTime"),
    ({"throttling": -1}, "Invalid Subscription"),
    ({"id": "not a uri"}, "Invalid Subscription id"),
    ({"q": "speed>1"}, "Not supported"),
])
def test_bad_subscriptions_are_refused(client, change, title):
    body = {"type": "Subscription", "entities": [{"type": "ROBOT"}],
            "notification": {"endpoint": {"uri": "http://127.0.0.1:9/notify"}}}
    body.update(change)
    assert_problem(client.post("/ngsi-ld/v1/subscriptions", body), 400, "BadRequestData", title)
    assert client.get("/ngsi-ld/v1/subscriptions").json == []


def test_subscription_get_list_patch_delete(client):
    sub_id = subscribe(client, "http://127.0.0.1:9/notify", id="urn:ngsi-ld:Subscription:mine")
    assert sub_id == "urn:ngsi-ld:Subscription:mine"
    assert_problem(client.post("/ngsi-ld/v1/subscriptions", {
        "id": sub_id, "type": "Subscription", "entities": [{"type": "ROBOT"}],
        "notification": {"endpoint": {"uri": "http://127.0.0.1:9/"}}}), 409, "AlreadyExists")
    assert [s["id"] for s in client.get("/ngsi-ld/v1/subscriptions").json] == [sub_id]
    # a refused PATCH changes nothing
    assert_problem(client.patch(f"/ngsi-ld/v1/subscriptions/{sub_id}", {"throttling": 5, "isActive": "no"}),
                   400, "BadRequestData")
    assert "throttling" not in client.get(f"/ngsi-ld/v1/subscriptions/{sub_id}").json
    assert client.delete(f"/ngsi-ld/v1/subscriptions/{sub_id}").status == 204
    assert_problem(client.get(f"/ngsi-ld/v1/subscriptions/{sub_id}"), 404, "ResourceNotFound")
    assert_problem(client.delete(f"/ngsi-ld/v1/subscriptions/{sub_id}"), 404, "ResourceNotFound")


# --- protocol ------------------------------------------------------------------------------------------------

def test_protocol_errors_are_problem_details(client, broker):
    assert_problem(client.get("/ngsi-ld/v1/nothing"), 404, "ResourceNotFound", "Service Not Found")
    wrong = client.request("PUT", "/ngsi-ld/v1/entities/urn:x:y", {"a": 1})
    assert wrong.status == 405 and "GET" in wrong.headers["Allow"], wrong
    assert_problem(client.get("/ngsi-ld/v1/entities?type=ROBOT", headers={"Accept": "text/html"}), 406,
                   "BadRequestData")
    assert_problem(client.post("/ngsi-ld/v1/entities", raw=b"{not json"), 400, "InvalidRequest")
    assert_problem(client.post("/ngsi-ld/v1/entities", raw=b"[" * 100000 + b"]" * 100000), 400, "InvalidRequest")
    assert_problem(client.post("/ngsi-ld/v1/entities", raw=b" " * (1024 * 1024 + 1)), 413,
                   "RequestEntityTooLarge")
    # still serving
    create(client, robot())


def test_tenants_are_apart_and_v2_is_untouched(client, broker):
    create(client, robot(speed=prop(1)))
    other = LdClient(broker.url, "ld_" + uuid.uuid4().hex[:12])
    assert other.get("/ngsi-ld/v1/entities?type=ROBOT").json == []
    assert client.get("/ngsi-ld/v1/entities?type=ROBOT", headers={"NGSILD-Tenant": client.tenant}).status == 200
    v2 = BrokerClient(broker.url, service=client.tenant)
    assert v2.get("/v2/entities").json == []
    assert v2.post("/v2/entities", {"id": "robot1", "type": "ROBOT"}).status == 201
    assert len(client.get("/ngsi-ld/v1/entities?type=ROBOT").json) == 1
    fiware_service = BrokerClient(broker.url, service=client.tenant)   # Orion-LD also takes Fiware-Service
    assert len(fiware_service.get("/ngsi-ld/v1/entities?type=ROBOT").json) == 1
