"""FIROS configuration: reading and validating config.json, whitelist.json and robotdescriptions.json.

Owns the `Settings` of the chosen environment block (CONTRACTS §3), the duration syntax the subscription keys
accept (seconds as a number, or ISO 8601 such as "PT0S", "PT5M", "P1D"), and `ConfigError`, whose text is one
line naming the file and the problem. Nothing here touches ROS or the network.
"""

import json
import os
import re
from dataclasses import dataclass, field

PACKAGE_CONFIG_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))),
                                  "config")

LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "WARN", "ERROR", "CRITICAL", "FATAL")
_ISO_DURATION = re.compile(
    r"^P(?:(?P<years>\d+(?:\.\d+)?)Y)?(?:(?P<months>\d+(?:\.\d+)?)M)?(?:(?P<weeks>\d+(?:\.\d+)?)W)?"
    r"(?:(?P<days>\d+(?:\.\d+)?)D)?(?:T(?:(?P<hours>\d+(?:\.\d+)?)H)?(?:(?P<minutes>\d+(?:\.\d+)?)M)?"
    r"(?:(?P<seconds>\d+(?:\.\d+)?)S)?)?$")
_UNIT_SECONDS = {"years": 365 * 86400, "months": 30 * 86400, "weeks": 7 * 86400, "days": 86400,
                 "hours": 3600, "minutes": 60, "seconds": 1}


class ConfigError(Exception):
    """A configuration file is missing, unreadable or wrong; str() is one line naming the file and problem."""

    def __init__(self, path, problem):
        super().__init__(f"{path}: {problem}")
        self.path = path
        self.problem = problem


@dataclass
class Settings:
    """The chosen environment block of config.json, validated, with defaults filled in."""
    config_dir: str
    environment: str
    server_port: int = 10100
    broker_address: str = ""
    broker_port: int = 1026
    throttling: float = 0.0                 # seconds
    subscription_length: float = 300.0      # seconds
    subscription_refresh_delay: float = 150.0  # seconds after (re)subscribing when FIROS refreshes
    interface: str = "public"
    endpoint_address: str | None = None
    endpoint_port: int | None = None
    log_level: str = "INFO"
    ngsi_version: str = "v2"
    context_type: str = "ROBOT"
    pub_frequency: float = 0.0              # milliseconds between two sends of one attribute
    fiware_service: str | None = None
    fiware_servicepath: str | None = None
    discovery_interval: float = 1.0         # (ext) seconds between two looks at the ROS graph; 0 = only at start
    retry_max_delay: float = 5.0            # (ext) longest wait between two tries while the broker is down
    extra: dict = field(default_factory=dict)


def parse_duration(value, path, key):
    """Seconds from a number or an ISO 8601 duration string; ConfigError naming ``key`` otherwise."""
    if isinstance(value, bool):
        raise ConfigError(path, f"{key} must be a number of seconds or an ISO 8601 duration, not {value!r}")
    if isinstance(value, (int, float)):
        if value < 0:
            raise ConfigError(path, f"{key} must not be negative (got {value})")
        return float(value)
    if isinstance(value, str):
        match = _ISO_DURATION.match(value.strip())
        if match and value.strip() not in ("P", "PT") and not value.strip().endswith("T"):
            return float(sum(float(v) * _UNIT_SECONDS[k] for k, v in match.groupdict().items() if v))
    raise ConfigError(path, f"{key} must be a number of seconds or an ISO 8601 duration like \"PT5M\", "
                            f"not {value!r}")


def read_json(path, what):
    """The parsed JSON object in ``path``; ConfigError (one line) when missing, unreadable or not an object."""
    try:
        with open(path, encoding="utf-8") as f:
            text = f.read()
    except FileNotFoundError:
        raise ConfigError(path, f"{what} file is missing") from None
    except OSError as exc:
        raise ConfigError(path, f"cannot read {what} file: {exc.strerror}") from None
    try:
        data = json.loads(text)
    except ValueError as exc:
        raise ConfigError(path, f"not valid JSON: {exc}") from None
    if not isinstance(data, dict):
        raise ConfigError(path, f"must hold a JSON object, not {type(data).__name__}")
    return data


def _port(value, path, key):
    if isinstance(value, str) and value.strip().isdigit():
        value = int(value.strip())
    if not isinstance(value, int) or isinstance(value, bool) or not 0 < value < 65536:
        raise ConfigError(path, f"{key} must be a TCP port number (1-65535), not {value!r}")
    return value


def _object(block, key, path, where):
    value = block.get(key, {})
    if not isinstance(value, dict):
        raise ConfigError(path, f"{where}{key} must be a JSON object")
    return value


