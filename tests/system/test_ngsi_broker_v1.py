"""The stand-in broker's NGSI v1 side (Orion before 3.10), including the seed guide's two curl commands verbatim.

One broker child serves the module; each test has its own tenant. The seed's commands run as real ``curl``
processes (argv lists, the heredoc fed on stdin) whose answer goes through a real ``python3 -mjson.tool``, as
in the seed, and is then parsed. Notifications go to real HTTP servers on loopback.
"""

import json
import random
import re
import subprocess
import uuid

import pytest

from tests.ngsi_broker.testing import BrokerClient, NotificationReceiver, start_broker
from tests.support.polling import wait_until
from tests.support.processes import ProcessGroup

# The seed guide's "End to End testing" commands, exactly as written (heredoc bodies included).
SEED_QUERY_BODY = """{
        "entities": [
                {
                        "type": "ROBOT",
                        "isPattern": "true",
                        "id": "end_end_test"
                }
        ],
        "attributes": [
                "s1"
        ]
}
"""
SEED_QUERY_ANSWER = {
    "contextResponses": [
        {
            "contextElement": {
                "attributes": [
                    {
                        "name": "s1",
                        "type": "std_msgs.msg.String",
                        "value": "{%27firosstamp%27: 1443020619.58971, %27data%27: %27test%27}"
                    }
                ],
                "id": "end_end_test",
                "isPattern": "false",
                "type": "ROBOT"
            },
            "statusCode": {
                "code": "200",
                "reasonPhrase": "OK"
            }
        }
    ]
}
SEED_UPDATE_BODY = """{
          "contextElements": [
                  {
                          "type": "ROBOT",
                          "isPattern": "false",
                          "id": "end_end_test",
                          "attributes": [
                          {
                                  "name": "p1",
                                  "type": "std_msgs.msg.String",
                                  "value": "{%27data%27: %27`echo $RANDOM`%27}"
                          },
                          {
                                  "name": "COMMAND",
                                  "type": "COMMAND",
                                  "value": ["p1"]
                          }
                          ]
                  }
          ],
          "updateAction": "APPEND"
}
"""


def seed_curl(broker, operation, heredoc, service=None):
    """``(curl contextbroker_ip:1026/v1/<op> -s -S --header ... -d @- | python -mjson.tool) <<EOF`` as argv."""
    argv = ["curl", f"{broker.host}:{broker.port}/v1/{operation}", "-s", "-S",
            "--header", "Content-Type: application/json", "--header", "Accept: application/json", "-d", "@-"]
    if service:
        argv[4:4] = ["--header", f"Fiware-Service: {service}"]
    done = subprocess.run(argv, input=heredoc.encode(), capture_output=True, timeout=10, check=False)
    assert done.returncode == 0, done.stderr
    # "| python -mjson.tool": the answer must be something json.tool accepts (a second process, no shell)
    pretty = subprocess.run(["/usr/bin/python3", "-mjson.tool"], input=done.stdout, capture_output=True,
                            timeout=10, check=False)
    assert pretty.returncode == 0, pretty.stderr
    return json.loads(pretty.stdout)


def shell_heredoc(text):
    """What the shell makes of the seed's unquoted heredoc: `echo $RANDOM` becomes a number 0..32767."""
    number = str(random.randint(0, 32767))
    return text.replace("`echo $RANDOM`", number), number


@pytest.fixture(scope="module")
def broker(tmp_path_factory):
    group = ProcessGroup(log_dir=str(tmp_path_factory.mktemp("ngsi-broker-v1")))
    try:
        yield start_broker(group)
    finally:
        group.stop_all()


@pytest.fixture
def client(broker):
    return BrokerClient(broker.url, service="t_" + uuid.uuid4().hex[:12])


@pytest.fixture
def receiver():
    with NotificationReceiver() as server:
        yield server


def element(entity_id, attributes, entity_type="ROBOT"):
    return {"type": entity_type, "isPattern": "false", "id": entity_id,
            "attributes": [{"name": n, "type": t, "value": v} for n, t, v in attributes]}


def update(client, action, *elements, prefix="/v1"):
    reply = client.post(f"{prefix}/updateContext", {"contextElements": list(elements), "updateAction": action})
    assert reply.status == 200, reply
    return reply.json


def query(client, entities, attributes=None, prefix="/v1"):
    body = {"entities": entities}
    if attributes is not None:
        body["attributes"] = attributes
    reply = client.post(f"{prefix}/queryContext", body)
    assert reply.status == 200, reply
    return reply.json


