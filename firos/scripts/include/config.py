"""FIROS configuration: reading and validating config.json, whitelist.json and robotdescriptions.json.

Owns the `Settings` of the chosen environment block (CONTRACTS §3), the duration syntax the subscription keys
accept (seconds as a number, or ISO 8601 such as "PT0S", "PT5M", "P1D"), and `ConfigError`, whose text is one
line naming the file and the problem. The keys of the block are one table (`KEYS`: where the key sits, which
Settings field it fills, which parser checks it); the few rules between keys follow it. Nothing here touches ROS
or the network.
"""

from __future__ import annotations

import ipaddress
import json
import os
import re
from dataclasses import dataclass, field

PACKAGE_CONFIG_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))),
                                  "config")

DEFAULT_LD_CONTEXT = "https://uri.etsi.org/ngsi-ld/v1/ngsi-ld-core-context.jsonld"
NGSI_VERSIONS = ("v1", "v2", "ld")
MAX_SOCKET_PATH = 107      # bytes of a Unix socket's path (sun_path holds 108 with the final NUL)
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
    server_addresses: list | None = None    # (ext) addresses the HTTP API listens on; None = core.py's default
    admin_token: str | None = None          # (ext) administrative calls over TCP need it (none without it)
    admin_socket: str | None = None         # (ext) the administration socket's path; None = admin_socket_path's
    broker_address: str = ""
    broker_port: int = 1026
    max_request_size: int = 1048576         # (ext) bytes; FIROS never sends a bigger request (Orion's limit)
    throttling: float = 0.0                 # seconds
    subscription_length: float = 300.0      # seconds
    subscription_refresh_delay: float = 150.0  # seconds after (re)subscribing when FIROS refreshes
    interface: str = "public"
    endpoint_address: str | None = None
    endpoint_port: int | None = None
    log_level: str = "INFO"
    ngsi_version: str = "v2"                # "v1", "v2" or "ld"
    ld_context: str = DEFAULT_LD_CONTEXT     # (ext) the @context FIROS names in NGSI-LD requests
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


class _Bad(ValueError):
    """A value refused by one of the parsers below; the text completes "<key> ..."."""


def _port(value):
    if isinstance(value, str) and value.strip().isdigit():
        value = int(value.strip())
    if not isinstance(value, int) or isinstance(value, bool) or not 0 < value < 65536:
        raise _Bad(f"must be a TCP port number (1-65535), not {value!r}")
    return value


def _duration(value):
    try:
        return parse_duration(value, "", "")
    except ConfigError as exc:
        raise _Bad(exc.problem.strip()) from None


def _refresh_delay(value):
    """Seconds, or a number between 0 and 1 meaning that fraction of subscription_length (kept negative here
    and resolved once the length is known)."""
    if isinstance(value, (int, float)) and not isinstance(value, bool) and 0 < value < 1:
        return -float(value)
    return _duration(value)


def _text(what):
    def parse(value):
        if not isinstance(value, str) or not value.strip():
            raise _Bad(f"must be {what}")
        return value.strip()
    return parse


def _log_level(value):
    if not isinstance(value, str) or value.upper() not in LOG_LEVELS:
        raise _Bad(f"must be one of {', '.join(LOG_LEVELS)}, not {value!r}")
    return value.upper()


def _ngsi_version(value):
    if value not in NGSI_VERSIONS:
        raise _Bad(f"must be \"v1\", \"v2\" or \"ld\", not {value!r}")
    return value


def _type_name(value):
    if not isinstance(value, str) or not re.fullmatch(r"[A-Za-z0-9_\-]{1,256}", value):
        raise _Bad(f"must be an NGSI type name, not {value!r}")
    return value


def _url(value):
    if not isinstance(value, str) or not re.fullmatch(r"https?://[^\s<>\"]+", value):
        raise _Bad(f"must be an http(s) URL of a JSON-LD @context, not {value!r}")
    return value


def _non_negative(value):
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value < 0:
        raise _Bad(f"must be a number not below zero, not {value!r}")
    return float(value)


def _size(value):
    if isinstance(value, bool) or not isinstance(value, int) or value < 1024:
        raise _Bad(f"must be a whole number of bytes, at least 1024, not {value!r}")
    return value


def _addresses(value):
    """One IP address or a list of them (``0.0.0.0`` only when written so)."""
    values = value if isinstance(value, list) else [value]
    if not values or not all(isinstance(v, str) and v.strip() for v in values):
        raise _Bad(f"must be an IP address or a list of them, not {value!r}")
    result = []
    for text in values:
        try:
            result.append(str(ipaddress.ip_address(text.strip())))
        except ValueError:
            raise _Bad(f"must be an IP address or a list of them, not {text!r}") from None
    return list(dict.fromkeys(result))


def _token(value):
    if not isinstance(value, str) or len(value) < 16 or not value.isprintable() or " " in value:
        raise _Bad("must be a secret of at least 16 printable characters without spaces")
    return value


