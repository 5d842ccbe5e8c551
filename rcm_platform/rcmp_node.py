"""The agent ``rcmp_n``: command line, logging, the agent's own files, and assembling the agent for its role.

Owns:
- the command line (``--home``, ``--log-level``, ``--no-stderr``, ``--help``, the ``vpn`` subcommand whose
  work is ``rcmp_vpn``'s, and ``rcmp_n token add NAME --role read|admin`` / ``token list`` / ``token revoke
  NAME``, which manage the RDAPI's tokens in the master's robotics data (the token is printed once; the agent
  need not be stopped)) and ``main()``: every command ends with one of the exit statuses of ``rcmp_config``
  (``EXIT_STATUSES``, shown by ``--help``) and every error is one line on stderr: a bad configuration or
  platform folder (``ConfigError``, ``folder_problem``) exit 2, a module that cannot be imported (anywhere in
  ``main``, ``--help`` included) or that the agent will need (``rcmp_deps.require``: ROS's loader, netifaces)
  the line ``rcmp_deps.missing_line`` gives, naming the package to install, exit 3;
- logging: ``HOME/log/rcmp.log`` rotating at ``log_max_bytes`` with 5 backups, plus stderr in the foreground;
  Twisted's own log goes to the same place;
- the agent's own files as root (issue 12): umask 027 (``UMASK``), older world-readable logs and data tightened
  (``tighten_files``); at start the ROS installation's environment (``ros_setup``,
  ``rcmp_service_item.apply_ros_environment``) and on top of it the catkin workspace named by ``RCMP_WS`` go
  into the agent's environment (``rcmp_service_item.apply_workspace``);
- the agent of each role as one Twisted ``MultiService`` (master: the MasterAgent, the console, the metrics
  (``rcmp_metrics``, served at ``/metrics``), then the RDAPI listener;
  robot and server VM: the RobotAgent), started when the reactor runs and stopped (in reverse order) on
  SIGTERM/SIGINT before the process exits 0. It builds the process table, the space runtime, the address
  function and the items' user (``rcmp_service_item.resolve_run_as``) and passes them in; before, it raises the
  open-file limit, and while the reactor runs it freezes the garbage collector's old objects
  (``rcmp_resources``).
"""

import argparse
import functools
import logging
import logging.handlers
import os
import signal
import sqlite3
import sys

from .rcmp_config import (EXIT_FAILED, EXIT_MISSING, EXIT_OK, EXIT_STATUSES, EXIT_USAGE, ConfigError,
                          folder_problem, load_config, platform_address, rdapi_address)
from .rcmp_log_guard import Budget, BudgetFilter

PROG = "rcmp_n"
DEFAULT_HOME = "/opt/rcm-platform"
LOG_BACKUPS = 5

log = logging.getLogger("rcm_platform")


# -- logging ----------------------------------------------------------------------------------------------------

def setup_logging(config, level=logging.INFO, to_stderr=True):
    """Log to HOME/log/rcmp.log (rotating, 5 backups) and, in the foreground, to stderr. Twisted's log too, through a
    ``rcmp_log_guard.Budget``: its lines about clients (timed out, broken) are ones any client can cause."""
    log_dir = os.path.join(config.home, "log")
    os.makedirs(log_dir, exist_ok=True)
    fmt = logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s")
    root = logging.getLogger()
    for handler in list(root.handlers):
        root.removeHandler(handler)
    file_handler = logging.handlers.RotatingFileHandler(
        os.path.join(log_dir, "rcmp.log"), maxBytes=config.log_max_bytes, backupCount=LOG_BACKUPS,
        encoding="utf-8")
    file_handler.setFormatter(fmt)
    root.addHandler(file_handler)
    if to_stderr:
        stream = logging.StreamHandler(sys.stderr)
        stream.setFormatter(fmt)
        root.addHandler(stream)
    root.setLevel(level)
    from twisted.logger import STDLibLogObserver, globalLogBeginner
    twisted_log = logging.getLogger("twisted")
    for old in [f for f in twisted_log.filters if isinstance(f, BudgetFilter)]:
        twisted_log.removeFilter(old)
    twisted_log.addFilter(BudgetFilter(Budget(twisted_log, "lines of Twisted's own log")))
    globalLogBeginner.beginLoggingTo([STDLibLogObserver(name="twisted")], redirectStandardIO=False)


# -- the agent's own files (it runs as root: CONTRACTS §10, docs/SECURITY.md) --------------------------------------

UMASK = 0o027   # the agent's files 0640, its folders 0750


