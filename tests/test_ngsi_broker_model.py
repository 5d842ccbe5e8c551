"""The stand-in broker's pure parts (durations, times, Orion's syntax rules, change detection, the notifier)
and its command line as a real child process."""

import os
import signal
import socket
import subprocess
import threading

import pytest

from tests.ngsi_broker import model
from tests.ngsi_broker.subscriptions import Notifier
from tests.ngsi_broker.testing import REPO_ROOT, NotificationReceiver, start_broker
from tests.support.polling import wait_until
from tests.support.ports import free_port


@pytest.mark.parametrize("text, seconds", [
    ("PT1S", 1), ("PT0.5S", 0.5), ("PT5M", 300), ("PT1H", 3600), ("PT24H", 86400), ("P1D", 86400),
    ("P1W", 7 * 86400), ("P1M", 30 * 86400), ("P1Y", 365 * 86400), ("P1DT2H30M", 86400 + 9000), ("PT0S", 0)])
def test_iso8601_durations(text, seconds):
    assert model.parse_duration(text) == pytest.approx(seconds)


@pytest.mark.parametrize("text", ["", "P", "PT", "1D", "P1H", "PT1D", "P1DT", "one day", None, 5])
def test_bad_durations(text):
    with pytest.raises(ValueError):
        model.parse_duration(text)


def test_times_render_as_orion_does():
    epoch = model.parse_iso_time("2040-01-01T14:00:00.00Z")
    assert model.iso_time(epoch) == "2040-01-01T14:00:00.000Z"
    assert model.parse_iso_time("2040-01-01T14:00:00") == epoch          # naive means UTC
    assert model.parse_iso_time("2040-01-01T15:00:00+01:00") == epoch
    assert model.iso_time(model.parse_iso_time("2040-01-01T14:00:00.123456Z")) == "2040-01-01T14:00:00.123Z"
    for bad in ("tomorrow", "", "2040-13-01"):
        with pytest.raises(ValueError):
            model.parse_iso_time(bad)


@pytest.mark.parametrize("value, bad", [
    ("plain text, with: {braces} [brackets] %27 & ? / #", False), ("a<b", True), ("a>b", True), ('"', True),
    ("'", True), ("a=b", True), ("a;b", True), ("f(x)", True), (12, False), (None, False), (True, False),
    ({"k": ["ok", {"deep": "x)"}]}, True), ({"k(": "v"}, True), (["ok", 1, {"a": "b"}], False)])
def test_forbidden_characters_in_values(value, bad):
    assert model.value_has_forbidden_chars(value) is bad


@pytest.mark.parametrize("identifier, ok", [
    ("robot1", True), ("move_base.goal", True), ("std_msgs.msg.String", True), ("a-b:c", True),
    ("a b", False), ("a/b", False), ("a#b", False), ("a?b", False), ("a&b", False), ("a=b", False),
    ("tab\there", False), ("ñ", False), ("", False), ("x" * 256, True), ("x" * 257, False)])
def test_identifier_rules(identifier, ok):
    if ok:
        assert model.check_identifier(identifier, "entity id") == identifier
    else:
        with pytest.raises(model.NgsiError) as caught:
            model.check_identifier(identifier, "entity id")
        assert caught.value.status == 400 and caught.value.error == "BadRequest"


def test_service_paths():
    assert model.parse_update_service_path(None) == "/"
    assert model.parse_update_service_path("/robots/") == "/robots"
    assert model.parse_query_service_paths(None) == [("/", True)]
    assert model.parse_query_service_paths("/a/#, /b") == [("/a", True), ("/b", False)]
    assert model.service_path_matches("/a/b", [("/a", True)])
    assert not model.service_path_matches("/ab", [("/a", True)])
    assert not model.service_path_matches("/a/b", [("/a", False)])
    for bad in ("relative", "/a b", "/" + "/".join("x" * 11), "/" + "x" * 51):
        with pytest.raises(model.NgsiError):
            model.parse_query_service_paths(bad)
    for bad in ("/a,/b", "/a/#"):
        with pytest.raises(model.NgsiError):
            model.parse_update_service_path(bad)
    assert model.parse_tenant("MyService") == "myservice"
    assert model.parse_tenant(None) == model.parse_tenant("") == ""
    with pytest.raises(model.NgsiError):
        model.parse_tenant("my-service")


def test_only_real_changes_count():
    entity = model.Entity("r1", "ROBOT", "/")

    def attr(value, attr_type="T", metadata=None):
        return {"type": attr_type, "value": value, "metadata": metadata or {}}

    assert model.set_attributes(entity, {"a": attr(1), "b": attr("x")}) == ["a", "b"]
    assert model.set_attributes(entity, {"a": attr(1), "b": attr("x")}) == []
    assert model.set_attributes(entity, {"a": attr(1.0)}) == ["a"]           # 1 and 1.0 differ in JSON
    assert model.set_attributes(entity, {"a": attr(1.0, "U")}) == ["a"]       # type change
    assert model.set_attributes(entity, {"a": attr(1.0, "U", {"m": {"type": "T", "value": 1}})}) == ["a"]
    assert model.set_attributes(entity, {"c": attr(True)}, replace=True) == ["c"]
    assert list(entity.attrs) == ["c"]


def test_notifier_reports_failures_quickly_and_keeps_order():
    notifier = Notifier(timeout=1.0)
    results = []
    done = threading.Event()
    try:
        notifier.post(f"http://127.0.0.1:{free_port()}/x", b"{}", {}, lambda ok, code, reason: (
            results.append(("dead", ok, code, reason)), done.set()))
        assert done.wait(5)
        assert results[0][1:3] == (False, None) and "connect" in results[0][3].lower()
        with NotificationReceiver() as receiver:
            for i in range(20):
                notifier.post(receiver.url, str(i).encode(), {"Content-Type": "application/json"},
                              lambda ok, code, reason: results.append((ok, code)))
            notes = receiver.wait_for(20)
            assert [n.json for n in notes] == list(range(20))
            wait_until(lambda: len(results) == 21, message="all results")
            assert results[1:] == [(True, 200)] * 20
    finally:
        notifier.close()


# --- the command line -------------------------------------------------------------------------------------

def run_cli(*args):
    return subprocess.run(["/usr/bin/python3", "-m", "tests.ngsi_broker", *args], cwd=REPO_ROOT,
                          capture_output=True, text=True, timeout=20, check=False)


def test_help_lists_every_option():
    done = run_cli("--help")
    assert done.returncode == 0
    for option in ("--port", "--host", "--notify-timeout", "--max-body", "--no-v1-initial-notification",
                   "--quiet"):
        assert option in done.stdout


def test_bad_options_are_refused_with_one_clear_line():
    for args, words in [(["--port", "70000"], "--port 70000"), (["--port", "abc"], "--port"),
                        (["--notify-timeout", "0"], "--notify-timeout")]:
        done = run_cli(*args)
        assert done.returncode == 2
        assert words in done.stderr and "Traceback" not in done.stderr


def test_port_in_use_is_one_line_and_exit_1():
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        done = run_cli("--port", str(taken.getsockname()[1]))
    assert done.returncode == 1
    assert done.stderr.strip().count("\n") == 0 and "cannot listen on 127.0.0.1:" in done.stderr


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_stops_cleanly_on_signal(procs, sig):
    broker = start_broker(procs)
    os.kill(broker.process.pid, sig)
    assert broker.process.wait(timeout=10) == 0


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