def _socket_path(value):
    if not isinstance(value, str) or not os.path.isabs(value) or "\0" in value:
        raise _Bad(f"must be an absolute path for a Unix socket, not {value!r}")
    if len(os.fsencode(value)) > MAX_SOCKET_PATH:
        raise _Bad(f"is longer than a Unix socket's path may be ({MAX_SOCKET_PATH} bytes)")
    return value


def admin_socket_path(settings, environ=None):
    """The administration socket's path: ``server.admin_socket``, else ``ROS_HOME/firos/admin-PORT.sock``
    (``ROS_HOME`` defaults to ``~/.ros``, as for ROS's own files); ConfigError when that is too long."""
    if settings.admin_socket:
        return settings.admin_socket
    environ = os.environ if environ is None else environ
    ros_home = environ.get("ROS_HOME") or os.path.join(os.path.expanduser("~"), ".ros")
    path = os.path.join(os.path.abspath(ros_home), "firos", f"admin-{settings.server_port}.sock")
    if len(os.fsencode(path)) > MAX_SOCKET_PATH:
        raise ConfigError(os.path.join(settings.config_dir, "config.json"),
                          f"the default administration socket {path} is longer than a Unix socket's path may "
                          f"be ({MAX_SOCKET_PATH} bytes): set server.admin_socket")
    return path


def _service_path(value):
    value = _text("a non-empty string")(value)
    if not value.startswith("/"):
        raise _Bad("must start with \"/\"")
    return value


# Every key of the environment block: (path inside the block, Settings field, parser). Keys listed twice are
# alternatives, the later place winning. contextbroker.address is required; the rest default to Settings'.
KEYS = (
    (("server", "port"), "server_port", _port),
    (("server", "address"), "server_addresses", _addresses),
    (("server", "admin_token"), "admin_token", _token),
    (("server", "admin_socket"), "admin_socket", _socket_path),
    (("contextbroker", "address"), "broker_address", _text("a host name or address")),
    (("contextbroker", "port"), "broker_port", _port),
    (("contextbroker", "max_request_size"), "max_request_size", _size),
    (("contextbroker", "subscription", "throttling"), "throttling", _duration),
    (("contextbroker", "subscription", "subscription_length"), "subscription_length", _duration),
    (("contextbroker", "subscription", "subscription_refresh_delay"), "subscription_refresh_delay",
     _refresh_delay),
    (("interface",), "interface", _text("\"public\" or an interface name")),
    (("endpoint", "address"), "endpoint_address", _text("a host name or address")),
    (("endpoint", "port"), "endpoint_port", _port),
    (("log_level",), "log_level", _log_level),
    (("ngsi_version",), "ngsi_version", _ngsi_version),
    (("ld_context",), "ld_context", _url),
    (("context_type",), "context_type", _type_name),
    (("pub_frequency",), "pub_frequency", _non_negative),
    (("discovery_interval",), "discovery_interval", _non_negative),
    (("retry_max_delay",), "retry_max_delay", _non_negative),
    (("contextbroker", "fiware_service"), "fiware_service", _text("a non-empty string")),
    (("fiware_service",), "fiware_service", _text("a non-empty string")),
    (("contextbroker", "fiware_servicepath"), "fiware_servicepath", _service_path),
    (("fiware_servicepath",), "fiware_servicepath", _service_path),
)


def _lookup(block, keys, path, where):
    """(True, value) when the block holds the dotted key, (False, None) when not; ConfigError when some part on
    the way is not an object."""
    node = block
    for depth, key in enumerate(keys):
        if not isinstance(node, dict):
            raise ConfigError(path, f"{where}{'.'.join(keys[:depth])} must be a JSON object")
        if key not in node:
            return False, None
        node = node[key]
    return True, node


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
    where = f"{env}."
    if not isinstance(block.get("contextbroker"), dict):
        raise ConfigError(path, f"{where}contextbroker is missing (it needs at least \"address\")")
    settings = Settings(config_dir=config_dir, environment=env)
    given = set()
    for keys, field_name, parse in KEYS:
        present, value = _lookup(block, keys, path, where)
        if not present:
            continue
        try:
            setattr(settings, field_name, parse(value))
        except _Bad as exc:
            raise ConfigError(path, f"{where}{'.'.join(keys)} {exc}") from None
        given.add(field_name)
    if "broker_address" not in given:
        raise ConfigError(path, f"{where}contextbroker.address is missing or empty")
    sub_where = f"{where}contextbroker.subscription."
    if settings.subscription_length < 1:
        raise ConfigError(path, f"{sub_where}subscription_length must be at least one second")
    if "subscription_refresh_delay" not in given:
        settings.subscription_refresh_delay = settings.subscription_length / 2
    elif settings.subscription_refresh_delay < 0:
        settings.subscription_refresh_delay *= -settings.subscription_length
    if not 0 < settings.subscription_refresh_delay < settings.subscription_length:
        raise ConfigError(path, f"{sub_where}subscription_refresh_delay must be above zero and below "
                                f"subscription_length, so that subscriptions are refreshed before they expire")
    if settings.retry_max_delay < 0.1:
        raise ConfigError(path, f"{where}retry_max_delay must be at least 0.1 seconds")
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