def status_codes(answer):
    return [r["statusCode"]["code"] for r in answer["contextResponses"]]


# --- the seed's end-to-end calls --------------------------------------------------------------------------

def test_seed_query_context_curl_returns_the_seeds_shape(broker):
    # what FIROS (v1) writes when /end_end_test/s1 publishes "test"
    writer = BrokerClient(broker.url)
    answer = update(writer, "APPEND", element("end_end_test", [
        ("s1", "std_msgs.msg.String", "{%27firosstamp%27: 1443020619.58971, %27data%27: %27test%27}"),
        ("COMMAND", "COMMAND", ["s1"])]))
    assert status_codes(answer) == ["200"]
    assert seed_curl(broker, "queryContext", SEED_QUERY_BODY) == SEED_QUERY_ANSWER


def test_seed_update_context_curl_notifies_the_subscriber(broker, receiver):
    service = "t_" + uuid.uuid4().hex[:12]
    client = BrokerClient(broker.url, service=service)
    update(client, "APPEND", element("end_end_test", [("s1", "std_msgs.msg.String", "{%27data%27: %27x%27}")]))
    # what FIROS (v1) subscribes for the robot's publisher topics
    reply = client.post("/v1/subscribeContext", {
        "entities": [{"type": "ROBOT", "isPattern": "false", "id": "end_end_test"}],
        "attributes": [], "reference": receiver.url, "duration": "PT1H",
        "notifyConditions": [{"type": "ONCHANGE", "condValues": ["COMMAND"]}], "throttling": "PT0S"})
    sub_id = reply.json["subscribeResponse"]["subscriptionId"]
    initial = receiver.wait_for(1)[0]   # Orion before 3.1 sent the current values at once
    assert initial.json["subscriptionId"] == sub_id

    body, number = shell_heredoc(SEED_UPDATE_BODY)
    answer = seed_curl(broker, "updateContext", body, service=service)
    assert answer == {"contextResponses": [{
        "contextElement": {"attributes": [{"name": "p1", "type": "std_msgs.msg.String", "value": ""},
                                          {"name": "COMMAND", "type": "COMMAND", "value": ""}],
                           "id": "end_end_test", "isPattern": "false", "type": "ROBOT"},
        "statusCode": {"code": "200", "reasonPhrase": "OK"}}]}
    note = receiver.wait_for(2)[1]
    assert note.json["subscriptionId"] == sub_id
    assert note.json["originator"] == "localhost"
    [response] = note.json["contextResponses"]
    assert response["statusCode"] == {"code": "200", "reasonPhrase": "OK"}
    attributes = {a["name"]: a for a in response["contextElement"]["attributes"]}
    assert attributes["p1"] == {"name": "p1", "type": "std_msgs.msg.String",
                                "value": "{%27data%27: %27" + number + "%27}"}
    assert attributes["COMMAND"]["value"] == ["p1"]
    assert set(attributes) == {"s1", "p1", "COMMAND"}
    assert (response["contextElement"]["id"], response["contextElement"]["type"]) == ("end_end_test", "ROBOT")
    assert note.headers["Fiware-Service"] == service
    assert note.headers["Content-Type"].startswith("application/json")


# --- updateContext ----------------------------------------------------------------------------------------

def test_update_context_actions(client):
    assert status_codes(update(client, "APPEND", element("r1", [("a", "T", "1"), ("b", "T", "2")]))) == ["200"]
    assert status_codes(update(client, "append", element("r1", [("c", "T", "3")]))) == ["200"]  # any case
    assert status_codes(update(client, "UPDATE", element("r1", [("a", "T", "10")]))) == ["200"]
    reply = client.get("/v2/entities/r1?options=keyValues")
    assert reply.json == {"id": "r1", "type": "ROBOT", "a": "10", "b": "2", "c": "3"}
    assert status_codes(update(client, "DELETE", element("r1", [("b", "", "")]))) == ["200"]
    assert status_codes(update(client, "REPLACE", element("r1", [("z", "T", "26")]))) == ["200"]
    assert client.get("/v2/entities/r1?options=keyValues").json == {"id": "r1", "type": "ROBOT", "z": "26"}
    answer = update(client, "APPEND_STRICT", element("r1", [("z", "T", "0")]))
    assert status_codes(answer) == ["400"]
    assert status_codes(update(client, "DELETE", element("r1", []))) == ["200"]
    assert client.get("/v2/entities/r1").status == 404


