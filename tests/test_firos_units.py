"""FIROS's modules one by one, without a ROS master: configuration and its errors (also through the real
`core.py`), the whitelist (the seed's examples), robots from a graph snapshot and from rcm_driver's answer,
notification parsing, and the sender and subscriptions against the stand-in broker served in-process.
"""

import json
import os
import subprocess
import sys
import time

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "firos", "scripts"))

from include import config as cfg  # noqa: E402
from include.discovery import robot_from_rcm, robots_from_graph  # noqa: E402
from include.ngsi_client import NgsiClient, NotificationError, parse_notification  # noqa: E402
from include.sender import Sender  # noqa: E402
from include.subscriptions import Subscriptions  # noqa: E402
from include.whitelist import Whitelist, WhitelistError  # noqa: E402
from tests.ngsi_broker.server import BrokerServer  # noqa: E402
from tests.support.firos import SEED_WHITELIST, write_config  # noqa: E402
from tests.support.polling import wait_until  # noqa: E402
from tests.support.processes import ros_env  # noqa: E402


# --- configuration ----------------------------------------------------------------------------------------------

def test_package_config_is_valid_and_uses_the_contract_defaults():
    settings = cfg.load_settings(cfg.PACKAGE_CONFIG_DIR)
    assert settings.server_port == 10100 and settings.broker_port == 1026
    assert settings.ngsi_version == "v2" and settings.context_type == "ROBOT"
    assert settings.subscription_length == 300 and settings.subscription_refresh_delay == 240
    Whitelist.load(cfg.PACKAGE_CONFIG_DIR)
    assert "turtle1" in cfg.load_descriptions(cfg.PACKAGE_CONFIG_DIR)


@pytest.mark.parametrize("text,seconds", [("PT0S", 0), ("PT5M", 300), ("P1D", 86400), ("PT1H30M", 5400),
                                          (12, 12), (0.5, 0.5), ("P1M", 30 * 86400)])
def test_durations(text, seconds):
    assert cfg.parse_duration(text, "f", "k") == seconds


@pytest.mark.parametrize("bad", ["5 minutes", "P", "PT", -1, True, None, "P1X"])
def test_bad_durations(bad):
    with pytest.raises(cfg.ConfigError, match="k must (be|not be negative)"):
        cfg.parse_duration(bad, "f", "k")


def _config(tmp_path, block, env="test"):
    (tmp_path / "config.json").write_text(json.dumps({"environment": env, env: block}))
    return str(tmp_path)


@pytest.mark.parametrize("block,problem", [
    ({}, "contextbroker is missing"),
    ({"contextbroker": {"port": 1026}}, "contextbroker.address is missing"),
    ({"contextbroker": {"address": "x", "port": 70000}}, "contextbroker.port must be a TCP port"),
    ({"contextbroker": {"address": "x"}, "ngsi_version": "v3"}, "ngsi_version must be"),
    ({"contextbroker": {"address": "x"}, "log_level": "LOUD"}, "log_level must be"),
    ({"contextbroker": {"address": "x"}, "pub_frequency": -5}, "pub_frequency must be"),
    ({"contextbroker": {"address": "x", "subscription": {"subscription_length": 10,
                                                         "subscription_refresh_delay": 20}}},
     "refreshed before they expire"),
    ({"contextbroker": {"address": "x"}, "fiware_servicepath": "nope"}, "must start with"),
])
def test_config_errors_name_file_and_problem(tmp_path, block, problem):
    with pytest.raises(cfg.ConfigError) as info:
        cfg.load_settings(_config(tmp_path, block))
    text = str(info.value)
    assert text.startswith(str(tmp_path / "config.json") + ": ") and problem in text and "\n" not in text


def test_config_block_must_exist_and_json_must_parse(tmp_path):
    (tmp_path / "config.json").write_text('{"environment": "prod", "test": {}}')
    with pytest.raises(cfg.ConfigError, match="\"prod\" has no block"):
        cfg.load_settings(str(tmp_path))
    (tmp_path / "config.json").write_text('{"environment": ')
    with pytest.raises(cfg.ConfigError, match="not valid JSON"):
        cfg.load_settings(str(tmp_path))
    with pytest.raises(cfg.ConfigError, match="missing"):
        cfg.load_settings(str(tmp_path / "nowhere"))