def tighten_files(home):
    """Take group-write and every "others" bit off what the agent writes in ``home`` (its log folder and files,
    the robotics data), as left by an older version that wrote them 0644/0755."""
    log_dir = os.path.join(home, "log")
    paths = [log_dir] if os.path.isdir(log_dir) else []
    if paths:
        paths += [os.path.join(log_dir, n) for n in os.listdir(log_dir)
                  if os.path.isfile(os.path.join(log_dir, n))]
    paths += [os.path.join(home, n) for n in os.listdir(home) if n.startswith("robotics_data.db")] \
        if os.path.isdir(home) else []
    for path in paths:
        try:
            st = os.lstat(path)
            if not os.path.islink(path) and st.st_mode & 0o027:
                os.chmod(path, st.st_mode & 0o7750)
        except OSError:
            continue


# -- assembly ---------------------------------------------------------------------------------------------------

class StartupError(Exception):
    """The agent cannot start (no address, data file unusable, cannot listen); ``str()`` is one line."""


def _items_user(config):
    """``rcmp_service_item.resolve_run_as``, its refusal as a StartupError."""
    from .rcmp_service_item import RunAsError, resolve_run_as
    try:
        return resolve_run_as(config)
    except RunAsError as exc:
        raise StartupError(str(exc)) from None


def _top_service(config, reactor, table):
    """The agent's MultiService. With a table of its own: ``rcmp_process.TableService``, which stops whatever the
    agent left in the table once the agent has stopped (``top.table``). Given the managed VPN's table
    (``build_agent``): a plain MultiService, the outer TableService stops that table after the VPN."""
    from twisted.application import service
    from . import rcmp_process
    if table is not None:
        top = service.MultiService()
        top.table = table
        return top
    return rcmp_process.TableService(rcmp_process.ProcessTable(reactor, os.path.join(config.home, "log")))


def build_master(config, reactor, table=None):
    """The master: robotics data, process table, MasterAgent, then the RDAPI listener, as one MultiService."""
    from . import rcmp_console, rcmp_event, rcmp_metrics, rcmp_ms, rcmp_vpn
    from .rcmp_command import CommandError
    from .rcmp_ext_connector import TlsError, Tokens, make_site, rdapi_service, tls_options
    from .rcmp_platform_command import PlatformCommands
    from .rcmp_robotics_data import DataError, RoboticsData
    from .rcmp_service_command import ServiceCommands

    where = config.config_file or os.path.join(config.home, ".init.cfg")
    vpn = platform_address(config)
    if vpn is None:
        raise StartupError(f"{where}: no IPv4 address on the VPN interface '{config.vpn_interface}' "
                           f"(is the VPN up? or set vpn_address)")
    public_ip = rdapi_address(config)
    if public_ip is None:
        raise StartupError(f"{where}: no IPv4 address on the external interface '{config.ext_interface}' "
                           f"(set ext_interface or ext_address)")
    try:
        data = RoboticsData(os.path.join(config.home, "robotics_data.db"))
        data.set_master(config.name, vpn, config.inbound_open_ports)
    except (DataError, CommandError) as exc:
        raise StartupError(str(exc)) from None
    tls = None
    if config.rdapi_tls_cert:
        try:
            tls = tls_options(config.rdapi_tls_cert, config.rdapi_tls_key)
        except TlsError as exc:
            raise StartupError(f"{where}: keys 'rdapi_tls_cert'/'rdapi_tls_key': {exc}") from None
    run_as = _items_user(config)
    top = _top_service(config, reactor, table)
    table = top.table
    address = functools.partial(platform_address, config)
    spaces = rcmp_ms.ServiceSpaceManager(reactor, table, config, public_ip, address=address, run_as=run_as)
    agent = rcmp_event.MasterAgent(config, data, table, reactor, public_ip, spaces=spaces, address=address,
                                   certificate_of=lambda name: rcmp_vpn.certificate_of(config.home, name))
    tokens = Tokens(data, reactor)
    platform = PlatformCommands(data, robots=agent)
    console = rcmp_console.Console(reactor, data, platform, agent.spaces, table, describe=agent.describe)
    metrics = rcmp_metrics.make_metrics(agent, spaces, platform)   # without prometheus_client: /metrics says so
    site = make_site(platform, ServiceCommands(data, spaces=agent), tokens=tokens,
                     allowed_origins=config.allowed_origins, console=rcmp_console.ConsoleResource(console),
                     metrics=metrics)
    metrics.watch_site(site)
    agent.setServiceParent(top)
    rcmp_console.ConsoleService(console).setServiceParent(top)
    metrics.setServiceParent(top)  # its hooks are in place before the first hello and the first request
    tokens.setServiceParent(top)   # loaded before the listener starts: never open by mistake
    rdapi_service(site, config.ext_port, public_ip, reactor=reactor, tls=tls).setServiceParent(top)
    top.rdapi_address = (public_ip, config.ext_port)
    top.rdapi_scheme = "https" if tls else "http"
    return top