def test_update_context_on_missing_entity_and_attribute(client):
    answer = update(client, "UPDATE", element("ghost", [("a", "T", "1")]))
    assert answer == {"contextResponses": [{
        "contextElement": {"attributes": [{"name": "a", "type": "T", "value": ""}], "id": "ghost",
                           "isPattern": "false", "type": "ROBOT"},
        "statusCode": {"code": "404", "reasonPhrase": "No context element found", "details": "ghost"}}]}
    update(client, "APPEND", element("r1", [("a", "T", "1")]))
    answer = update(client, "UPDATE", element("r1", [("nope", "T", "1")]))
    assert answer["contextResponses"][0]["statusCode"] == {
        "code": "472", "reasonPhrase": "request parameter is invalid/not allowed",
        "details": "action: UPDATE - entity: [r1, ROBOT] - offending attribute: nope"}
    # one element failing does not stop the others
    answer = update(client, "UPDATE", element("ghost", [("a", "T", "1")]), element("r1", [("a", "T", "2")]))
    assert status_codes(answer) == ["404", "200"]
    assert client.get("/v2/entities/r1/attrs/a").json["value"] == "2"


def test_update_context_without_type_matches_any_type(client):
    update(client, "APPEND", element("r1", [("a", "T", "1")]))
    answer = update(client, "UPDATE", {"id": "r1", "isPattern": "false",
                                       "attributes": [{"name": "a", "type": "T", "value": "5"}]})
    assert status_codes(answer) == ["200"]
    assert client.get("/v2/entities/r1?options=keyValues").json["a"] == "5"


def test_v1_error_answers(client):
    reply = client.post("/v1/updateContext", raw=b'{"contextElements": [')
    assert (reply.status, reply.json) == (400, {"orionError": {"code": "400", "reasonPhrase": "Bad Request",
                                                               "details": "JSON Parse Error"}})
    reply = client.post("/v1/queryContext", raw=b"not json")
    assert (reply.status, reply.json["orionError"]["details"]) == (400, "JSON Parse Error")
    reply = client.post("/v1/updateContext", {"contextElements": [element("r1", [("a", "T", "x(y)")])],
                                              "updateAction": "APPEND"})
    assert (reply.status, reply.json) == (400, {"orionError": {
        "code": "400", "reasonPhrase": "Bad Request", "details": "Illegal value for JSON field"}})
    reply = client.post("/v1/updateContext", {"contextElements": [element("r1", [("a", "T", "1")])],
                                              "updateAction": "UPSERT"})
    assert (reply.status, reply.json["orionError"]["code"]) == (400, "400")
    reply = client.post("/v1/updateContext", {"updateAction": "APPEND"})
    assert reply.status == 400
    reply = client.post("/v1/queryContext", {"entities": [{"id": "(", "isPattern": "true"}]})
    assert (reply.status, reply.json["orionError"]["code"]) == (400, "400")
    reply = client.post("/v1/subscribeContext", {"entities": [{"id": "r1"}]})
    assert (reply.status, reply.json["subscribeError"]["errorCode"]["code"]) == (400, "400")
    reply = client.get("/v1/queryContext")
    assert (reply.status, reply.headers["Allow"]) == (405, "POST")
    reply = client.post("/v1/registry/registerContext", {})
    assert reply.status == 400 and "Service not found" in reply.json["orionError"]["details"]
    assert client.get("/v2/entities").json == []   # none of the refused writes changed anything


def test_body_size_limit_on_v1(client):
    big = json.dumps({"contextElements": [element("r1", [("a", "T", "x" * (1024 * 1024))])],
                      "updateAction": "APPEND"}).encode()
    reply = client.post("/v1/updateContext", raw=big)
    assert (reply.status, reply.json) == (413, {"errorCode": {
        "code": "413", "reasonPhrase": "Request Entity Too Large",
        "details": f"payload size: {len(big)}, max size supported: 1048576"}})


# --- queryContext -----------------------------------------------------------------------------------------

