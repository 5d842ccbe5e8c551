#!/usr/bin/env python3
"""FIROS: maps the topics of ROS robots to entities of an NGSI context broker (Orion, or an NGSI-LD broker such as
Orion-LD) and broker commands back to ROS topics (CONTRACTS §3).
Run as `rosrun firos core.py [-P PORT] [--config DIR]`.

This file only assembles the node: command line, configuration (one clear line and exit 1 when it is wrong),
logging (stderr, /rosout and the node's ROS log file), the notification address, the listeners (the HTTP API on its
addresses and the administration socket, with the broker's addresses given a larger share), the parts in
`include/` and their metrics, the discovery loop in the main thread, and an orderly shutdown (subscriptions and
entities removed) on SIGINT/SIGTERM or a ROS shutdown.
"""

import argparse
import errno
import logging
import os
import signal
import socket
import sys
import threading

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from include.config import (PACKAGE_CONFIG_DIR, ConfigError, admin_socket_path,  # noqa: E402
                            load_descriptions, load_settings)
from include.whitelist import Whitelist  # noqa: E402

log = logging.getLogger("firos")


def parse_args(argv):
    parser = argparse.ArgumentParser(prog="core.py", description="FIROS: ROS robots as NGSI entities.")
    parser.add_argument("-P", "--port", type=int, help="HTTP server port (overrides server.port of config.json)")
    parser.add_argument("--config", metavar="DIR", default=PACKAGE_CONFIG_DIR,
                        help="configuration folder with config.json, whitelist.json, robotdescriptions.json "
                             "(default: the package's config/)")
    return parser.parse_args(argv)


def notification_address(settings):
    """(address, port) the broker sends notifications to: endpoint, else the configured interface's address."""
    port = settings.endpoint_port or settings.server_port
    if settings.endpoint_address:
        return settings.endpoint_address, port
    path = os.path.join(settings.config_dir, "config.json")
    if settings.interface == "public":
        from include.ngsi_client import local_address_towards
        try:
            return local_address_towards(settings.broker_address, settings.broker_port), port
        except OSError as exc:
            raise ConfigError(path, f"cannot find the address towards the broker {settings.broker_address}: "
                                    f"{exc}") from None
    import netifaces
    if settings.interface not in netifaces.interfaces():
        raise ConfigError(path, f"interface {settings.interface!r} does not exist on this machine")
    addresses = netifaces.ifaddresses(settings.interface).get(netifaces.AF_INET)
    if not addresses:
        raise ConfigError(path, f"interface {settings.interface!r} has no IPv4 address")
    return addresses[0]["addr"], port


def listen_addresses(settings, notify_host):
    """(required, optional) addresses of the HTTP API: ``server.address`` when configured; else the platform
    address the agent gives FIROS (``ROS_IP``), and, optionally (when it is an address of this machine), the
    address the broker is told to notify. Never a wildcard unless configured so."""
    if settings.server_addresses:
        return list(settings.server_addresses), []
    platform = os.environ.get("ROS_IP", "").strip()
    if not platform:
        return [notify_host], []
    return [platform], [] if notify_host == platform else [notify_host]


def broker_shares(settings, share):
    """{address: share} for the addresses the broker's name has now (none when it cannot be resolved): the
    broker's notifications come from there, and may take more connections than another address."""
    try:
        found = socket.getaddrinfo(settings.broker_address, settings.broker_port, proto=socket.IPPROTO_TCP)
    except (OSError, UnicodeError):
        return {}
    return {info[4][0]: share for info in found}


def open_servers(http, settings, notify_host, admin_socket):
    """The listening servers (the administration socket, at ``admin_socket``, last); OSError (its strerror naming
    the address or path) when a required one cannot be bound.

    A configured ``server.admin_socket`` another FIROS answers on stops FIROS. The default one (one per port and
    user, so one per FIROS on a machine) can be another FIROS's only where machines share a home folder (test
    hosts in network namespaces, two FIROS on two addresses with one port): then this FIROS takes
    ``admin-PORT-PID.sock`` beside it and says so in its log."""
    try:
        return _open_servers(http, settings, notify_host, admin_socket)
    except OSError as exc:
        if settings.admin_socket or exc.errno != errno.EADDRINUSE or admin_socket not in (exc.strerror or ""):
            raise
    taken, admin_socket = admin_socket, admin_socket[:-len(".sock")] + f"-{os.getpid()}.sock"
    log.warning("another FIROS answers on %s: this one's administration socket is %s", taken, admin_socket)
    return _open_servers(http, settings, notify_host, admin_socket)