def build_robot(config, reactor, table=None):
    """A robot or a server VM: the RobotAgent as one MultiService."""
    from . import rcmp_event, rcmp_ms
    run_as = _items_user(config)
    top = _top_service(config, reactor, table)
    table = top.table
    address = functools.partial(platform_address, config)
    runner = rcmp_ms.ItemRunner(reactor, table, config, address=address, run_as=run_as)
    agent = rcmp_event.RobotAgent(config, table, reactor, runner=runner, address=address)
    agent.setServiceParent(top)
    return top


def build_agent(config, reactor, on_error=None):
    """The agent of ``config.role`` as one MultiService (not started yet); StartupError if it cannot be built.

    With a managed VPN (``rcmp_vpn.managed_config``) the MultiService holds OpenVPN first (stopped last) and the
    agent, built once the VPN gave the agent its address; ``on_error(message)`` is told if that build fails.
    """
    from . import rcmp_process, rcmp_vpn
    build = build_master if config.role == "master" else build_robot
    conf = rcmp_vpn.managed_config(config)
    if conf is None:
        return build(config, reactor)
    table = rcmp_process.ProcessTable(reactor, os.path.join(config.home, "log"))
    top = rcmp_process.TableService(table)   # stops what the VPN and the agent left, after both stopped
    vpn = rcmp_vpn.ManagedVpn(config, conf, table, reactor, lambda: platform_address(config))
    rcmp_vpn.VpnFirst(vpn, rcmp_vpn.AfterVpn(vpn, lambda: build(config, reactor, table),
                                             on_error or log.error)).setServiceParent(top)
    return top


# -- main -------------------------------------------------------------------------------------------------------

def parse_args(argv):
    parser = argparse.ArgumentParser(
        prog=PROG,
        description="The RCM platform agent. With HOME/init.cfg it runs as a robot (robot=yes) or a server VM "
                    "(robot=no); without it, as the master (optional HOME/.init.cfg) serving the RDAPI. Runs in "
                    "the foreground until SIGTERM or SIGINT, then stops everything it started.",
        epilog="'rcmp_n token add NAME --role read|admin', 'rcmp_n token list' and 'rcmp_n token revoke NAME' "
               "manage the RDAPI's bearer tokens on the master (docs/SECURITY.md). " + EXIT_STATUSES)
    home_help = ("the platform folder: configuration, robotics_data.db, log/ "
                 f"(default: $RCMP_HOME, else {DEFAULT_HOME})")
    parser.add_argument("--home", metavar="DIR", default=os.environ.get("RCMP_HOME", DEFAULT_HOME), help=home_help)
    parser.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"],
                        help="the lowest level written to the log (default: INFO)")
    parser.add_argument("--no-stderr", action="store_true",
                        help="log only to HOME/log/rcmp.log, not to stderr (for running as a daemon)")
    from . import rcmp_vpn
    from .rcmp_command import TOKEN_ROLES
    commands = parser.add_subparsers(dest="command", metavar="COMMAND",
                                     help="without a command, run the agent; 'vpn' manages the platform's VPN "
                                          "('rcmp_n vpn --help'), 'token' the RDAPI's tokens ('rcmp_n token --help')")
    rcmp_vpn.add_parser(commands, DEFAULT_HOME)
    token = commands.add_parser("token", help="manage the RDAPI's bearer tokens (master only): add, list, revoke",
                                description="The RDAPI's bearer tokens. Once one exists, every RDAPI call but "
                                            "GET / needs 'Authorization: Bearer TOKEN'; only a hash is kept.",
                                epilog=EXIT_STATUSES)
    actions = token.add_subparsers(dest="token_command", metavar="add|list|revoke", required=True)
    add = actions.add_parser("add", help="make a token and print it (once: only its hash is kept)",
                             epilog=EXIT_STATUSES)
    add.add_argument("name", metavar="NAME", help="the token's name (a letter, then letters, digits, _)")
    add.add_argument("--role", required=True, choices=TOKEN_ROLES,
                     help="read: GET calls only; admin: every call")
    actions.add_parser("list", help="list the tokens (name, role, when made)", epilog=EXIT_STATUSES)
    revoke = actions.add_parser("revoke", help="forget a token; the running agent refuses it within a second",
                                epilog=EXIT_STATUSES)
    revoke.add_argument("name", metavar="NAME")
    for sub in (token, add, revoke, actions.choices["list"]):
        sub.add_argument("--home", metavar="DIR", default=argparse.SUPPRESS, help=home_help)
    return parser.parse_args(argv)


