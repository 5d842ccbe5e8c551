"""The agent's configuration: ``Config``, its keys and their parsers, loading the files, and derived addresses.

This is the package's bottom layer: it imports no other module of ``rcm_platform``, so any module may take a
``Config`` (and tests build real ones with ``make_config``). Owns:

- ``Config``: every ``[main]`` key of CONTRACTS §1 and the (ext) ones, one field each. A key's default is its
  field's default, written once here; the two defaults that depend on the role (``name``: ``master`` on the
  master; ``inbound_open_ports``: ``MASTER_DEFAULT_PORTS`` on the master, none elsewhere) are ``make_config``'s.
  Nobody else repeats a default (no ``getattr(config, key, default)``): code reads ``config.key``.
- ``KEYS``: key -> (parser, roles that may set it). A new key is one field of ``Config`` and one entry here
  (with its parser, if none of the ones below fits).
- ``load_config(home)``: ``HOME/init.cfg`` (a robot, ``robot=yes``, or a server VM, ``robot=no``) or, when it is
  absent, the master's optional ``HOME/.init.cfg``; ``ConfigError`` is one line naming the file, the key and
  the problem (the agent exits 2 with it).
- derived addresses: ``platform_address`` (the agent's VPN address: ``vpn_address`` or ``vpn_interface``'s),
  ``rdapi_address`` (the master's RDAPI address: ``ext_address`` or ``ext_interface``'s), looked up with
  netifaces, and ``master_address_from`` (a robot's default ``ip_master``: its own address with the last octet 1).
- the platform's name rule (``NAME_RE``, ``MAX_NAME_LENGTH``, ``is_name``): an instance's configured ``name`` and
  every name the RDAPI takes follow it (``rcmp_command.validate_name`` applies it to user input);
- the platform folder's checks (``folder_problem``: missing, a file or another kind, unreachable, not readable, not
  writable where the command writes) and the exit statuses every ``rcmp_n`` command uses (``EXIT_OK``,
  ``EXIT_FAILED``, ``EXIT_USAGE``, ``EXIT_MISSING``; ``EXIT_STATUSES`` is the text ``--help`` shows);
- where ROS is (``ros_setup_script``): the ROS installation's setup script by the rule ``sub_inst.sh ros-setup``
  holds for the installer: ``ros_setup`` (a file, or ``none``), else the first ``/opt/ros/*/setup.bash``
  (``noetic`` first), else none, which means ROS on the system's paths as Debian's packages put it.
  ``rcmp_service_item.ros_environment`` runs the script; this module only says which one.
"""

from __future__ import annotations

import configparser
import dataclasses
import glob
import ipaddress
import os
import pwd
import re
import socket
import stat
from typing import Optional

AGENT_ROLES = ("master", "robot", "server")
DEFAULT_LOG_MAX_BYTES = 1024 * 1024
MASTER_DEFAULT_PORTS = (10100, 10101, 10102, 10103)
SERVER_STARTING_SPACES = 4   # spaces the master builds at once on a server VM whose hello does not say how many


def default_max_starting_spaces():
    """Service spaces an agent builds at once unless ``max_starting_spaces`` says otherwise: two per core of its
    own machine, at least 2 (the master's count for the spaces it hosts; what a server VM announces in its hello)."""
    return max(2, 2 * (os.cpu_count() or 1))


MAX_NAME_LENGTH = 64
NAME_RE = re.compile(r"[A-Za-z][A-Za-z0-9_]*\Z")


def is_name(value):
    """True when ``value`` follows the platform's name rule: a letter, then letters, digits and underscores, at
    most ``MAX_NAME_LENGTH`` characters (ROS graph names without slashes)."""
    return isinstance(value, str) and 0 < len(value) <= MAX_NAME_LENGTH and NAME_RE.match(value) is not None


class ConfigError(Exception):
    """A configuration problem; ``str()`` is one line naming the file, the key and the problem."""


# -- exit statuses of every rcmp_n command (the agent, vpn, token) --------------------------------------------------

EXIT_OK = 0        # done (the agent: stopped by SIGTERM or SIGINT)
EXIT_FAILED = 1    # asked rightly, but it could not be done now: the state forbids it or the system refused
EXIT_USAGE = 2     # bad usage or configuration: command line, configuration file, platform folder
EXIT_MISSING = 3   # a package the command needs is not installed: the line names it
EXIT_STATUSES = ("Exit status: 0 done (the agent: stopped by SIGTERM or SIGINT); 1 it could not be done (a name "
                 "that exists already or is unknown, a port taken, a write refused: nothing was changed); 2 bad "
                 "usage or configuration (the command line, the configuration file, the platform folder: missing, "
                 "not a folder, not readable or writable, of the wrong role, holding damaged files); 3 a package "
                 "the command needs is not installed (the line names it). Errors are one line on stderr.")


