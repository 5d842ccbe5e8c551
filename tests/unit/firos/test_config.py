"""FIROS's `include/config.py`: the package's own configuration, durations, the keys of config.json and their
one-line errors."""

import json

import pytest

from include import config as cfg
from include.ngsi_versions import client_for
from include.whitelist import Whitelist


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
    ({"contextbroker": {"address": "x", "max_request_size": 100}}, "contextbroker.max_request_size must be"),
    ({"contextbroker": {"address": "x", "max_request_size": "1MB"}}, "contextbroker.max_request_size must be"),
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
        "endpoint": {"address": "203.0.113.5", "port": 10101}, "fiware_service": "robots",
        "fiware_servicepath": "/lab", "pub_frequency": 100, "ngsi_version": "v1"}))
    assert (settings.broker_address, settings.broker_port, settings.throttling) == ("broker", 1027, 2.0)
    assert settings.subscription_refresh_delay == 300
    assert (settings.endpoint_address, settings.endpoint_port) == ("203.0.113.5", 10101)
    client = client_for(settings)
    assert client.headers["Fiware-Service"] == "robots" and client.headers["Fiware-ServicePath"] == "/lab"


def test_max_request_size_defaults_to_orions_limit(tmp_path):
    assert cfg.load_settings(_config(tmp_path, {"contextbroker": {"address": "x"}})).max_request_size == 1048576
    settings = cfg.load_settings(_config(tmp_path, {"contextbroker": {"address": "x", "max_request_size": 8000000}}))
    assert settings.max_request_size == 8000000 and client_for(settings).max_request_size == 8000000


def test_ld_settings(tmp_path):
    settings = cfg.load_settings(_config(tmp_path, {"contextbroker": {"address": "x"}, "ngsi_version": "ld",
                                                    "ld_context": "https://example.org/ctx.jsonld"}))
    assert settings.ngsi_version == "ld" and settings.ld_context == "https://example.org/ctx.jsonld"
    assert client_for(settings).headers["Link"].startswith("<https://example.org/ctx.jsonld>")
    with pytest.raises(cfg.ConfigError, match="test.ld_context must be an http"):
        cfg.load_settings(_config(tmp_path, {"contextbroker": {"address": "x"}, "ld_context": "ctx"}))
    assert cfg.load_settings(_config(tmp_path, {"contextbroker": {"address": "x"}})).ld_context == \
        cfg.DEFAULT_LD_CONTEXT