def token_command(args):
    """``rcmp_n token add|list|revoke``: the RDAPI's tokens in HOME/robotics_data.db; returns the exit status."""
    from .rcmp_command import CommandError, validate_name
    from .rcmp_ext_connector import new_token
    from .rcmp_robotics_data import DataError, RoboticsData
    try:
        config = load_config(args.home)
    except ConfigError as exc:
        return _fail(str(exc), EXIT_USAGE)
    if config.role != "master":
        return _fail(f"{config.config_file}: this is a robot's or server VM's folder; RDAPI tokens belong to the "
                     f"master", EXIT_USAGE)
    problem = folder_problem(config.home, write=args.token_command != "list")
    if problem:
        return _fail(f"{config.home}: {problem}", EXIT_USAGE)
    os.umask(0o027)  # a new robotics_data.db is not readable by others
    try:
        data = RoboticsData(os.path.join(config.home, "robotics_data.db"), forget_live_state=False)
    except DataError as exc:       # a file that is not robotics data: the folder's problem
        return _fail(str(exc).splitlines()[0], EXIT_USAGE)
    except sqlite3.Error as exc:
        return _fail(str(exc).splitlines()[0], EXIT_FAILED)
    try:
        if args.token_command == "add":
            name = validate_name(args.name, "NAME")
            token, digest = new_token()
            data.add_token(name, args.role, digest)
            sys.stdout.write(token + "\n")
            sys.stderr.write(f"{PROG}: token '{name}' ({args.role}) added; it is shown only this once: send it as "
                             f"'Authorization: Bearer TOKEN'\n")
        elif args.token_command == "list":
            rows = data.tokens()
            if not rows:
                sys.stdout.write("no tokens: the RDAPI is open to anyone who can reach it\n")
            for row in rows:
                sys.stdout.write(f"{row['name']}\t{row['role']}\t{row['created']} UTC\n")
        else:
            name = validate_name(args.name, "NAME")
            data.revoke_token(name)
            left = len(data.tokens())
            sys.stderr.write(f"{PROG}: token '{name}' revoked" +
                             ("" if left else "; no token is left, so the RDAPI is open again") + "\n")
    except CommandError as exc:
        return _fail(str(exc), EXIT_USAGE if exc.status == 400 else EXIT_FAILED)
    except sqlite3.Error as exc:
        return _fail(f"{data.path}: {exc}", EXIT_FAILED)
    finally:
        data.close()
    return EXIT_OK


def _log_to_file_only(message):
    """Record a fatal error in rcmp.log without repeating it on stderr (stderr gets exactly one line)."""
    root = logging.getLogger()
    for handler in list(root.handlers):
        if type(handler) is logging.StreamHandler:
            root.removeHandler(handler)
    log.error("%s", message)


def _fail(message, status):
    sys.stderr.write(f"{PROG}: {message}\n")
    return status


def _vpn_default_remote(home):
    """The address client files name by default (``rcmp_n vpn init`` without --remote): ``ext_interface``'s."""
    from . import rcmp_vpn
    try:
        config = load_config(home)
    except ConfigError as exc:
        raise rcmp_vpn.VpnError(str(exc), EXIT_USAGE) from None
    remote = rdapi_address(config)
    if remote is None:
        raise rcmp_vpn.VpnError(f"no IPv4 address on the external interface '{config.ext_interface}' to put in "
                                f"client files: give --remote HOST", EXIT_USAGE)
    return remote


def main(argv=None):
    """Run the command (the agent without one); returns its exit status (``rcmp_config.EXIT_STATUSES``)."""
    try:
        return _main(sys.argv[1:] if argv is None else argv)
    except ImportError as exc:   # Twisted, cryptography, ...: one line naming the package, also for --help
        from . import rcmp_deps
        return _fail(rcmp_deps.missing_line(exc), EXIT_MISSING)


def _written_folder(config):
    """The folder the agent writes first (the master: the platform folder, for robotics_data.db; the others: log/,
    or the platform folder while log/ does not exist) and why it cannot, or (None, None)."""
    log_dir = os.path.join(config.home, "log")
    if config.role != "master" and os.path.lexists(log_dir):
        return log_dir, folder_problem(log_dir, write=True, what="the agent's log folder")
    return config.home, folder_problem(config.home, write=True)