def test_settings_extensions(tmp_path):
    settings = cfg.load_settings(_config(tmp_path, {
        "contextbroker": {"address": "broker", "port": "1027",
                          "subscription": {"throttling": "PT2S", "subscription_length": "PT10M",
                                           "subscription_refresh_delay": 0.5}},
        "endpoint": {"address": "10.0.0.5", "port": 10101}, "fiware_service": "robots",
        "fiware_servicepath": "/lab", "pub_frequency": 100, "ngsi_version": "v1"}))
    assert (settings.broker_address, settings.broker_port, settings.throttling) == ("broker", 1027, 2.0)
    assert settings.subscription_refresh_delay == 300
    assert (settings.endpoint_address, settings.endpoint_port) == ("10.0.0.5", 10101)
    client = NgsiClient(settings)
    assert client.headers["Fiware-Service"] == "robots" and client.headers["Fiware-ServicePath"] == "/lab"


def _run_core(config_dir, *extra):
    env = ros_env({"ROS_LOG_DIR": str(config_dir) + "/roslog", "ROS_MASTER_URI": "http://127.0.0.1:9/"})
    return subprocess.run(["/usr/bin/rosrun", "firos", "core.py", "--config", str(config_dir), *extra],
                          env=env, capture_output=True, text=True, timeout=60)


@pytest.mark.parametrize("breakage,expected", [
    ("config", "config.json: test.contextbroker.address is missing or empty"),
    ("json", "whitelist.json: not valid JSON"),
    ("regex", "whitelist.json: robot regex 'turtle(' is not a valid regular expression"),
])
def test_core_stops_with_one_clear_line(tmp_path, breakage, expected):
    write_config(str(tmp_path), 1026)
    if breakage == "config":
        _config(tmp_path, {"contextbroker": {"port": 1026}})
    elif breakage == "json":
        (tmp_path / "whitelist.json").write_text('{"turtle1": ')
    else:
        (tmp_path / "whitelist.json").write_text('{"turtle(": {"publisher": []}}')
    result = _run_core(tmp_path)
    assert result.returncode == 1, result
    lines = [l for l in result.stderr.splitlines() if l.strip()]
    assert len(lines) == 1 and expected in lines[0] and "Traceback" not in result.stderr, result.stderr


# --- whitelist --------------------------------------------------------------------------------------------------

def test_seed_whitelist_examples(tmp_path):
    wl = Whitelist(str(tmp_path / "whitelist.json"), SEED_WHITELIST)
    assert wl.robot_allowed("turtle1") and wl.robot_allowed("turtle_two") and wl.robot_allowed("robot7")
    assert not wl.robot_allowed("turtle") and not wl.robot_allowed("myturtle1") and not wl.robot_allowed("robot")
    assert wl.topic_kinds("turtle1", "cmd_vel") == {"publisher"}
    assert wl.topic_kinds("turtle1", "pose") == {"subscriber"}
    assert wl.topic_kinds("turtle1", "pose2") == set()
    assert wl.topic_kinds("robot1", "cmd_vel_teleop") == {"publisher"}
    assert wl.topic_kinds("robot1", "cmd_vel/teleop") == {"publisher"}
    assert wl.topic_kinds("robot1", "cmd_vel") == set()
    assert wl.topic_kinds("robot1", "move_base/goal") == {"publisher"}
    assert wl.topic_kinds("robot1", "arm/move_base/cancel") == {"publisher"}
    assert wl.topic_kinds("robot1", "move_base/result") == {"subscriber"}
    assert wl.topic_kinds("robot1", "move_base/result_x") == set()


