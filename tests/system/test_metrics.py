"""The master's ``/metrics`` scraped as Prometheus would, parsed with prometheus_client's own parser, against a real
master and real robot agents pairing on loopback: the values follow robots connecting, pairing, failing and
leaving (heartbeats missed included), the RDAPI's tokens guard it, and a flood of requests to random paths adds no
series beyond a bounded few."""

import os
import random
import signal
import string

from prometheus_client.parser import text_string_to_metric_families

from tests.support.lifecycle import Platform
from tests.support.polling import wait_until
from tests.system.test_rdapi_security import add_token, call

CRASHER = {"sn_package": "robotics_test", "sn_type": "crasher.py", "sn_name": "crasher", "sn_side": "R"}
NO_LAUNCH_FILE = {"sl_package": "robotics_test", "sl_file_launcher": "no_such.launch", "sl_name": "missing",
                  "sl_side": "S"}


def scrape(master, token=None):
    """{(sample name, ((label, value), ...)): value} of the master's /metrics."""
    status, text, headers = call(master, "GET", "/metrics", token=token)
    assert status == 200, (status, text)
    assert headers["content-type"].startswith("text/plain; version=0.0.4")
    found = {}
    for family in text_string_to_metric_families(text):
        for sample in family.samples:
            found[(sample[0], tuple(sorted(sample[1].items())))] = sample[2]
    return found


def value(master, name, token=None, **labels):
    return scrape(master, token).get((name, tuple(sorted(labels.items()))))


def robots(master, token=None):
    found = scrape(master, token)
    return tuple(found[(f"rcm_robots_{what}", ())] for what in ("provisioned", "connected", "paired"))


def wait_for(master, expected, what, token=None, timeout=30):
    wait_until(lambda: what(master, token) == expected, timeout=timeout,
               message=f"/metrics to say {expected} (now {what(master, token)})")


def test_metrics_follow_robots_connecting_pairing_failing_and_leaving(procs, tmp_path):
    platform = Platform(procs, tmp_path)
    master = platform.master.start()
    assert robots(master) == (0, 0, 0)
    found = scrape(master)
    assert found[("rcm_servers_connected", ())] == 1
    assert found[("rcm_service_spaces", (("server", "master"), ("state", "paired")))] == 0
    assert found[("rcm_hello_duration_seconds_count", ())] == 0

    platform.provision_logic("broken", sn_list=[CRASHER], sl_list=[NO_LAUNCH_FILE])
    platform.provision_robot("robot1", "empty")
    platform.provision_robot("robot2", "broken")
    assert robots(master) == (2, 0, 0)

    # robot1 pairs: connected, paired, one hello and one pairing timed, its space on the master
    robot1 = platform.robot("robot1", "127.0.0.2").start()
    wait_for(master, (2, 1, 1), robots)
    found = scrape(master)
    assert found[("rcm_hello_duration_seconds_count", ())] == 1
    assert found[("rcm_pairing_duration_seconds_count", ())] == 1
    assert 0 < found[("rcm_pairing_duration_seconds_sum", ())] < 60
    assert found[("rcm_service_spaces", (("server", "master"), ("state", "paired")))] == 1
    assert found[("rcm_robot_connections_total", ())] == 1

    # robot2 connects but cannot pair: its crasher exits on the robot, its launch file does not exist here
    robot2 = platform.robot("robot2", "127.0.0.3").start()
    wait_for(master, (2, 2, 1), robots)
    wait_until(lambda: value(master, "rcm_item_failures_total", reason="exited") == 1
               and value(master, "rcm_item_failures_total", reason="launch_file") == 1, timeout=30,
               message="robot2's two failed items to be counted")
    found = scrape(master)
    assert found[("rcm_service_spaces", (("server", "master"), ("state", "unpaired")))] == 1
    assert found[("rcm_pairing_duration_seconds_count", ())] == 1            # only what paired
    assert sum(v for (n, _), v in found.items() if n == "rcm_item_failures_total") == 2
    assert value(master, "rcm_item_failures_total", reason="exited") == 1   # counted once, scrape after scrape

    # robot2 stops answering: heartbeats missed, then it is declared gone
    os.killpg(robot2.process.pid, signal.SIGSTOP)
    try:
        wait_for(master, (2, 1, 1), robots, timeout=20)
        assert value(master, "rcm_heartbeat_timeouts_total", peer="robot") == 1
        assert value(master, "rcm_heartbeat_misses_total", peer="robot") >= 1
    finally:
        os.killpg(robot2.process.pid, signal.SIGCONT)
    assert value(master, "rcm_robot_disconnections_total") >= 1

    # robot1 leaves: neither connected nor paired any more, its space gone
    assert robot1.stop() == 0
    wait_until(lambda: robots(master)[2] == 0, timeout=20, message="robot1 no longer paired")
    wait_until(lambda: value(master, "rcm_service_spaces", server="master", state="paired") == 0, timeout=20,
               message="robot1's space gone")
    assert robot2.stop() == 0
    wait_for(master, (2, 0, 0), robots)
    platform.stop_all_and_check_nothing_left()


def test_metrics_need_a_read_token_once_tokens_exist_and_labels_stay_bounded(procs, tmp_path):
    platform = Platform(procs, tmp_path)
    master = platform.master.start()
    assert call(master, "GET", "/metrics")[0] == 200                        # open, like the rest of the RDAPI
    reader = add_token(master, "prometheus", "read")
    wait_until(lambda: call(master, "GET", "/metrics")[0] == 401, timeout=10, message="/metrics to need a token")
    status, answer, headers = call(master, "GET", "/metrics")
    assert answer["result"] == "ERROR" and "Bearer" in headers["www-authenticate"]
    assert call(master, "GET", "/metrics", token="x" * 43)[0] == 401
    assert robots(master, reader) == (0, 0, 0)
    admin = add_token(master, "ops", "admin")
    for token in (None, reader, admin):                                     # GET only, whoever asks
        assert call(master, "POST", "/metrics", body={}, token=token)[0] == 405

    call(master, "GET", "/platform_instance/read", token=reader)
    before = scrape(master, reader)
    rng = random.Random(19)
    for _ in range(300):
        path = "/" + "".join(rng.choice(string.ascii_letters + string.digits + "/_.-")
                             for _ in range(rng.randint(1, 60)))
        method = rng.choice(["GET", "POST", "PUT", "DELETE", "PATCH", "BREW"])
        status = call(master, method, path, token=rng.choice([reader, admin, None]))[0]
        assert status in (401, 403, 404, 405, 415), (method, path, status)
    after = scrape(master, reader)
    new = {k for k in after if k not in before and not k[0].startswith(("process_", "python_"))}
    assert {dict(labels).get("route") for _, labels in new} <= {"other", "/metrics"}
    request_series = [labels for name, labels in after if name == "rcm_rdapi_requests_total"]
    assert len(request_series) <= 20, request_series     # routes x methods x statuses seen, not paths
    routes = {dict(labels)["route"] for labels in request_series}
    assert routes <= {"other", "/metrics", "/platform_instance/read", "/"}, routes   # / : the start probe
    assert sum(v for (n, labels), v in after.items() if n == "rcm_rdapi_requests_total"
               and dict(labels)["route"] == "other") == 300
    platform.stop_all_and_check_nothing_left()
