"""FIROS's `include/config.py`, the keys that decide who may reach FIROS: `server.address` and
`server.admin_token`."""

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