def test_whitelist_write_remove_restore(tmp_path):
    path = tmp_path / "whitelist.json"
    path.write_text(json.dumps(SEED_WHITELIST))
    wl = Whitelist(str(path))
    wl.write({"turtle\\w+": {"subscriber": ["odom"]}, "drone\\d": {"publisher": ["goto"]}})
    assert wl.topic_kinds("turtle1", "odom") == {"subscriber"} and wl.topic_kinds("drone1", "goto") == {"publisher"}
    wl.remove({"turtle\\w+": {"subscriber": ["pose"]}, "drone\\d": {}})
    assert wl.topic_kinds("turtle1", "pose") == set() and not wl.robot_allowed("drone1")
    before = wl.snapshot()
    for bad in ([], {"x(": {}}, {"x": {"publisher": "p"}}, {"x": {"other": []}}, {"x": {"publisher": ["("]}}):
        with pytest.raises(WhitelistError):
            wl.write(bad)
    assert wl.snapshot() == before
    wl.restore()
    assert wl.snapshot() == SEED_WHITELIST
    path.write_text("{bad json")
    with pytest.raises(cfg.ConfigError):
        wl.restore()
    assert wl.snapshot() == SEED_WHITELIST


# --- robots from the graph and from rcm_driver ------------------------------------------------------------------

def test_robots_from_graph(tmp_path):
    wl = Whitelist(str(tmp_path / "w.json"), SEED_WHITELIST)
    graph = {"/turtle1/pose": ("turtlesim/Pose", True, False),
             "/turtle1/cmd_vel": ("geometry_msgs/Twist", False, True),
             "/turtle1/secret": ("std_msgs/String", True, True),
             "/turtle2/pose": ("turtlesim/Pose", False, True),          # nobody publishes: nothing to forward
             "/robot1/move_base/goal": ("move_base_msgs/MoveBaseActionGoal", False, True),
             "/robot1/move_base/result": ("move_base_msgs/MoveBaseActionResult", True, False),
             "/rosout": ("rosgraph_msgs/Log", True, True),
             "/firos/connect": ("std_msgs/String", True, True),
             "/myturtle/pose": ("turtlesim/Pose", True, False)}
    robots = robots_from_graph(graph, wl)
    assert set(robots) == {"turtle1", "robot1"}
    assert {k: v.kinds for k, v in robots["turtle1"].items()} == {"pose": {"subscriber"},
                                                                   "cmd_vel": {"publisher"}}
    assert robots["robot1"]["move_base/goal"].attribute == "move_base.goal"
    assert set(robots_from_graph(graph, wl, only="robot1")) == {"robot1"}


def test_robot_from_rcm_flips_rcm_driver_point_of_view(tmp_path):
    wl = Whitelist(str(tmp_path / "w.json"), SEED_WHITELIST)
    info = {"topics": [{"name": "/odom", "msg": "nav_msgs/Odometry", "type": "publisher"},
                       {"name": "/odom", "msg": "nav_msgs/Odometry", "type": "subscriber"},
                       {"name": "/bot/arm/cmd", "msg": "std_msgs/String", "type": "subscriber"},
                       {"name": "/rosout", "msg": "rosgraph_msgs/Log", "type": "publisher"},
                       {"name": 5}]}
    topics = robot_from_rcm("bot", info, wl)
    assert topics["odom"].kinds == {"publisher", "subscriber"} and topics["odom"].name == "/odom"
    assert topics["arm/cmd"].kinds == {"publisher"} and topics["arm/cmd"].name == "/bot/arm/cmd"
    assert set(topics) == {"odom", "arm/cmd"}
    # a whitelisted robot name filters rcm_driver's topics as usual
    topics = robot_from_rcm("turtle1", {"topics": [
        {"name": "/turtle1/pose", "msg": "turtlesim/Pose", "type": "publisher"},
        {"name": "/turtle1/other", "msg": "std_msgs/String", "type": "publisher"}]}, wl)
    assert set(topics) == {"pose"}


