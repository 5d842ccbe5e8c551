"""FIROS's `include/sender.py` against the stand-in broker (in-process) and a recording server: only the newest
value waits while the broker is away, batches and `pub_frequency`, retries of a broker answering 500."""

import time

import pytest

from include.ngsi_versions import client_for
from include.sender import Sender
from tests.ngsi_broker.server import BrokerServer
from tests.support.firos import RecordingBroker, settings_for
from tests.support.polling import wait_until


def _entity(settings, eid):
    client = client_for(settings)
    return client.get_entity(eid)


@pytest.mark.parametrize("version", ["v1", "v2", "ld"])
def test_sender_keeps_only_the_newest_value_while_the_broker_is_away(tmp_path, version):
    from tests.support.ports import stable_free_ports
    (port,) = stable_free_ports(1)
    settings = settings_for(tmp_path, port, version=version)
    created = []
    sender = Sender(client_for(settings), settings, on_created=created.append)
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
    settings = settings_for(tmp_path, broker.port, pub_frequency=1000)
    sender = Sender(client_for(settings), settings)
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


def test_sender_retries_a_broker_answering_500_and_keeps_the_newest(tmp_path):
    server = RecordingBroker(failures=3)
    settings = settings_for(tmp_path, server.port)
    sender = Sender(client_for(settings), settings)
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


def test_values_not_sent_are_counted_by_reason_and_sent_ones_timed(tmp_path, broker):
    settings = settings_for(tmp_path, broker.port)
    sender = Sender(client_for(settings), settings)
    timed = []
    sender.forward_observers.append(timed.extend)
    sender.forward_observers.append(lambda latencies: 1 / 0)      # a failing observer never stops the sender
    sender.create("bot", {})
    sender.offer("bot", "a", "std_msgs.msg.Int32", {"data": 1}, stamp=time.time())
    sender.offer("bot", "a", "std_msgs.msg.Int32", {"data": 2}, stamp=time.time())   # before any send: superseded
    sender.offer("bot", "b", "std_msgs.msg.Int32", {"data": 3})
    sender.forget("bot", "b")                                                          # unmapped while waiting
    sender.start()
    try:
        wait_until(lambda: sender.snapshot_stats()["forwarded"] == 1, message="the newest value of a sent")
        assert dict(sender.skips) == {"superseded": 1, "rate_limited": 0, "too_large": 0, "conversion_error": 0,
                                      "refused": 0, "unmapped": 1}
        assert len(timed) == 1 and 0 <= timed[0] < 10
    finally:
        sender.stop()