def test_query_context_patterns_and_attribute_filter(client):
    update(client, "APPEND", element("robot1", [("a", "T", "1"), ("b", "T", "2")]),
           element("robot2", [("a", "T", "3")]), element("cam1", [("a", "T", "4")], entity_type="CAMERA"))

    def ids(entities, attributes=None):
        answer = query(client, entities, attributes)
        return [r["contextElement"]["id"] for r in answer.get("contextResponses", [])]

    assert ids([{"type": "ROBOT", "isPattern": "false", "id": "robot1"}]) == ["robot1"]
    assert ids([{"type": "ROBOT", "isPattern": "true", "id": "robot.*"}]) == ["robot1", "robot2"]
    assert ids([{"type": "", "isPattern": "true", "id": ".*"}]) == ["robot1", "robot2", "cam1"]
    assert ids([{"isPattern": "true", "id": "1$"}]) == ["robot1", "cam1"]
    assert ids([{"type": "ROBOT", "isPattern": "true", "id": "robot"}], ["b"]) == ["robot1"]
    assert ids([{"type": "ROBOT", "isPattern": "false", "id": "robot1"},
                {"type": "CAMERA", "isPattern": "false", "id": "cam1"}]) == ["robot1", "cam1"]
    answer = query(client, [{"type": "ROBOT", "isPattern": "false", "id": "robot1"}], ["b"])
    assert answer["contextResponses"][0]["contextElement"]["attributes"] == [{"name": "b", "type": "T",
                                                                              "value": "2"}]


def test_query_context_nothing_found(client):
    not_found = {"errorCode": {"code": "404", "reasonPhrase": "No context element found"}}
    assert query(client, [{"type": "ROBOT", "isPattern": "false", "id": "ghost"}]) == not_found
    update(client, "APPEND", element("robot1", [("a", "T", "1")]))
    assert query(client, [{"type": "ROBOT", "isPattern": "false", "id": "robot1"}], ["humidity"]) == not_found
    assert query(client, [{"type": "CAMERA", "isPattern": "false", "id": "robot1"}]) == not_found
    assert query(client, [{"type": "ROBOT", "isPattern": "true", "id": "^x"}]) == not_found


def test_v1_and_v2_share_one_store(client):
    client.post("/v2/entities", {"id": "r1", "type": "ROBOT", "n": {"value": 5},
                                 "o": {"type": "geometry_msgs.msg.Point", "value": {"x": 1}}})
    answer = query(client, [{"type": "ROBOT", "isPattern": "false", "id": "r1"}])
    assert answer["contextResponses"][0]["contextElement"]["attributes"] == [
        {"name": "n", "type": "Number", "value": 5},
        {"name": "o", "type": "geometry_msgs.msg.Point", "value": {"x": 1}}]
    update(client, "UPDATE", element("r1", [("n", "Number", "6")]))
    assert client.get("/v2/entities/r1/attrs/n").json["value"] == "6"


def test_ngsi10_twins(client, receiver):
    assert status_codes(update(client, "APPEND", element("r1", [("a", "T", "1")]), prefix="/NGSI10")) == ["200"]
    assert query(client, [{"type": "ROBOT", "isPattern": "false", "id": "r1"}],
                 prefix="/NGSI10")["contextResponses"][0]["contextElement"]["id"] == "r1"
    assert query(client, [{"type": "ROBOT", "isPattern": "false", "id": "r1"}],
                 prefix="/ngsi10")["contextResponses"][0]["contextElement"]["id"] == "r1"
    reply = client.post("/NGSI10/subscribeContext", {
        "entities": [{"type": "ROBOT", "isPattern": "false", "id": "r1"}], "reference": receiver.url,
        "duration": "P1D", "notifyConditions": [{"type": "ONCHANGE", "condValues": ["a"]}]})
    sub_id = reply.json["subscribeResponse"]["subscriptionId"]
    reply = client.post("/NGSI10/updateContextSubscription", {"subscriptionId": sub_id, "duration": "P2D"})
    assert reply.json == {"subscribeResponse": {"subscriptionId": sub_id, "duration": "P2D"}}
    reply = client.post("/NGSI10/unsubscribeContext", {"subscriptionId": sub_id})
    assert reply.json == {"statusCode": {"code": "200", "reasonPhrase": "OK"}, "subscriptionId": sub_id}


# --- subscriptions ----------------------------------------------------------------------------------------

def subscribe(client, url, entity_id="r1", cond=None, attributes=None, duration="PT1H", throttling=None,
              pattern=False):
    body = {"entities": [{"type": "ROBOT", "isPattern": "true" if pattern else "false", "id": entity_id}],
            "reference": url, "duration": duration,
            "notifyConditions": [{"type": "ONCHANGE", "condValues": cond or []}]}
    if attributes is not None:
        body["attributes"] = attributes
    if throttling:
        body["throttling"] = throttling
    reply = client.post("/v1/subscribeContext", body)
    assert reply.status == 200, reply
    return reply.json["subscribeResponse"]