def test_names_and_types_come_from_ngsi_encoding_only():
    import include.discovery as discovery
    from include import ngsi_encoding as enc
    for loose in ("attribute_name", "python_type", "ros_type", "topic_from_attribute"):
        assert not hasattr(discovery, loose)
    assert enc.relative_topic_to_attribute("move_base/goal") == "move_base.goal"
    assert enc.attribute_to_relative_topic("move_base.goal") == "move_base/goal"
    with pytest.raises(enc.NgsiEncodingError):
        enc.attribute_to_relative_topic("a..b")
    assert enc.ld_entity_id("ROBOT", "robot1") == "urn:ngsi-ld:ROBOT:robot1"
    assert enc.robot_from_ld_entity_id("urn:ngsi-ld:ROBOT:robot1", "ROBOT") == "robot1"
    for bad in ("robot1", "urn:ngsi-ld:Car:robot1", "urn:ngsi-ld:ROBOT:a/b", "urn:ngsi-ld:ROBOT:"):
        with pytest.raises(enc.NgsiEncodingError):
            enc.robot_from_ld_entity_id(bad, "ROBOT")
    # discovery leaves out what the rules refuse
    wl = Whitelist("w.json", {"bot": {"subscriber": [".*"]}})
    graph = {"/bot/ok": ("std_msgs/String", True, False), "/bot/weird": ("notatype", True, False)}
    assert set(robots_from_graph(graph, wl)["bot"]) == {"ok"}


# --- notifications ----------------------------------------------------------------------------------------------

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


# --- sender and subscriptions against the stand-in broker (in-process, real HTTP on loopback) -----------------

@pytest.fixture
def broker():
    server = BrokerServer(port=0, quiet=True).start()
    try:
        yield server
    finally:
        server.shutdown()


def _settings(tmp_path, port, version="v2", **extra):
    write_config(str(tmp_path), port, version=version, **extra)
    return cfg.load_settings(str(tmp_path))


def _entity(settings, eid):
    client = NgsiClient(settings)
    return client.get_entity(eid)


@pytest.mark.parametrize("version", ["v1", "v2", "ld"])
def test_sender_keeps_only_the_newest_value_while_the_broker_is_away(tmp_path, version):
    from tests.support.ports import stable_free_ports
    (port,) = stable_free_ports(1)
    settings = _settings(tmp_path, port, version=version)
    created = []
    sender = Sender(NgsiClient(settings), settings, on_created=created.append)
    sender.start()
    try:
        sender.create("bot", {"descriptions": ("DescriptionData", "http://a||http://b")})
        for i in range(50):
            sender.offer("bot", "count", "std_msgs.msg.Int32", {"data": i}, stamp=1000.0 + i)
        wait_until(lambda: not sender.broker_up(), message="the sender to notice no broker")
        server = BrokerServer(port=port, quiet=True).start()
        try:
            wait_until(lambda: (_entity(settings, "bot") or {}).get("count"), timeout=10,
                       message="the entity after the broker came up")
            entity = _entity(settings, "bot")
            assert entity["count"]["value"] == {"firosstamp": 1049.0, "data": 49}
            assert entity["descriptions"]["value"] == "http://a||http://b"
            stats = wait_until(lambda: sender.snapshot_stats()["forwarded"] and sender.snapshot_stats(),
                               message="the sender's count")
            assert stats["forwarded"] == 1 and stats["skipped"] == 49 and stats["broker_up"]
            assert created == ["bot"]
            assert sender.is_own("bot", "count", {"firosstamp": 1049.0, "data": 49})
            assert not sender.is_own("bot", "count", {"data": 49})
        finally:
            server.shutdown()
    finally:
        sender.stop()


