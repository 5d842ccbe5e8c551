"""FIROS's `include/subscriptions.py` against the stand-in broker (in-process), in v1, v2 and NGSI-LD:
refreshed before expiry, removed, and made again when the broker forgot one."""

import time

import pytest

from include.ngsi_versions import client_for
from include.subscriptions import Subscriptions
from tests.support.firos import settings_for
from tests.support.polling import wait_until


@pytest.mark.parametrize("version", ["v1", "v2", "ld"])
def test_subscriptions_are_refreshed_before_expiry_and_removed(tmp_path, broker, version):
    settings = settings_for(tmp_path, broker.port, version=version)
    settings.subscription_length, settings.subscription_refresh_delay = 60.0, 0.3
    client = client_for(settings)
    subs = Subscriptions(client_for(settings), settings, "http://127.0.0.1:9/firos")
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


@pytest.mark.parametrize("version", ["v1", "v2", "ld"])
def test_a_forgotten_subscription_is_an_error_on_refresh_and_is_recreated(tmp_path, broker, version):
    from include.ngsi_client import BrokerError
    settings = settings_for(tmp_path, broker.port, version=version)
    client = client_for(settings)
    with pytest.raises(BrokerError):
        client.refresh("5c57f0a2a5529b6dc9a4ab0e", 60, time.time())
    settings.subscription_length, settings.subscription_refresh_delay = 60.0, 0.3
    lost = []
    subs = Subscriptions(client_for(settings), settings, "http://127.0.0.1:9/firos", on_lost=lost.append)
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