# -- the platform folder --------------------------------------------------------------------------------------------

_KINDS = ((stat.S_ISREG, "a file"), (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
          (stat.S_ISFIFO, "a named pipe"), (stat.S_ISSOCK, "a socket"))


def _user():
    try:
        return pwd.getpwuid(os.geteuid()).pw_name
    except KeyError:
        return f"uid {os.geteuid()}"


def _owner_mode(path):
    try:
        st = os.stat(path)
    except OSError:
        return ""
    try:
        owner = pwd.getpwuid(st.st_uid).pw_name
    except KeyError:
        owner = f"uid {st.st_uid}"
    return f" (owner {owner}, mode {stat.S_IMODE(st.st_mode):04o})"


def _blocking_parent(path):
    """The first folder on the way to ``path`` that is not a folder or cannot be entered: (path, sentence)."""
    current = os.sep
    for part in [p for p in path.split(os.sep) if p][:-1]:
        current = os.path.join(current, part)
        try:
            st = os.stat(current)
        except FileNotFoundError:
            return current, "does not exist"
        except OSError:
            continue
        if not stat.S_ISDIR(st.st_mode):
            kind = next((name for test, name in _KINDS if test(st.st_mode)), "not a folder")
            return current, f"is {kind}, not a folder"
        if not os.access(current, os.X_OK):
            return current, f"cannot be entered by user {_user()}{_owner_mode(current)}"
    return None, None


def folder_problem(path, write=False, what="the platform folder"):
    """Why ``path`` cannot serve as ``what`` (a sentence naming it, to follow ``path: ``), or None when it can:
    it does not exist, is a file (or another kind), lies below a file or a folder that cannot be entered, cannot
    be read, or (``write``) cannot be written by this user or lies on a read-only file system."""
    path = os.path.abspath(path)
    try:
        st = os.stat(path)
    except FileNotFoundError:
        if os.path.islink(path):
            return f"{what} is a symbolic link to {os.readlink(path)!r}, which does not exist"
        parent, why = _blocking_parent(path)
        if parent is not None and why != "does not exist":
            return f"{what} cannot exist: {parent} {why}"
        return f"{what} does not exist"
    except (NotADirectoryError, PermissionError) as exc:
        parent, why = _blocking_parent(path)
        verb = "cannot exist" if isinstance(exc, NotADirectoryError) else "cannot be reached"
        return f"{what} {verb}: {parent} {why}" if parent else f"{what} {verb}"
    except OSError as exc:
        return f"{what} cannot be looked at: {exc.strerror or exc}"
    if not stat.S_ISDIR(st.st_mode):
        kind = next((name for test, name in _KINDS if test(st.st_mode)), "not a folder")
        return f"{what} is {kind}, not a folder"
    if not os.access(path, os.R_OK | os.X_OK):
        return f"{what} cannot be read by user {_user()}{_owner_mode(path)}"
    if write and not os.access(path, os.W_OK):
        try:
            read_only = bool(os.statvfs(path).f_flag & os.ST_RDONLY)
        except OSError:
            read_only = False
        if read_only:
            return f"{what} is on a read-only file system"
        return f"{what} cannot be written by user {_user()}{_owner_mode(path)}"
    return None


@dataclasses.dataclass
class Config:
    home: str
    role: str                          # "master" | "robot" | "server"
    config_file: Optional[str]         # HOME/init.cfg, HOME/.init.cfg or None
    name: str
    ip_master: Optional[str] = None    # robot, server: the master's VPN address (load_config derives a default)
    inbound_open_ports: list = dataclasses.field(default_factory=list)   # the master's default: make_config
    vpn_interface: str = "tun0"
    vpn_address: Optional[str] = None
    ext_interface: str = "eth0"
    ext_address: Optional[str] = None
    ext_port: int = 80
    ic_port: int = 9999
    ros_port_base: int = 11311
    heartbeat_interval: float = 2.0    # (ext) seconds between heartbeats
    heartbeat_misses: int = 3          # (ext) missed beats before a peer is gone
    log_max_bytes: int = DEFAULT_LOG_MAX_BYTES   # (ext) size at which rcmp.log rolls over
    rdapi_tls_cert: Optional[str] = None  # (ext) master: PEM certificate (chain): the RDAPI speaks HTTPS
    rdapi_tls_key: Optional[str] = None   # (ext) master: its PEM private key
    allowed_origins: tuple = ()        # (ext) master: origins of web pages that may write to the RDAPI
    run_as: Optional[str] = None       # (ext) the user service items run as (default: the workspace's owner)
    max_starting_spaces: Optional[int] = None    # (ext) service spaces this machine builds at once (None: 2 per core)
    ic_max_connections: Optional[int] = None     # (ext) agent-port connections (None: a quarter of the fd limit,
                                                 # which the agent raises to the hard limit at start)
    ic_max_per_address: Optional[int] = None     # (ext) agent-port connections from one address (None: 8)
    max_service_spaces: int = 100      # (ext) master, server VM: service spaces it hosts at most (0: none)
    servers: Optional[dict] = None     # (ext) master: server VM names allowed (name -> its only address, or None);
                                       # None: no list (any name that is not a robot's; with a managed VPN, server
                                       # certificates); {}: no server VM at all
    ros_setup: Optional[str] = None    # (ext) a setup script's absolute path, or "none"; None: ros_setup_script's rule


def make_config(role, home, config_file=None, **values):
    """A ``Config`` for ``role`` with that role's defaults under ``values`` (what ``load_config`` gives for a file
    holding just those keys, without reading anything): ``name`` defaults to ``master`` on the master (a robot's
    or server's must be given: ``load_config`` takes the host name), ``inbound_open_ports`` to
    ``MASTER_DEFAULT_PORTS`` on the master and to none elsewhere. TypeError for a key ``Config`` does not have."""
    if role not in AGENT_ROLES:
        raise ValueError(f"role must be one of {', '.join(AGENT_ROLES)}, not {role!r}")
    if role == "master":
        values.setdefault("name", "master")
        values.setdefault("inbound_open_ports", list(MASTER_DEFAULT_PORTS))
    return Config(home=home, role=role, config_file=config_file, **values)


# -- parsers: text of a key -> its value, ValueError with the problem ---------------------------------------------

def _parse_port(value):
    try:
        port = int(value, 10)
    except ValueError:
        raise ValueError(f"not a port number: {value!r}") from None
    if not 1 <= port <= 65535:
        raise ValueError(f"not a port number (1-65535): {value!r}")
    return port


def _parse_ports(value):
    ports = []
    for part in value.split(","):
        part = part.strip()
        if not part:
            continue
        port = _parse_port(part)
        if port in ports:
            raise ValueError(f"port {port} is listed twice: {value!r}")
        ports.append(port)
    return ports


def _parse_bool(value):
    lowered = value.strip().lower()
    if lowered in ("yes", "true", "on", "1"):
        return True
    if lowered in ("no", "false", "off", "0"):
        return False
    raise ValueError(f"expected yes or no: {value!r}")


def _parse_ipv4(value):
    try:
        return str(ipaddress.IPv4Address(value.strip()))
    except ValueError:
        raise ValueError(f"not an IPv4 address: {value!r}") from None


def _parse_name(value):
    value = value.strip()
    if not is_name(value):
        raise ValueError(f"not a valid instance name (a letter, then letters, digits and underscores, "
                         f"at most {MAX_NAME_LENGTH}): {value!r}")
    return value


def _parse_interface(value):
    value = value.strip()
    if not value or len(value) > 15 or "/" in value or any(c.isspace() for c in value):
        raise ValueError(f"not a network interface name: {value!r}")
    return value


def _parse_positive_float(value):
    try:
        number = float(value)
    except ValueError:
        raise ValueError(f"not a number: {value!r}") from None
    if not 0 < number < 3600:
        raise ValueError(f"must be more than 0 and less than 3600 seconds: {value!r}")
    return number


def _int_parser(minimum, maximum):
    def parse(value):
        try:
            number = int(value, 10)
        except ValueError:
            raise ValueError(f"not a whole number: {value!r}") from None
        if not minimum <= number <= maximum:
            raise ValueError(f"must be between {minimum} and {maximum}: {value!r}")
        return number
    return parse


def _parse_path(value):
    value = value.strip()
    if not value or not os.path.isabs(value) or "\x00" in value:
        raise ValueError(f"not an absolute file path: {value!r}")
    return value


def _parse_ros_setup(value):
    value = value.strip()
    if value == "none":
        return value
    try:
        return _parse_path(value)
    except ValueError:
        raise ValueError(f"neither none nor the absolute path of a setup script (like "
                         f"/opt/ros/noetic/setup.bash): {value!r}") from None


def _parse_origins(value):
    origins = []
    for part in value.split(","):
        part = part.strip()
        if not part:
            continue
        if not re.match(r"https?://[A-Za-z0-9.-]+(:[0-9]{1,5})?\Z|https?://\[[0-9A-Fa-f:.]+\](:[0-9]{1,5})?\Z",
                        part):
            raise ValueError(f"not an origin (scheme://host or scheme://host:port, scheme http or https, no "
                             f"path): {part!r}")
        origins.append(part.lower())
    return tuple(origins)


def _parse_servers(value):
    """``vm1, vm2@198.51.100.7``: the names of the server VMs that may join, each optionally with the one address
    its hello must come from; an empty value lets none join."""
    servers = {}
    for part in value.split(","):
        part = part.strip()
        if not part:
            continue
        name, at, address = part.partition("@")
        name = _parse_name(name)
        if name in servers:
            raise ValueError(f"server {name} is listed twice: {value[:200]!r}")
        servers[name] = _parse_ipv4(address) if at else None
    return servers


def _parse_user(value):
    value = value.strip()
    if not re.match(r"[a-z_][a-z0-9_-]{0,31}\Z", value):
        raise ValueError(f"not a user name (lower-case letters, digits, _ and -, at most 32): {value!r}")
    return value


# key -> (parser, roles that may set it); every key but ``robot`` is a field of Config
KEYS = {
    "name": (_parse_name, AGENT_ROLES),
    "robot": (_parse_bool, ("robot", "server")),
    "ip_master": (_parse_ipv4, ("robot", "server")),
    "inbound_open_ports": (_parse_ports, AGENT_ROLES),
    "vpn_interface": (_parse_interface, AGENT_ROLES),
    "vpn_address": (_parse_ipv4, AGENT_ROLES),
    "ext_interface": (_parse_interface, ("master",)),
    "ext_address": (_parse_ipv4, ("master",)),
    "ext_port": (_parse_port, ("master",)),
    "ic_port": (_parse_port, AGENT_ROLES),
    "ros_port_base": (_parse_port, ("master", "server")),
    "heartbeat_interval": (_parse_positive_float, AGENT_ROLES),
    "heartbeat_misses": (_int_parser(1, 1000), AGENT_ROLES),
    "log_max_bytes": (_int_parser(1024, 1024 ** 3), AGENT_ROLES),
    "rdapi_tls_cert": (_parse_path, ("master",)),
    "rdapi_tls_key": (_parse_path, ("master",)),
    "allowed_origins": (_parse_origins, ("master",)),
    "max_starting_spaces": (_int_parser(1, 1000), ("master", "server")),
    "max_service_spaces": (_int_parser(0, 100000), ("master", "server")),
    "ic_max_connections": (_int_parser(1, 100000), ("master",)),
    "ic_max_per_address": (_int_parser(1, 10000), ("master",)),
    "run_as": (_parse_user, AGENT_ROLES),
    "servers": (_parse_servers, ("master",)),
    "ros_setup": (_parse_ros_setup, AGENT_ROLES),
}


# -- loading ------------------------------------------------------------------------------------------------------

def _read_file(path):
    parser = configparser.ConfigParser(interpolation=None, strict=True, inline_comment_prefixes=None)
    parser.optionxform = str  # keys are case-sensitive, as written in the seed
    try:
        with open(path, encoding="utf-8") as f:
            parser.read_file(f)
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a UTF-8 text file") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None
    except configparser.MissingSectionHeaderError as exc:
        raise ConfigError(f"{path}: line {exc.lineno}: a key before the [main] section") from None
    except configparser.DuplicateOptionError as exc:
        raise ConfigError(f"{path}: key '{exc.option}': given twice") from None
    except configparser.DuplicateSectionError as exc:
        raise ConfigError(f"{path}: section [{exc.section}] given twice") from None
    except configparser.Error as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ConfigError(f"{path}: {first}") from None
    sections = parser.sections()
    if "main" not in sections:
        raise ConfigError(f"{path}: no [main] section")
    for section in sections:
        if section != "main":
            raise ConfigError(f"{path}: unknown section [{section}] (only [main] is read)")
    return dict(parser.items("main"))


def _host_name():
    return socket.gethostname().split(".")[0]


def load_config(home):
    """Read and validate the configuration of the agent living in ``home``; raise ConfigError on any problem."""
    home = os.path.abspath(home)
    problem = folder_problem(home)
    if problem:
        raise ConfigError(f"{home}: {problem}")
    robot_file = os.path.join(home, "init.cfg")
    master_file = os.path.join(home, ".init.cfg")
    if os.path.exists(robot_file):
        path, raw = robot_file, _read_file(robot_file)
        try:
            is_robot = _parse_bool(raw["robot"]) if "robot" in raw else True
        except ValueError as exc:
            raise ConfigError(f"{path}: key 'robot': {exc}") from None
        role = "robot" if is_robot else "server"
    else:
        role = "master"
        path = master_file if os.path.exists(master_file) else None
        raw = _read_file(master_file) if path else {}

    values = {}
    for key, text in raw.items():
        if key not in KEYS:
            raise ConfigError(f"{path}: unknown key '{key}'")
        parser, roles = KEYS[key]
        if role not in roles:
            what = {"master": "the master", "robot": "a robot", "server": "a server VM"}[role]
            raise ConfigError(f"{path}: key '{key}': not used by {what}")
        try:
            values[key] = parser(text)
        except ValueError as exc:
            raise ConfigError(f"{path}: key '{key}': {exc}") from None
    values.pop("robot", None)

    if "name" not in values and role != "master":
        host = _host_name()
        try:
            values["name"] = _parse_name(host)
        except ValueError:
            raise ConfigError(f"{path}: key 'name': not set, and the host name {host!r} is not a valid "
                              f"instance name: set name=") from None
    config = make_config(role, home, path, **values)
    if config.role == "master":
        clash = {config.ext_port, config.ic_port} & set(config.inbound_open_ports)
        if config.ext_port == config.ic_port or clash:
            raise ConfigError(f"{path or master_file}: key 'ic_port': the ports ext_port, ic_port and "
                              f"inbound_open_ports must all differ")
    if config.role == "master" and (config.rdapi_tls_cert is None) != (config.rdapi_tls_key is None):
        given, missing = (("rdapi_tls_cert", "rdapi_tls_key") if config.rdapi_tls_cert
                          else ("rdapi_tls_key", "rdapi_tls_cert"))
        raise ConfigError(f"{path}: key '{missing}': needed with '{given}' (HTTPS needs a certificate and its key)")
    if config.role != "master" and config.ip_master is None:
        address = platform_address(config)
        if address is not None:
            config.ip_master = master_address_from(address)
    return config


# -- where ROS is --------------------------------------------------------------------------------------------------

ROS_ROOT = "/opt/ros"
PREFERRED_DISTRO = "noetic"


def ros_setup_script(config, search_root=ROS_ROOT):
    """(setup script or None, how it was chosen): ``ros_setup`` when set (None for ``none``), else the first
    ``search_root/*/setup.bash`` (``noetic`` first, then by name), else None: ROS is on the system's paths.
    The rule of ``sub_inst.sh ros-setup``, which the installer and the workspace build follow."""
    if config.ros_setup == "none":
        return None, "ros_setup=none"
    if config.ros_setup is not None:
        return config.ros_setup, "ros_setup"
    found = sorted(glob.glob(os.path.join(glob.escape(search_root), "*", "setup.bash")))
    preferred = os.path.join(search_root, PREFERRED_DISTRO, "setup.bash")
    for path in ([preferred] if preferred in found else []) + found:
        if os.path.isfile(path):
            return path, f"found in {search_root}"
    return None, f"no {search_root}/*/setup.bash"


# -- derived addresses --------------------------------------------------------------------------------------------

def master_address_from(own_address):
    """The master's address when ``ip_master`` is not set: the agent's own VPN address with the last octet 1
    (a robot whose address appears late, with the VPN, applies it when it says hello)."""
    parts = own_address.split(".")
    return ".".join(parts[:3] + ["1"])


def _interface_ipv4(interface):
    import netifaces   # without it, ImportError: rcmp_node says which package to install (rcmp_deps)
    try:
        addresses = netifaces.ifaddresses(interface).get(netifaces.AF_INET, [])
    except ValueError:
        return None
    for entry in addresses:
        if entry.get("addr"):
            return entry["addr"]
    return None


def platform_address(config):
    """The agent's platform (VPN) address: ``vpn_address``, or the IPv4 address of ``vpn_interface``, or None."""
    return config.vpn_address or _interface_ipv4(config.vpn_interface)


def rdapi_address(config):
    """The master's RDAPI address: ``ext_address``, or the IPv4 address of ``ext_interface``, or None."""
    return config.ext_address or _interface_ipv4(config.ext_interface)