def test_sender_batches_and_honours_pub_frequency(tmp_path, broker):
    settings = _settings(tmp_path, broker.port, pub_frequency=1000)
    sender = Sender(NgsiClient(settings), settings)
    sender.start()
    try:
        sender.create("bot", {})
        wait_until(lambda: _entity(settings, "bot") is not None, message="the entity")
        with sender._cond:   # the three arrive "at once" (the sender cannot take the first one alone)
            for name in ("a", "b", "c"):
                sender.offer("bot", name, "std_msgs.msg.Int32", {"data": 1})
        wait_until(lambda: sender.snapshot_stats()["forwarded"] == 3, message="three attributes sent")
        assert sender.snapshot_stats()["requests"] == 1          # one batch
        assert _entity(settings, "bot")["COMMAND"]["value"] == ["a", "b", "c"]
        first = time.monotonic()
        sender.offer("bot", "a", "std_msgs.msg.Int32", {"data": 2})
        wait_until(lambda: _entity(settings, "bot")["a"]["value"]["data"] == 2, message="the second value")
        assert time.monotonic() - first >= 0.5                    # 1000 ms after the first send of "a"
    finally:
        sender.stop()


@pytest.mark.parametrize("version", ["v1", "v2", "ld"])
def test_subscriptions_are_refreshed_before_expiry_and_removed(tmp_path, broker, version):
    settings = _settings(tmp_path, broker.port, version=version)
    settings.subscription_length, settings.subscription_refresh_delay = 60.0, 0.3
    client = NgsiClient(settings)
    subs = Subscriptions(NgsiClient(settings), settings, "http://127.0.0.1:9/firos")
    subs.start()
    path, expiry = ("/ngsi-ld/v1/subscriptions", "expiresAt") if version == "ld" else ("/v2/subscriptions", "expires")
    try:
        subs.set("bot", ["p1"])
        sub_id = wait_until(lambda: subs.ids().get("bot"), message="the subscription")
        listed = lambda: {s["id"]: s for s in (client.request("GET", path)[2] or [])}  # noqa: E731
        first = listed()[sub_id]
        if version == "ld":
            assert first["watchedAttributes"] == ["p1"]
            assert first["entities"] == [{"id": "urn:ngsi-ld:ROBOT:bot", "type": "ROBOT"}]
            assert first["notification"]["endpoint"]["uri"] == "http://127.0.0.1:9/firos"
        else:
            assert first["subject"]["condition"]["attrs"] == ["p1"]
        wait_until(lambda: listed()[sub_id][expiry] != first[expiry], timeout=5,
                   message="the expiry pushed ahead by a refresh")
        subs.remove("bot")
        wait_until(lambda: sub_id not in listed(), message="the subscription removed")
    finally:
        subs.stop()


def test_notification_address_from_interface_or_endpoint(tmp_path):
    import importlib.util
    spec = importlib.util.spec_from_file_location("firos_core", os.path.join(ROOT, "firos", "scripts", "core.py"))
    core = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(core)
    settings = _settings(tmp_path, 1026)
    settings.endpoint_address, settings.endpoint_port = None, None
    settings.interface = "lo"
    assert core.notification_address(settings) == ("127.0.0.1", settings.server_port)
    settings.interface = "public"                       # the address this machine uses towards the broker
    assert core.notification_address(settings) == ("127.0.0.1", settings.server_port)
    settings.interface = "nosuch0"
    with pytest.raises(cfg.ConfigError, match="interface 'nosuch0' does not exist"):
        core.notification_address(settings)
    settings.endpoint_address, settings.endpoint_port = "10.1.2.3", 10101
    assert core.notification_address(settings) == ("10.1.2.3", 10101)


class RecordingBroker:
    """A real HTTP server on loopback that records each request's client port and body, answering 500 to the
    first ``failures`` requests and 204 afterwards (a broker in trouble, then well)."""

    def __init__(self, failures=0):
        from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
        import threading
        self.requests = []
        self.failures = failures
        recorder = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def log_message(self, *args):
                pass

            def do_POST(self):
                body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
                recorder.requests.append((self.client_address[1], self.path, body))
                status = 500 if len(recorder.requests) <= recorder.failures else 204
                self.send_response(status)
                self.send_header("Content-Length", "0")
                self.end_headers()

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.port = self.httpd.server_address[1]
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def close(self):
        self.httpd.shutdown()
        self.httpd.server_close()


