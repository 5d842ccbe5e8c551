"""FIROS's `core.py` pieces that run without ROS: the notification address (interface or endpoint) and the
addresses the HTTP API listens on."""

import os

import pytest

import core
from include import config as cfg
from tests.support.firos import settings_for


def test_notification_address_from_interface_or_endpoint(tmp_path):
    settings = settings_for(tmp_path, 1026)
    settings.endpoint_address, settings.endpoint_port = None, None
    settings.interface = "lo"
    assert core.notification_address(settings) == ("127.0.0.1", settings.server_port)
    settings.interface = "public"                       # the address this machine uses towards the broker
    assert core.notification_address(settings) == ("127.0.0.1", settings.server_port)
    settings.interface = "nosuch0"
    with pytest.raises(cfg.ConfigError, match="interface 'nosuch0' does not exist"):
        core.notification_address(settings)
    settings.endpoint_address, settings.endpoint_port = "203.0.113.3", 10101
    assert core.notification_address(settings) == ("203.0.113.3", 10101)


def test_default_listening_addresses(tmp_path, monkeypatch):
    settings = settings_for(tmp_path, 1026, server={"port": 10100})
    monkeypatch.delenv("ROS_IP", raising=False)
    assert core.listen_addresses(settings, "127.0.0.1") == (["127.0.0.1"], [])
    monkeypatch.setenv("ROS_IP", "198.51.100.1")
    assert core.listen_addresses(settings, "203.0.113.10") == (["198.51.100.1"], ["203.0.113.10"])
    assert core.listen_addresses(settings, "198.51.100.1") == (["198.51.100.1"], [])
    configured = settings_for(tmp_path, 1026, server={"port": 10100, "address": ["0.0.0.0"]})
    assert core.listen_addresses(configured, "203.0.113.10") == (["0.0.0.0"], [])


def test_the_brokers_addresses_get_the_brokers_share(tmp_path):
    settings = settings_for(tmp_path, 1026)
    assert core.broker_shares(settings, 8) == {"127.0.0.1": 8}
    settings.broker_address = "no-such-host.invalid"
    assert core.broker_shares(settings, 8) == {}


def test_a_default_administration_socket_another_firos_answers_on_gives_way(tmp_path, firos_log):
    from include import server as http
    path = str(tmp_path / "admin-10100.sock")
    other = http.make_servers(None, 0, [], admin_socket=path, pool=http.WorkerPool(workers=1))
    http.serve_in_thread(other[0])
    settings = settings_for(tmp_path, 1026)
    settings.server_port = 0                              # any free port for the TCP side
    try:
        servers = core.open_servers(http, settings, "127.0.0.1", path)
        for server in servers:
            http.serve_in_thread(server)                  # close_servers stops servers that serve
        try:
            assert servers[-1].path == str(tmp_path / f"admin-10100-{os.getpid()}.sock")
            assert any("another FIROS answers on" in r.getMessage() for r in firos_log.records)
        finally:
            http.close_servers(servers)
        settings.admin_socket = path                      # configured: the operator's choice stops FIROS
        with pytest.raises(OSError, match="another FIROS answers"):
            core.open_servers(http, settings, "127.0.0.1", path)
    finally:
        http.close_servers(other)
