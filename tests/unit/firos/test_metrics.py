"""FIROS's `include/metrics.py`: a real scrape parsed by prometheus_client's parser, values that follow what FIROS
did (values forwarded and skipped, commands published and skipped, the broker's answers and the latency, the HTTP
server's requests), labels from fixed sets only (a flood of invented names adds no series), and a FIROS without
prometheus_client answering 503."""

import random
import string

import pytest

from include import metrics as firos_metrics
from include import server as http
from include.bridge import ApiError, Firos
from include.metrics import Metrics, make_metrics
from include.ngsi_versions import client_for
from include.sender import Sender
from include.whitelist import Whitelist
from tests.support.firos import metric_samples, settings_for
from tests.support.polling import wait_until
from tests.unit.firos.test_bridge import FakeGraph, FakeSubscriptions, FakeTopics, v2_note


@pytest.fixture
def parts(tmp_path, broker):
    """A Firos with a real sender towards the in-process stand-in broker, the HTTP server's pool and tally, and
    Metrics wired as core.py wires them."""
    settings = settings_for(tmp_path, broker.port)
    settings.max_request_size = 4096
    sender = Sender(client_for(settings), settings)
    whitelist = Whitelist("unused", {"bot": {"publisher": ["cmd", {"topic": "go", "type": "std_msgs/Int32"}, "off"],
                                             "subscriber": ["pose", {"topic": "map", "max_rate": 0.01}]}})
    graph = FakeGraph({"/bot/pose": ("std_msgs/String", True, False), "/bot/map": ("std_msgs/String", True, False),
                       "/bot/cmd": ("std_msgs/String", False, True)})
    firos = Firos(settings, whitelist, {}, sender, FakeSubscriptions(), FakeTopics(), graph, client_for(settings))
    pool, tally = http.WorkerPool(workers=1), http.Tally()
    metrics = Metrics(firos, pool, tally, http.FirosHandler.ROUTE_LABELS)
    for client in (sender.client, firos.read_client):
        client.observer = metrics.broker_request
    sender.forward_observers.append(metrics.forwarded)
    sender.start()
    firos.scan()
    try:
        yield firos, sender, pool, tally, metrics
    finally:
        sender.stop()
        pool.close()


def scrape(metrics):
    content_type, data = metrics.scrape()
    assert content_type.startswith("text/plain")
    return metric_samples(data.decode())


def test_a_scrape_follows_what_firos_did(parts):
    firos, sender, pool, tally, metrics = parts
    before = scrape(metrics)
    assert before[("firos_robots", ())] == 1
    assert before[("firos_topics", (("direction", "ros_to_broker"),))] == 2
    assert before[("firos_topics", (("direction", "broker_to_ros"),))] == 1
    for reason in ("superseded", "rate_limited", "too_large", "conversion_error", "refused", "unmapped"):
        assert before[("firos_values_skipped_total", (("reason", reason),))] == 0   # every reason from the start
    wait_until(lambda: sender.snapshot_stats()["broker_up"] and scrape(metrics)[
        ("firos_broker_requests_total", (("status", "2xx"),))] >= 1, message="the entity created")

    for i in range(5):
        sender.offer("bot", "pose", "std_msgs.msg.String", {"data": f"p{i}"})
    sender.offer("bot", "map", "std_msgs.msg.String", {"data": "m1"})
    wait_until(lambda: sender.snapshot_stats()["forwarded"] >= 2, message="pose and map forwarded")
    sender.offer("bot", "map", "std_msgs.msg.String", {"data": "m2"})     # waits for max_rate ...
    sender.offer("bot", "map", "std_msgs.msg.String", {"data": "m3"})     # ... and is replaced: rate limited
    sender.offer("bot", "pose", "std_msgs.msg.String", {"data": "x" * 5000})   # over max_request_size
    wait_until(lambda: sender.skips["too_large"] == 1, message="the big value refused")

    firos.handle_notification(v2_note("bot", ["cmd", "go", "off"], cmd=("std_msgs.msg.String", {"data": "c"}),
                                      go=("std_msgs.msg.Int32", {"data": 1}), off=("std_msgs.msg.Empty", {})))
    with pytest.raises(ApiError):
        firos.handle_notification(v2_note("bot", ["cmd"], cmd=("std_msgs.msg.Int32", {"data": 1})))
    tally.add(("/robots", 200))
    tally.add(("other", 404))

    after = scrape(metrics)
    forwarded = after[("firos_values_forwarded_total", ())]
    assert forwarded >= 2 and forwarded == sender.snapshot_stats()["forwarded"]
    assert after[("firos_forward_latency_seconds_count", ())] == forwarded
    assert after[("firos_values_skipped_total", (("reason", "too_large"),))] == 1
    assert after[("firos_values_skipped_total", (("reason", "rate_limited"),))] >= 1
    assert after[("firos_commands_published_total", ())] == 2
    assert after[("firos_commands_skipped_total", (("reason", "not_in_graph"),))] == 1
    assert after[("firos_commands_skipped_total", (("reason", "refused"),))] == 1
    assert after[("firos_broker_request_duration_seconds_count", ())] == sum(
        value for (name, _), value in after.items() if name == "firos_broker_requests_total")
    assert after[("firos_http_requests_total", (("code", "200"), ("route", "/robots")))] == 1
    assert after[("firos_http_requests_total", (("code", "404"), ("route", "other")))] == 1
    assert after[("firos_broker_up", ())] == 1 and ("process_cpu_seconds_total", ()) in after


def test_broker_trouble_is_counted_by_status_class(parts):
    firos, sender, pool, tally, metrics = parts
    with pytest.raises(ApiError) as info:
        firos.read_robot("nobody")                        # the broker answers 404
    assert info.value.status == 404
    found = scrape(metrics)
    assert found[("firos_broker_requests_total", (("status", "4xx"),))] >= 1
    unreachable = client_for(settings_for(sender.client.settings.config_dir, 9))   # nothing listens on port 9
    unreachable.observer = metrics.broker_request
    with pytest.raises(Exception):
        unreachable.get_entity("bot")
    assert scrape(metrics)[("firos_broker_requests_total", (("status", "connection"),))] == 1


def test_invented_names_add_no_series(parts):
    firos, sender, pool, tally, metrics = parts
    before = set(scrape(metrics))
    rng = random.Random(7)
    for _ in range(200):
        robot = rng.choice(["bot", "".join(rng.choices(string.ascii_letters, k=12))])
        attr = "".join(rng.choices(string.ascii_lowercase, k=rng.randint(1, 40)))
        try:
            firos.handle_notification(v2_note(robot, [attr], **{attr: ("std_msgs.msg.String", {"data": attr})}))
        except ApiError:
            pass
    after = set(scrape(metrics))
    assert {name for name, _ in after - before} <= {"firos_broker_requests_total"}, after - before
    assert len(after) - len(before) <= 6


def test_without_prometheus_client_metrics_answer_503_naming_the_package(monkeypatch, firos_log):
    monkeypatch.setattr(firos_metrics, "prometheus_client", None)
    unavailable = make_metrics(None, None, None, ())
    with pytest.raises(ApiError) as info:
        unavailable.scrape()
    assert info.value.status == 503 and "python3-prometheus-client" in info.value.reason
    unavailable.broker_request("2xx", 0.1)                 # the hooks do nothing, and never fail
    unavailable.forwarded([0.1])
    warnings = [r.getMessage() for r in firos_log.records if "python3-prometheus-client" in r.getMessage()]
    assert len(warnings) == 1