def _agent_needs(config):
    """The modules the agent imports late (ROS's launch-file loader, netifaces for an interface's address, pyOpenSSL
    for an RDAPI over HTTPS): checked at start, so that a missing one is one line now rather than a failing item,
    or an agent that stops after its VPN came up, later."""
    from . import rcmp_deps
    needs = list(rcmp_deps.ROS_MODULES)
    if config.vpn_address is None or (config.role == "master" and config.ext_address is None):
        needs.append("netifaces")
    if config.role == "master" and config.rdapi_tls_cert:
        needs.append("OpenSSL")
    return needs


def _main(argv):
    args = parse_args(argv)
    os.umask(UMASK)
    if args.command == "vpn":
        from . import rcmp_vpn
        return rcmp_vpn.run(args, default_remote=_vpn_default_remote)
    if args.command == "token":
        return token_command(args)
    try:
        config = load_config(args.home)
    except ConfigError as exc:
        return _fail(str(exc), EXIT_USAGE)
    folder, problem = _written_folder(config)
    if problem:
        return _fail(f"{folder}: {problem}", EXIT_USAGE)
    try:
        setup_logging(config, getattr(logging, args.log_level), to_stderr=not args.no_stderr)
    except OSError as exc:
        return _fail(f"{os.path.join(config.home, 'log')}: cannot write the log: {exc.strerror or exc}", EXIT_FAILED)
    tighten_files(config.home)
    from .rcmp_service_item import RosSetupError, apply_ros_environment, apply_workspace
    try:   # ROS first (the workspace chains onto it), before anything imports a ROS module
        apply_ros_environment(config, os.environ)
    except RosSetupError as exc:
        _log_to_file_only(f"cannot start: {exc}")
        return _fail(str(exc), EXIT_USAGE)
    apply_workspace(os.environ)
    from . import rcmp_deps
    try:
        rcmp_deps.require(_agent_needs(config))
    except rcmp_deps.MissingDependency as exc:
        _log_to_file_only(f"cannot start: {exc}")
        return _fail(str(exc), EXIT_MISSING)

    from twisted.internet import reactor
    from twisted.internet.error import ReactorNotRunning
    from . import rcmp_resources
    rcmp_resources.raise_open_files()    # before the agent port's cap is taken from the limit
    outcome = {"status": EXIT_OK}

    def late_error(message):  # the agent could not start once the managed VPN was up
        _log_to_file_only(f"cannot start: {message}")
        sys.stderr.write(f"{PROG}: cannot start the {config.role}: {message}\n")
        outcome["status"] = EXIT_USAGE
        try:
            reactor.stop()
        except ReactorNotRunning:
            pass

    try:
        top = build_agent(config, reactor, on_error=late_error)
    except StartupError as exc:
        _log_to_file_only(f"cannot start: {exc}")
        return _fail(str(exc), EXIT_USAGE)
    # after the imports (a fleet of agents starting at once on one machine should not import ahead of the
    # agents already serving), before any thread (niceness is per thread)
    from . import rcmp_process
    boost = rcmp_process.raise_agent_priority()
    if boost:
        log.info("rcmp_n runs %d nice levels above the processes it starts (they keep nice %d)", boost,
                 os.nice(0) + boost)

    def start():
        try:
            top.startService()
        except Exception as exc:  # cannot listen, or an agent refused to start: one line, then stop
            message = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            _log_to_file_only(f"cannot start: {message}")
            sys.stderr.write(f"{PROG}: cannot start the {config.role}: {message}\n")
            outcome["status"] = EXIT_FAILED
            try:
                reactor.stop()
            except ReactorNotRunning:  # a signal already began the shutdown
                pass
            return
        where = getattr(top, "rdapi_address", None)
        rdapi = (f", RDAPI on {top.rdapi_scheme}://{where[0]}:{where[1]}/, console on "
                 f"{top.rdapi_scheme}://{where[0]}:{where[1]}/console/") if where else ""
        log.info("rcmp_n started as %s '%s' in %s%s", config.role, config.name, config.home, rdapi)

    def stop():
        log.info("rcmp_n stopping")
        if top.running:
            return top.stopService()
        return None

    # a shell starting us in the background leaves SIGINT ignored; CONTRACTS §1 says SIGINT stops the agent, so
    # give it the default handler, which Twisted then replaces with its own (stop the reactor)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    reactor.callWhenRunning(start)
    reactor.callWhenRunning(rcmp_resources.GcFreezer(reactor).start)
    reactor.addSystemEventTrigger("before", "shutdown", stop)
    reactor.run()
    log.info("rcmp_n stopped")
    return outcome["status"]