def test_subscribe_context_answer_and_notifications(client, receiver):
    answer = subscribe(client, receiver.url, cond=["cmd"], attributes=["cmd"], throttling="PT0S")
    assert re.fullmatch(r"[0-9a-f]{24}", answer["subscriptionId"])
    assert answer == {"subscriptionId": answer["subscriptionId"], "duration": "PT1H", "throttling": "PT0S"}
    update(client, "APPEND", element("r1", [("cmd", "T", "1"), ("pose", "T", "0")]))
    update(client, "UPDATE", element("r1", [("pose", "T", "5")]))   # not a condition value: no notification
    update(client, "UPDATE", element("r1", [("cmd", "T", "1")]))    # same value: no notification
    update(client, "UPDATE", element("r1", [("cmd", "T", "2")]))
    notes = receiver.wait_for(2)
    assert [n.json["contextResponses"][0]["contextElement"]["attributes"] for n in notes] == [
        [{"name": "cmd", "type": "T", "value": "1"}], [{"name": "cmd", "type": "T", "value": "2"}]]
    assert notes[0].json == {"subscriptionId": answer["subscriptionId"], "originator": "localhost",
                             "contextResponses": [{
                                 "contextElement": {"attributes": [{"name": "cmd", "type": "T", "value": "1"}],
                                                    "id": "r1", "isPattern": "false", "type": "ROBOT"},
                                 "statusCode": {"code": "200", "reasonPhrase": "OK"}}]}
    listed = client.get(f"/v2/subscriptions/{answer['subscriptionId']}").json
    assert listed["notification"]["attrsFormat"] == "legacy"
    assert listed["subject"]["condition"]["attrs"] == ["cmd"]


def test_initial_notification_with_pattern_subject(client, receiver):
    update(client, "APPEND", element("robot1", [("a", "T", "1")]), element("robot2", [("a", "T", "2")]),
           element("other", [("a", "T", "3")]))
    answer = subscribe(client, receiver.url, entity_id="^robot", pattern=True)
    [note] = receiver.wait_for(1)
    assert note.json["subscriptionId"] == answer["subscriptionId"]
    assert [r["contextElement"]["id"] for r in note.json["contextResponses"]] == ["robot1", "robot2"]


def test_no_initial_notification_when_switched_off(tmp_path, receiver):
    with ProcessGroup(log_dir=str(tmp_path)) as procs:
        quiet_broker = start_broker(procs, extra_args=["--no-v1-initial-notification", "--quiet"])
        client = BrokerClient(quiet_broker.url)
        update(client, "APPEND", element("r1", [("a", "T", "1")]))
        subscribe(client, receiver.url)
        update(client, "UPDATE", element("r1", [("a", "T", "2")]))
        notes = receiver.wait_for(1)
        assert [n.json["contextResponses"][0]["contextElement"]["attributes"][0]["value"] for n in notes] == ["2"]


def test_v1_subscription_throttling(client, receiver):
    subscribe(client, receiver.url, throttling="PT1S")
    update(client, "APPEND", element("r1", [("n", "T", "0")]))
    receiver.wait_for(1)
    update(client, "UPDATE", element("r1", [("n", "T", "1")]))   # inside the window: dropped
    counter = iter(range(2, 10000))

    def next_arrived():
        update(client, "UPDATE", element("r1", [("n", "T", str(next(counter)))]))
        return len(receiver.notifications()) >= 2

    wait_until(next_arrived, timeout=10, interval=0.05, message="a notification after the throttling window")
    first, second = receiver.notifications()[:2]
    assert second.received_at - first.received_at >= 0.75
    assert int(second.json["contextResponses"][0]["contextElement"]["attributes"][0]["value"]) >= 2


def test_v1_duration_expiry_and_update_context_subscription(client, receiver):
    answer = subscribe(client, receiver.url + "?which=short", duration="PT1S")
    sub_id = answer["subscriptionId"]
    fence = subscribe(client, receiver.url + "?which=fence")["subscriptionId"]
    wait_until(lambda: client.get(f"/v2/subscriptions/{sub_id}").json["status"] == "expired", timeout=5,
               message="the v1 subscription to expire")
    update(client, "APPEND", element("r1", [("n", "T", "0")]))
    notes = receiver.wait_for(1)
    assert [n.path for n in notes] == ["/notify?which=fence"]    # the expired one stays silent
    reply = client.post("/v1/updateContextSubscription", {"subscriptionId": sub_id, "duration": "PT1H"})
    assert reply.json == {"subscribeResponse": {"subscriptionId": sub_id, "duration": "PT1H"}}
    assert client.get(f"/v2/subscriptions/{sub_id}").json["status"] == "active"
    update(client, "UPDATE", element("r1", [("n", "T", "1")]))
    notes = receiver.wait_for(3)
    assert sorted(n.path for n in notes[1:]) == ["/notify?which=fence", "/notify?which=short"]
    assert client.post("/v1/unsubscribeContext", {"subscriptionId": fence}).json["statusCode"]["code"] == "200"