def load_settings(config_dir):
    """Read CONFIG_DIR/config.json and return the Settings of its chosen environment."""
    path = os.path.join(config_dir, "config.json")
    data = read_json(path, "configuration")
    env = data.get("environment")
    if not isinstance(env, str) or not env:
        raise ConfigError(path, "\"environment\" must name the block to use (a string)")
    block = data.get(env)
    if not isinstance(block, dict):
        raise ConfigError(path, f"the environment \"{env}\" has no block (an object named \"{env}\")")
    settings = Settings(config_dir=config_dir, environment=env)
    where = f"{env}."

    server = _object(block, "server", path, where)
    if "port" in server:
        settings.server_port = _port(server["port"], path, f"{where}server.port")

    broker = block.get("contextbroker")
    if not isinstance(broker, dict):
        raise ConfigError(path, f"{where}contextbroker is missing (it needs at least \"address\")")
    address = broker.get("address")
    if not isinstance(address, str) or not address.strip():
        raise ConfigError(path, f"{where}contextbroker.address is missing or empty")
    settings.broker_address = address.strip()
    if "port" in broker:
        settings.broker_port = _port(broker["port"], path, f"{where}contextbroker.port")
    sub = _object(broker, "subscription", path, f"{where}contextbroker.")
    sub_where = f"{where}contextbroker.subscription."
    if "throttling" in sub:
        settings.throttling = parse_duration(sub["throttling"], path, sub_where + "throttling")
    if "subscription_length" in sub:
        settings.subscription_length = parse_duration(sub["subscription_length"], path,
                                                      sub_where + "subscription_length")
    if settings.subscription_length < 1:
        raise ConfigError(path, f"{sub_where}subscription_length must be at least one second")
    settings.subscription_refresh_delay = settings.subscription_length / 2
    if "subscription_refresh_delay" in sub:
        delay = sub["subscription_refresh_delay"]
        if isinstance(delay, (int, float)) and not isinstance(delay, bool) and 0 < delay < 1:
            settings.subscription_refresh_delay = delay * settings.subscription_length
        else:
            settings.subscription_refresh_delay = parse_duration(delay, path, sub_where + "subscription_refresh_delay")
    if not 0 < settings.subscription_refresh_delay < settings.subscription_length:
        raise ConfigError(path, f"{sub_where}subscription_refresh_delay must be above zero and below "
                                f"subscription_length, so that subscriptions are refreshed before they expire")

    interface = block.get("interface", "public")
    if not isinstance(interface, str) or not interface:
        raise ConfigError(path, f"{where}interface must be \"public\" or an interface name")
    settings.interface = interface
    endpoint = _object(block, "endpoint", path, where)
    if endpoint:
        ep_addr = endpoint.get("address")
        if ep_addr is not None and (not isinstance(ep_addr, str) or not ep_addr):
            raise ConfigError(path, f"{where}endpoint.address must be a host name or address")
        settings.endpoint_address = ep_addr
        if "port" in endpoint:
            settings.endpoint_port = _port(endpoint["port"], path, f"{where}endpoint.port")

    level = block.get("log_level", "INFO")
    if not isinstance(level, str) or level.upper() not in LOG_LEVELS:
        raise ConfigError(path, f"{where}log_level must be one of {', '.join(LOG_LEVELS)}, not {level!r}")
    settings.log_level = level.upper()

    version = block.get("ngsi_version", "v2")
    if version not in ("v1", "v2"):
        raise ConfigError(path, f"{where}ngsi_version must be \"v1\" or \"v2\", not {version!r}")
    settings.ngsi_version = version

    ctype = block.get("context_type", "ROBOT")
    if not isinstance(ctype, str) or not re.fullmatch(r"[A-Za-z0-9_\-]{1,256}", ctype):
        raise ConfigError(path, f"{where}context_type must be an NGSI type name, not {ctype!r}")
    settings.context_type = ctype

    for key, attr in (("pub_frequency", "pub_frequency"), ("discovery_interval", "discovery_interval"),
                      ("retry_max_delay", "retry_max_delay")):
        if key in block:
            value = block[key]
            if isinstance(value, bool) or not isinstance(value, (int, float)) or value < 0:
                raise ConfigError(path, f"{where}{key} must be a number not below zero, not {value!r}")
            setattr(settings, attr, float(value))
    if settings.retry_max_delay < 0.1:
        raise ConfigError(path, f"{where}retry_max_delay must be at least 0.1 seconds")

    for key, attr in (("fiware_service", "fiware_service"), ("fiware_servicepath", "fiware_servicepath")):
        value = block.get(key, broker.get(key))
        if value is not None:
            if not isinstance(value, str) or not value:
                raise ConfigError(path, f"{where}{key} must be a non-empty string")
            setattr(settings, attr, value)
    if settings.fiware_servicepath is not None and not settings.fiware_servicepath.startswith("/"):
        raise ConfigError(path, f"{where}fiware_servicepath must start with \"/\"")
    return settings


def load_descriptions(config_dir):
    """{robot: "url1||url2"} from CONFIG_DIR/robotdescriptions.json (an absent file means none)."""
    path = os.path.join(config_dir, "robotdescriptions.json")
    if not os.path.exists(path):
        return {}
    data = read_json(path, "robot descriptions")
    result = {}
    for robot, entry in data.items():
        urls = entry.get("descriptions") if isinstance(entry, dict) else None
        if not isinstance(urls, list) or not all(isinstance(u, str) for u in urls):
            raise ConfigError(path, f"\"{robot}\" must be {{\"descriptions\": [urls as strings]}}")
        result[robot] = "||".join(urls)
    return result