def test_client_reuses_one_connection(tmp_path):
    server = RecordingBroker()
    try:
        client = NgsiClient(_settings(tmp_path, server.port))
        for i in range(5):
            client.update({"bot": {"a": ("std_msgs.msg.Int32", {"data": i})}})
        assert len(server.requests) == 5
        assert len({port for port, _, _ in server.requests}) == 1       # HTTP/1.1 keep-alive
        assert server.requests[-1][1] == "/v2/op/update"
        assert server.requests[-1][2]["entities"][0]["a"] == {"type": "std_msgs.msg.Int32", "value": {"data": 4}}
    finally:
        server.close()


def test_sender_retries_a_broker_answering_500_and_keeps_the_newest(tmp_path):
    server = RecordingBroker(failures=3)
    settings = _settings(tmp_path, server.port)
    sender = Sender(NgsiClient(settings), settings)
    sender.start()
    try:
        sender.create("bot", {})
        wait_until(lambda: not sender.broker_up(), message="the sender to see the 500")
        for i in range(10):
            sender.offer("bot", "a", "std_msgs.msg.Int32", {"data": i}, stamp=float(i))
        wait_until(lambda: sender.snapshot_stats()["forwarded"] == 1, timeout=10, message="the value sent")
        bodies = [body for _, _, body in server.requests]
        assert len(bodies) >= 5 and all(b["actionType"] == "append" for b in bodies)
        assert bodies[-1]["entities"][0]["a"]["value"] == {"firosstamp": 9.0, "data": 9}
        assert sender.broker_up() and sender.snapshot_stats()["errors"] >= 3
    finally:
        sender.stop()
        server.close()


@pytest.mark.parametrize("version", ["v1", "v2", "ld"])
def test_a_forgotten_subscription_is_an_error_on_refresh_and_is_recreated(tmp_path, broker, version):
    from include.ngsi_client import BrokerError
    settings = _settings(tmp_path, broker.port, version=version)
    client = NgsiClient(settings)
    with pytest.raises(BrokerError):
        client.refresh("5c57f0a2a5529b6dc9a4ab0e", 60, time.time())
    settings.subscription_length, settings.subscription_refresh_delay = 60.0, 0.3
    lost = []
    subs = Subscriptions(NgsiClient(settings), settings, "http://127.0.0.1:9/firos", on_lost=lost.append)
    subs.start()
    try:
        subs.set("bot", [])
        first = wait_until(lambda: subs.ids().get("bot"), message="the subscription")
        if version == "ld":
            client.request("DELETE", f"/ngsi-ld/v1/subscriptions/{first}")
        elif version == "v2":
            client.request("DELETE", f"/v2/subscriptions/{first}")
        else:
            client.request("POST", "/v1/unsubscribeContext", {"subscriptionId": first})
        second = wait_until(lambda: subs.ids().get("bot") not in (None, first) and subs.ids()["bot"],
                            timeout=5, message="a new subscription after the broker forgot the first")
        assert second != first and lost == ["bot"]
    finally:
        subs.stop()


def test_ld_client_writes_by_batch_upsert_and_reports_problem_details(tmp_path, broker):
    from include.ngsi_client import BrokerError
    settings = _settings(tmp_path, broker.port, version="ld")
    client = NgsiClient(settings)
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


def test_ld_settings(tmp_path):
    settings = cfg.load_settings(_config(tmp_path, {"contextbroker": {"address": "x"}, "ngsi_version": "ld",
                                                    "ld_context": "https://example.org/ctx.jsonld"}))
    assert settings.ngsi_version == "ld" and settings.ld_context == "https://example.org/ctx.jsonld"
    assert NgsiClient(settings).headers["Link"].startswith("<https://example.org/ctx.jsonld>")
    with pytest.raises(cfg.ConfigError, match="test.ld_context must be an http"):
        cfg.load_settings(_config(tmp_path, {"contextbroker": {"address": "x"}, "ld_context": "ctx"}))
    assert cfg.load_settings(_config(tmp_path, {"contextbroker": {"address": "x"}})).ld_context == \
        cfg.DEFAULT_LD_CONTEXT
