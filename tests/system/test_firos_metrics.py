"""FIROS's /metrics scraped from a real FIROS (`rosrun firos core.py`) beside the stand-in broker and a ROS peer,
parsed by prometheus_client's own parser: the values follow real traffic both ways (values forwarded and timed,
values held back by a topic's max_rate, commands published and refused, the broker's answers), and nothing a
request names becomes a label."""

import json

import pytest

from tests.ngsi_broker.testing import start_broker
from tests.support.firos import Firos, metric_samples, received, request, talker, write_config
from tests.support.polling import wait_until

pytestmark = pytest.mark.slow   # real ROS master, broker and FIROS children

WHITELIST = {"end_end_test": {"publisher": [{"topic": "p1", "type": "std_msgs/String"}],
                              "subscriber": ["s1", {"topic": "slow", "max_rate": 0.5}]}}


def scrape(firos):
    status, text = request(firos.port, "GET", "/metrics")
    assert status == 200, text
    return metric_samples(text)


def test_firos_metrics_follow_the_traffic(procs, ros_master, tmp_path):
    broker = start_broker(procs)
    config = write_config(str(tmp_path / "config"), broker.port, whitelist=WHITELIST)
    peer = talker(procs, ros_master, tmp_path, "--rate", "10", "--pub", "/end_end_test/s1", "std_msgs/String",
                  json.dumps({"data": "fast"}), "--pub", "/end_end_test/slow", "std_msgs/String",
                  json.dumps({"data": "slow"}), "--sub", "/end_end_test/p1", "std_msgs/String")
    firos = Firos(procs, ros_master, config).start()
    wait_until(lambda: scrape(firos)[("firos_values_forwarded_total", ())] >= 5, timeout=20,
               message="values forwarded")
    first = scrape(firos)
    assert first[("firos_robots", ())] == 1
    assert first[("firos_topics", (("direction", "ros_to_broker"),))] == 2
    assert first[("firos_broker_up", ())] == 1

    def grown():
        now = scrape(firos)
        return (now[("firos_values_forwarded_total", ())] >= first[("firos_values_forwarded_total", ())] + 10
                and now[("firos_values_skipped_total", (("reason", "rate_limited"),))] > 0 and now)
    later = wait_until(grown, timeout=20, message="more values forwarded, and slow held back by its max_rate")
    forwarded = later[("firos_values_forwarded_total", ())]
    assert later[("firos_forward_latency_seconds_count", ())] == forwarded
    assert later[("firos_forward_latency_seconds_bucket", (("le", "+Inf"),))] == forwarded
    assert later[("firos_broker_requests_total", (("status", "2xx"),))] > first[
        ("firos_broker_requests_total", (("status", "2xx"),))]

    # commands: one through the broker, one refused (another type), one for a name that is no topic
    status, _ = request(broker.port, "POST", "/v2/op/update?options=forcedUpdate", {"actionType": "append",
        "entities": [{"id": "end_end_test", "type": "ROBOT", "COMMAND": {"type": "COMMAND", "value": ["p1"]},
                      "p1": {"type": "std_msgs.msg.String", "value": {"data": "go"}}}]})
    assert status == 204
    wait_until(lambda: {"data": "go"} in received(procs, peer, "/end_end_test/p1"), timeout=15,
               message="the command on p1")
    bad = {"subscriptionId": "x", "data": [{"id": "end_end_test", "type": "ROBOT",
                                            "p1": {"type": "std_msgs.msg.Int32", "value": {"data": 1}},
                                            "COMMAND": {"type": "COMMAND", "value": ["p1"]}}]}
    assert firos.post("/firos", bad)[0] == 400
    invented = {"subscriptionId": "x", "data": [{"id": f"robot{i}", "type": "ROBOT",
                                                 f"topic{i}": {"type": "std_msgs.msg.String", "value": {}},
                                                 "COMMAND": {"type": "COMMAND", "value": [f"topic{i}"]}}
                                                for i in range(50)]}
    assert firos.post("/firos", invented) == (200, {"result": "OK", "reason": {}})
    for i in range(20):
        assert firos.get(f"/robot/nobody{i}")[0] == 404
        assert firos.get(f"/no/such/path/{i}")[0] == 404
    after = scrape(firos)
    assert after[("firos_commands_published_total", ())] >= 1
    assert after[("firos_commands_skipped_total", (("reason", "refused"),))] == 1
    assert after[("firos_commands_skipped_total", (("reason", "unknown_robot"),))] == 50
    assert after[("firos_http_requests_total", (("code", "400"), ("route", "/firos")))] == 1
    assert after[("firos_http_requests_total", (("code", "404"), ("route", "other")))] == 20
    assert after[("firos_http_requests_total", (("code", "404"), ("route", "/robot/<name>")))] == 20
    assert after[("firos_broker_requests_total", (("status", "4xx"),))] >= 20     # the broker's 404s
    labels = {value for (_, pairs) in after for _, value in pairs}
    assert not any("robot1" in value or "topic" in value or "nobody" in value for value in labels), labels
    assert firos.alive()