def test_unsubscribe_and_update_unknown_subscription(client):
    reply = client.post("/v1/unsubscribeContext", {"subscriptionId": "0123456789abcdef01234567"})
    assert reply.json == {"statusCode": {"code": "404", "reasonPhrase": "No context element found",
                                         "details": "subscriptionId: /0123456789abcdef01234567/"},
                          "subscriptionId": "0123456789abcdef01234567"}
    reply = client.post("/v1/updateContextSubscription", {"subscriptionId": "0123456789abcdef01234567",
                                                          "duration": "P1D"})
    assert reply.json == {"subscribeError": {"subscriptionId": "0123456789abcdef01234567",
                                             "errorCode": {"code": "404",
                                                           "reasonPhrase": "No context element found"}}}
    reply = client.post("/v1/subscribeContext", {"entities": [{"id": "r1", "isPattern": "false"}],
                                                 "reference": "http://127.0.0.1:9/x", "duration": "one day"})
    assert reply.status == 400 and "duration" in reply.json["subscribeError"]["errorCode"]["details"]


def test_v1_and_v2_subscriptions_see_each_others_updates(client, receiver):
    v1_sub = subscribe(client, receiver.url + "?api=v1")["subscriptionId"]
    reply = client.post("/v2/subscriptions", {"subject": {"entities": [{"id": "r1"}]},
                                              "notification": {"http": {"url": receiver.url + "?api=v2"}}})
    assert reply.status == 201
    client.post("/v2/entities", {"id": "r1", "type": "ROBOT", "a": {"value": 1}})          # v2 write
    update(client, "UPDATE", element("r1", [("a", "Number", 2)]))                       # v1 write
    notes = receiver.wait_for(4)
    v1_values = [n.json["contextResponses"][0]["contextElement"]["attributes"][0]["value"]
                 for n in notes if n.path.endswith("v1")]
    v2_values = [n.json["data"][0]["a"]["value"] for n in notes if n.path.endswith("v2")]
    assert (v1_values, v2_values) == ([1, 2], [1, 2])
    assert all(n.json["subscriptionId"] == v1_sub for n in notes if n.path.endswith("v1"))


def test_v1_tenants_are_kept_apart(broker):
    a = BrokerClient(broker.url, service="t_" + uuid.uuid4().hex[:12])
    b = BrokerClient(broker.url, service="t_" + uuid.uuid4().hex[:12])
    update(a, "APPEND", element("r1", [("a", "T", "1")]))
    assert query(b, [{"type": "ROBOT", "isPattern": "false", "id": "r1"}])["errorCode"]["code"] == "404"
    assert "contextResponses" in query(a, [{"type": "ROBOT", "isPattern": "false", "id": "r1"}])


def test_convenience_operations_kept_after_orion_3_10(client):
    update(client, "APPEND", element("r1", [("a", "T", "1"), ("b", "T", "2")]))
    reply = client.get("/v1/contextEntities/r1/attributes/a")
    assert reply.json == {"attributes": [{"name": "a", "type": "T", "value": "1"}],
                          "statusCode": {"code": "200", "reasonPhrase": "OK"}}
    reply = client.put("/v1/contextEntities/r1", {"attributes": [{"name": "a", "type": "T", "value": "5"}]})
    assert reply.json == {"contextResponses": [{"attributes": [{"name": "a", "type": "T", "value": ""}],
                                                "statusCode": {"code": "200", "reasonPhrase": "OK"}}]}
    assert client.get("/v2/entities/r1/attrs/a").json["value"] == "5"
    assert client.delete("/v1/contextEntities/r1").json == {"code": "200", "reasonPhrase": "OK"}
    assert client.get("/v1/contextEntities/r1/attributes/a").json == {"statusCode": {
        "code": "404", "reasonPhrase": "No context element found", "details": "Entity id: /r1/"}}
    assert client.delete("/v1/contextEntities/r1").json["code"] == "404"
