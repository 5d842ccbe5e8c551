"""FIROS's `include/config.py`, the keys that decide who may reach FIROS: `server.address`, `server.admin_token`
and `server.admin_socket` (and where the administration socket is without it)."""

import pytest

from include import config as cfg
from tests.support.firos import settings_for


def _settings(tmp_path, **server):
    return settings_for(tmp_path, 1026, server=dict({"port": 10100}, **server))


def test_server_address_and_admin_token_keys(tmp_path):
    assert _settings(tmp_path).server_addresses is None and _settings(tmp_path).admin_token is None
    assert _settings(tmp_path, address="203.0.113.5").server_addresses == ["203.0.113.5"]
    assert _settings(tmp_path, address=["127.0.0.1", "::1", "127.0.0.1"]).server_addresses == ["127.0.0.1", "::1"]
    assert _settings(tmp_path, admin_token="x" * 16).admin_token == "x" * 16
    for bad in ({"address": "somehost"}, {"address": []}, {"address": 5}, {"admin_token": "short"},
                {"admin_token": "has a space in it!!"}):
        with pytest.raises(cfg.ConfigError) as info:
            _settings(tmp_path, **bad)
        assert "server." in str(info.value) and "\n" not in str(info.value)


def test_the_administration_socket_is_configured_or_under_ros_home(tmp_path):
    assert _settings(tmp_path, admin_socket="/run/firos/admin.sock").admin_socket == "/run/firos/admin.sock"
    for bad in ("relative/admin.sock", 5, "/" + "x" * 120):
        with pytest.raises(cfg.ConfigError) as info:
            _settings(tmp_path, admin_socket=bad)
        assert "server.admin_socket" in str(info.value) and "\n" not in str(info.value)
    settings = _settings(tmp_path)
    assert cfg.admin_socket_path(settings, {"ROS_HOME": "/home/op/.ros"}) == "/home/op/.ros/firos/admin-10100.sock"
    settings.server_port = 10101                           # -P changes the port: the default follows it
    assert cfg.admin_socket_path(settings, {}).endswith("/.ros/firos/admin-10101.sock")
    with pytest.raises(cfg.ConfigError, match="set server.admin_socket"):
        cfg.admin_socket_path(settings, {"ROS_HOME": "/" + "h" * 100})
    settings.admin_socket = "/run/firos/admin.sock"
    assert cfg.admin_socket_path(settings, {"ROS_HOME": "/" + "h" * 100}) == "/run/firos/admin.sock"