def _open_servers(http, settings, notify_host, admin_socket):
    required, optional = listen_addresses(settings, notify_host)
    options = {"admin_token": settings.admin_token, "admin_socket": admin_socket,
               "shares": broker_shares(settings, http.BROKER_SHARE)}
    if optional:
        try:
            return http.make_servers(None, settings.server_port, required + optional, **options)
        except OSError as exc:
            if not (exc.strerror or "").startswith(f"{optional[0]}:"):
                raise
            log.info("not listening on %s too (%s): the broker's notifications reach FIROS only if they come "
                     "to %s", optional[0], exc.strerror, ", ".join(required))
    return http.make_servers(None, settings.server_port, required, **options)


def load(args):
    settings = load_settings(args.config)
    if args.port is not None:
        if not 0 < args.port < 65536:
            raise ConfigError("-P", f"{args.port} is not a TCP port number")
        settings.server_port = args.port
        if settings.endpoint_port is None:
            settings.endpoint_port = args.port
    whitelist = Whitelist.load(args.config)
    descriptions = load_descriptions(args.config)
    return settings, whitelist, descriptions


def setup_logging(level):
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("[%(levelname)s] [%(asctime)s] %(name)s: %(message)s"))
    log.addHandler(handler)
    log.setLevel({"WARN": "WARNING", "FATAL": "CRITICAL"}.get(level, level))
    log.propagate = False


def route_logs_to_ros():
    """After rospy.init_node: FIROS's log lines also go to /rosout (rqt_console, rosout.log) and to the node's
    own log file under ROS_LOG_DIR, as the seed's "Diagnosis procedures" expect of service nodes."""
    for handler in logging.getLogger("rosout").handlers:
        if type(handler).__name__ == "RosOutHandler":
            log.addHandler(handler)
    log.propagate = True     # the root logger holds rospy's file handler for this node's log file


def main(argv=None):
    import rospy
    argv = rospy.myargv(sys.argv if argv is None else argv)[1:]
    args = parse_args(argv)
    try:
        settings, whitelist, descriptions = load(args)
        address, port = notification_address(settings)
        admin_socket = admin_socket_path(settings)
    except ConfigError as exc:
        print(f"firos: configuration error: {exc}", file=sys.stderr)
        return 1
    setup_logging(settings.log_level)

    from include import server as http
    from include.bridge import Firos
    from include.discovery import GraphReader
    from include.metrics import make_metrics
    from include.ngsi_versions import client_for
    from include.rcm_bridge import RosControl
    from include.sender import Sender
    from include.subscriptions import Subscriptions
    from include.topics import TopicHandler

    try:
        servers = open_servers(http, settings, address, admin_socket)
    except OSError as exc:
        print(f"firos: cannot listen on {exc.strerror}", file=sys.stderr)
        return 1

    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    rospy.init_node("firos", anonymous=False, disable_signals=True)
    route_logs_to_ros()

    url = f"http://{address}:{port}/firos"
    holder = {}
    sender = Sender(client_for(settings), settings,
                    on_created=lambda r: holder["firos"].entity_created(r),
                    on_removed=lambda r: holder["firos"].entity_removed(r),
                    on_recovered=lambda: subscriptions.renew_all())
    subscriptions = Subscriptions(client_for(settings), settings, url,
                                  on_lost=lambda r: holder["firos"].entity_lost(r))
    topics = TopicHandler(sender)
    firos = Firos(settings, whitelist, descriptions, sender, subscriptions, topics, GraphReader(rospy.get_name()),
                  client_for(settings))
    holder["firos"] = firos
    control = RosControl(firos)
    firos.events = control
    metrics = make_metrics(firos, servers[0].pool, servers[0].RequestHandlerClass.tally,
                           servers[0].RequestHandlerClass.ROUTE_LABELS)
    for client in (sender.client, subscriptions.client, firos.read_client):
        client.observer = metrics.broker_request
    sender.forward_observers.append(metrics.forwarded)
    http.bind(servers, firos, metrics)

    sender.start()
    subscriptions.start()
    control.start()
    for httpd in servers:
        http.serve_in_thread(httpd)
    log.info("FIROS up: HTTP on %s, broker %s:%d (NGSI %s), notifications to %s",
             ", ".join(h.describe() for h in servers), settings.broker_address, settings.broker_port,
             settings.ngsi_version, url)

    while not stop.is_set() and not rospy.is_shutdown():
        try:
            firos.scan()
        except (OSError, socket.error) as exc:
            log.warning("cannot read the ROS graph: %s", exc)
        except Exception:  # discovery must go on whatever one look at the graph met
            log.exception("robot discovery failed")
        if settings.discovery_interval <= 0:
            stop.wait()
        else:
            stop.wait(settings.discovery_interval)

    log.info("FIROS stopping: removing subscriptions and entities")
    http.close_servers(servers)
    control.stop()
    firos.disconnect_all()
    sender.wait_idle(3.0)
    subscriptions.stop()
    sender.stop()
    control.finish_events()
    rospy.signal_shutdown("FIROS stopped")
    return 0


if __name__ == "__main__":
    sys.exit(main())
