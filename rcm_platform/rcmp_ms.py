"""Managed services: the service-space runtime of an agent, on top of its process table (``rcmp_process``).

See docs/SERVICE_SPACES.md. Owns:

* ``ServiceSpace``: one robot's running context on this agent. It has one state from a closed set
  (``creating``, ``paired``, ``unpaired``, ``stopping``, ``gone``) and changes state only through
  ``ServiceSpace.transition``, checked as a process's transitions are (``rcmp_process.check_transition``).
* the start sequence, written once (``_SpaceHost._bring_up``) and run by both sides: the space's ROS master
  (``rosmaster --core`` plus ``rosout``, measured leaner and faster than ``roscore``) on a free port from
  ``config.ros_port_base`` upward, here or by the remote agent that hosts it; once that master answers (as
  roslaunch does: a rospy node given private params, ``_x:=1``, sets them on its master first thing and dies
  if none answers) every part's items at once, here and through ``RemoteAgent``s; the special items'
  ``started`` hooks; then the space settles: ``paired`` when the ROS master answers and every item has started
  (its node(s) registered with the space's master, a launcher's every node; a node that never registers under
  its name stayed up for the settle time). rosout is watched but not waited for (it only collects logs).
* ``ServiceSpaceManager`` (the master): per connected robot a ``ServiceSpace``, placed on a server (``Server``,
  ``choose_server``: the master or a server VM, CONTRACTS §8), moved when its server goes, torn down when its
  robot goes; ``item_exited`` reports from the robots; ``observers`` (the console).
* ``ItemRunner`` (a robot, or a server VM): what the master asks this agent to run of a space (a robot's R
  items, and the ROS master for ``ss_side`` R; a server VM's ROS master, from its own ``ros_port_base``, and
  S items), and reports items that die later.
* ``RemoteAgent``: the protocol the master's agent layer implements over the network, one per robot or server.
  A space's ROS master that a remote agent started is taken only at that agent's own address
  (``remote_master_uri``): its answer cannot point the S side or the master's polling anywhere else.
* the special items' side of the runtime: the ports they take (``take_inbound_port``, ``choose_driver_port``)
  and rcm_driver's connection (``connect_driver``, ``say_goodbye_to_driver``: ``r_connection`` /
  ``r_disconnection`` over a ``rcmp_inter_communication.DriverLink`` kept open), which their hooks call.
* ``poll_until``: every "try again until a deadline" of the runtime (a ROS master answering, nodes
  registering, rcm_driver accepting) is this one helper.

What a service item is and how it becomes a process (command line, environment, user, special items) is
``rcmp_service_item``'s; ``rcmp_service_command.describe`` renders a space for ``service_space/read``. This module
imports neither ``rcmp_event`` nor ``rcmp_node``: ``rcmp_node`` builds the runtime and hands it (and the function
giving the platform address) to the agents.

About 1,200 lines, more than the 900 or so of the other modules, because it is one runtime that both sides run:
the master's manager and the ``ItemRunner`` share the start sequence, the ROS master, the items' start and
registration, the special items' ports and rcm_driver link, and the stopping (``_SpaceHost``); the parts that
were jobs of their own have left it (the process table: ``rcmp_process``; what an item is: ``rcmp_service_item``).
"""

import collections
import logging
import os
import re
import socket
import uuid
from typing import Protocol

from twisted.internet import defer, task, threads
from twisted.web import xmlrpc

from rcm_platform import rcmp_inter_communication as ic
from rcm_platform.rcmp_command import CommandError
from rcm_platform.rcmp_config import SERVER_STARTING_SPACES, default_max_starting_spaces
from rcm_platform.rcmp_log_guard import Budget, shown
from rcm_platform.rcmp_process import DONE_STATES, FAILED, RUNNING, STARTING, STATES, check_transition
from rcm_platform.rcmp_service_item import (ITEM_FAILURES, NodeExecutables, ServiceItem, child_env, graph_name,
                                            items_of_logic, launcher_nodes, launcher_nodes_as)

# one "Starting factory" log line per XML-RPC call to a ROS master is noise (Twisted 18.9 names it _QueryFactory)
(getattr(xmlrpc, "QueryFactory", None) or xmlrpc._QueryFactory).noisy = False

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------------------------
# Helpers of the service-space runtime.

AGAIN = object()  # what an attempt given to poll_until returns to be called again


class SpaceError(Exception):
    """Why a service space cannot be paired (a sentence shown in service_space/read as ``reason``)."""


@defer.inlineCallbacks
def poll_until(reactor, attempt, interval, timeout=None, on_timeout=None, slowest=None):
    """Call ``attempt()`` (a value or a Deferred) every ``interval`` seconds until it gives something other
    than ``AGAIN``, and fire with that. An exception other than SpaceError counts as AGAIN (a saturated
    machine makes single calls fail); SpaceError ends the poll. Once ``timeout`` seconds have passed the poll
    fires with ``on_timeout(last exception or None)`` (which may raise) instead of trying again. With
    ``slowest``, each wait is a quarter longer than the one before, up to ``slowest`` seconds: quick answers
    are seen quickly, and what takes long (a busy machine) is not asked ever more often."""
    deadline = None if timeout is None else reactor.seconds() + timeout
    while True:
        last = None
        try:
            result = yield defer.maybeDeferred(attempt)
        except SpaceError:
            raise
        except Exception as exc:
            result, last = AGAIN, exc
        if result is not AGAIN:
            return result
        if deadline is not None and reactor.seconds() > deadline:
            return on_timeout(last)
        yield task.deferLater(reactor, interval, lambda: None)
        if slowest is not None:
            interval = min(slowest, interval * 1.25)


def _tcp_port_free(port, host=""):
    """True when nothing listens on ``port`` on any address (a listener on one address makes it busy)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host, port))
            return True
        except OSError:
            return False


HERE = object()   # this agent, as a place where a part of a service space runs (beside its RemoteAgents)

REPORTED_TEXT = 4000     # characters of an item's error the master keeps from a robot's (or server's) report
REPORTED_NAME = 256      # characters of each name in it
REPORTED_NODES = 1000    # nodes of one launcher it keeps


def received_report(report):
    """What the master keeps of an item report a robot or server VM sent (docs/DESIGN.md's fields): strings cut
    (names to ``REPORTED_NAME`` characters, the error to ``REPORTED_TEXT``), a state of the process table's set
    (``failed`` otherwise), at most ``REPORTED_NODES`` nodes. A peer's report is never kept or shown whole."""
    def text(value, limit=REPORTED_NAME):
        return value[:limit] if isinstance(value, str) else None
    kept = {field: text(report.get(field)) for field in ("kind", "name", "package", "type_or_file", "side",
                                                          "i_name")}
    kept["state"] = report.get("state") if report.get("state") in STATES else FAILED
    kept["error"] = text(report.get("error"), REPORTED_TEXT)
    if report.get("failure") is not None:   # why it failed: one word of the closed set, "other" for anything else
        kept["failure"] = report["failure"] if report["failure"] in ITEM_FAILURES else "other"
    nodes = report.get("nodes")
    kept["nodes"] = [text(n) for n in nodes[:REPORTED_NODES] if isinstance(n, str)] if isinstance(nodes, list) else []
    types = report.get("node_types")
    types = list(types.items())[:REPORTED_NODES] if isinstance(types, dict) else []
    kept["node_types"] = {text(node): [text(part) or "" for part in pair[:2]] for node, pair in types
                          if isinstance(pair, list) and len(pair) == 2}
    return kept


def _items_on(parts, host):
    """The items of ``parts`` (``[(host, items)]``) that run on ``host``."""
    return [item for where, items in parts if where is host for item in items]


DRIVER_EVENTS_KEPT = 50  # rcm_driver's last events a space keeps for service_space/read
DRIVER_RECONNECTS = 10   # times a space connects to its rcm_driver again after the connection closed
RCM_DRIVER_PORT = 9998  # rcm_driver's default port (CONTRACTS §4); each further space takes the next free one
_PORT_TAKEN = "is already in use"  # rosmaster's words when its XML-RPC port is taken ("port N is already in use")
_REMOTE_MASTER_URI = re.compile(r"http://([0-9.]{7,15}):([0-9]{1,5})/?\Z")
SHOWN_URI = 80          # characters of a URI a peer answered that go into a sentence


def remote_master_uri(answer, address):
    """The URI of a space's ROS master that the remote agent whose connection comes from ``address`` says it
    started, as ``http://ADDRESS:PORT/``; None unless ``answer`` is exactly that: an ``http`` URI whose host is
    ``address`` itself (the session's source address, written the same way) and whose port is 1 to 65535, with
    nothing else (no other host or scheme, no user, path, query or fragment). Anything else would let the agent
    steer the S-side items and the master's XML-RPC polling to a URL of its choosing."""
    match = _REMOTE_MASTER_URI.match(answer) if isinstance(answer, str) else None
    if match is None or match.group(1) != address or not 1 <= int(match.group(2)) <= 65535:
        return None
    return f"http://{address}:{int(match.group(2))}/"


# ---------------------------------------------------------------------------------------------------------
# Service spaces: states, a closed set, and the only transitions allowed between them (target -> sources).

SPACE_CREATING = "creating"    # being built
SPACE_PAIRED = "paired"        # built; the ROS master and every item run (robot side: its items run)
SPACE_UNPAIRED = "unpaired"    # built, not paired: ``why_unpaired()`` says why
SPACE_STOPPING = "stopping"    # torn down (creation, if still going, gives up)
SPACE_GONE = "gone"            # nothing of it is left

SPACE_STATES = frozenset({SPACE_CREATING, SPACE_PAIRED, SPACE_UNPAIRED, SPACE_STOPPING, SPACE_GONE})
_SPACE_SOURCES = {
    SPACE_PAIRED: frozenset({SPACE_CREATING, SPACE_UNPAIRED}),
    SPACE_UNPAIRED: frozenset({SPACE_CREATING, SPACE_PAIRED}),
    SPACE_STOPPING: frozenset({SPACE_CREATING, SPACE_PAIRED, SPACE_UNPAIRED}),
    SPACE_GONE: frozenset({SPACE_STOPPING}),
}


class ServiceSpace:
    """The running context of one robot on this agent: ROS master, items, ports, and one state."""

    def __init__(self, name, ss_side, key_prefix, address, i_name):
        self.name = name
        self.ss_side = ss_side
        self.key_prefix = key_prefix
        self.address = address
        self.i_name = i_name
        self.state = SPACE_CREATING
        self.ros_master_uri = None
        self.ros_master_port = None
        self.master = None          # ManagedProcess of rosmaster, when the master runs here
        self.core_env = None        # the environment of the space's rosmaster and rosout
        self.rosout = None
        self.items = []
        self.inbound_port = None
        self.reason = None          # why it can never pair (set once; the items' errors say the rest)
        self.robot = None
        self.logic = None           # master side: the service logic it was built from (to rebuild it elsewhere)
        self.server = None          # master side: the name of the server hosting its S side (and ROS master)
        self.host = None            # master side: that server's RemoteAgent, None when it is this agent
        self.public_ip = None       # master side: the hosting server's address for service_space/read
        self.driver_link = None
        self.driver_events = collections.deque(maxlen=DRIVER_EVENTS_KEPT)
        self.driver_waiters = []
        self.told = set()           # robot side: keys of the failures already reported
        self.teardown_waiters = None
        self.notes = Budget(log, f"notes about service space {name}")   # robots report at will
        self.driver_reconnects = 0

    def __repr__(self):
        return f"<ServiceSpace {self.name} {self.state}>"

    def transition(self, new, why):
        """The only way the space changes state; InvalidTransition for a change the set does not allow."""
        old = self.state
        check_transition(f"service space {self.name}", old, new, SPACE_STATES, _SPACE_SOURCES)  # never to creating
        self.state = new
        log.debug("service space %s: %s -> %s (%s)", self.name, old, new, why)

    @property
    def creating(self):
        return self.state == SPACE_CREATING

    @property
    def paired(self):
        return self.state == SPACE_PAIRED

    @property
    def cancelled(self):
        """Torn down (or being torn down): whatever is still starting gives up."""
        return self.state in (SPACE_STOPPING, SPACE_GONE)

    def key(self, *parts):
        return "/".join((self.key_prefix, self.name) + parts)

    def core_processes(self):
        return [p for p in (self.rosout, self.master) if p is not None]

    def pairs(self):
        """Whether everything the space needs runs now (its state aside)."""
        if self.reason or not self.ros_master_uri:
            return False
        if self.master is not None and self.master.state != RUNNING:
            return False
        if self.rosout is not None and self.rosout.state not in (STARTING, RUNNING):
            return False
        return all(item.state == RUNNING for item in self.items)

    def why_unpaired(self):
        if self.reason:
            return self.reason
        for item in self.items:
            if item.state != RUNNING:
                return f"{item.kind} {item.name} on {item.i_name} is {item.state}" + (
                    f": {item.current_error}" if item.current_error else "")
        return STARTING

    def settle(self):
        """Creation is over (and the space not torn down meanwhile): paired or not. Returns the new state."""
        if self.creating:
            self.transition(SPACE_PAIRED if self.pairs() else SPACE_UNPAIRED, "created")
        return self.state


class RemoteAgent(Protocol):
    """A connected robot or server VM as the master sees it (``rcmp_event.AgentSession``, over the network): the
    space's R items run on a robot; a server VM hosts a space's ROS master and S items."""

    name: str
    address: str

    def start_items(self, ss_name, ros_master_uri, items, start_ros_master_port=None):
        """Deferred({"ros_master_uri": str, "items": [item report, ...]}) once the agent's items settled."""

    def stop_items(self, ss_name):
        """Deferred fired when the agent stopped every item (and ROS master) of the space."""


# ---------------------------------------------------------------------------------------------------------
# The runtime shared by both sides: the start sequence, the ROS master, local items, stopping a space.

class _SpaceHost:
    """What the master's ``ServiceSpaceManager`` and a robot's or server VM's ``ItemRunner`` share."""

    master_timeout = 20.0        # seconds for a new ROS master to answer
    driver_timeout = 20.0        # seconds for rcm_driver's port to accept
    driver_goodbye_timeout = 3.0 # seconds to wait for e_removed after r_disconnection (with FIROS)
    robot_timeout = 30.0         # seconds for a robot to stop its items before we carry on
    launcher_nodes_timeout = 15.0  # seconds for a launcher's nodes to register after it was spawned
    registration_poll = 0.02       # seconds between two looks at the ROS master while items register
    registration_poll_slowest = 0.2  # ... growing to at most this (dozens of spaces starting at once)
    _roslaunch_imported = False    # launcher_nodes ran once on the reactor thread (see _prepare)

    key_prefix = "ss"

    def __init__(self, reactor, table, config, env=None, address=None, run_as=None):
        """``address``: the platform address children advertise (ROS_IP), or a function giving it now (it
        may appear late, with the VPN); None: ``config.vpn_address``. ``run_as``: the ``RunAs`` every process
        of a space runs as (its ROS master, rosout and items), None for the agent's own user."""
        self.reactor = reactor
        self.table = table
        self.config = config
        self.env = env
        self.run_as = run_as
        self._address = address
        self.spaces = {}
        self.executables = NodeExecutables()   # nodes run as one exec, not through rosrun (rcmp_service_item)
        self.ros_log_dir = os.path.join(table.log_dir, "ros")

    @property
    def address(self):
        """The platform address children advertise (ROS_IP) now; SpaceError when there is none yet."""
        address = self._address() if callable(self._address) else self._address
        address = address or self.config.vpn_address
        if not address:
            raise SpaceError(f"no platform address: interface {self.config.vpn_interface} has "
                             "no IPv4 address and vpn_address is not set")
        return address

    def _proxy(self, space):
        return xmlrpc.Proxy(space.ros_master_uri.encode(), connectTimeout=1.0, reactor=self.reactor)

    # -- ports --------------------------------------------------------------------------------------------
    def _taken_ros_ports(self):
        return {s.ros_master_port for s in self.spaces.values() if s.ros_master_port}

    def _choose_ros_port(self, base):
        taken = self._taken_ros_ports()
        for port in range(base, min(base + 1000, 65536)):
            if port not in taken and _tcp_port_free(port):
                return port
        raise SpaceError(f"no free port for a ROS master between {base} and {min(base + 999, 65535)}")

    def choose_driver_port(self):
        """A local port for a space's rcm_driver: rcm_driver's default (9998) or the next free one above it.
        Never a port-0 (ephemeral) port: any process's outgoing or port-0 socket can take one of those between
        our check and the driver's bind, and the agent would then say r_connection to a stranger."""
        taken = {i.driver_port for s in self.spaces.values() for i in s.items if i.driver_port}
        taken.add(self.config.ic_port)
        for port in range(RCM_DRIVER_PORT, RCM_DRIVER_PORT + 1000):
            if port not in taken and _tcp_port_free(port):
                return port
        raise SpaceError(f"no free local port for rcm_driver between {RCM_DRIVER_PORT} and {RCM_DRIVER_PORT + 999}")

    def take_inbound_port(self, space):
        ports = list(self.config.inbound_open_ports)
        users = {s.inbound_port: s.name for s in self.spaces.values() if s.inbound_port}
        for port in ports:
            if port not in users and _tcp_port_free(port):
                return port
        if not ports:
            raise SpaceError("FIROS needs an inbound open port but inbound_open_ports is empty")
        used = ", ".join(f"{p} ({users[p]})" if p in users else f"{p} (busy)" for p in ports)
        raise SpaceError(f"no inbound open port left for FIROS: all of {used} are in use")

    # -- ROS master -----------------------------------------------------------------------------------------
    def _spawn_master(self, space, base):
        """Spawn the space's ROS master on a free port from ``base``; its URI is known at once, so items can
        be started right away (rospy nodes and ``roslaunch --wait`` wait for their master themselves)."""
        port = self._choose_ros_port(base)
        space.ros_master_port = port
        space.ros_master_uri = f"http://{space.address}:{port}/"
        space.core_env = self._child_env(space)
        space.master = self.table.spawn(space.key("rosmaster"), ["rosmaster", "--core", "-p", str(port)],
                                        space.core_env, f"{space.name}-rosmaster", core=True, user=self.run_as)

    @defer.inlineCallbacks
    def _master_ready(self, space):
        """Wait for the spawned ROS master to answer, give it ``/run_id`` as roscore does, start rosout, and
        mark both running as soon as they prove it (the master answers, rosout registers). The space's items
        start after this fires (rospy nodes with private params need an answering master at once)."""
        yield self._wait_for_master(space)
        if space.cancelled:
            return
        space.master.confirm_running("answers on its XML-RPC port")
        # roscore sets /run_id; roslaunch --wait (launchers) waits for it and rosout names its log dir after it
        yield self._call_master(space, "setParam", "/run_id", str(uuid.uuid1()), what="set /run_id")
        if space.cancelled:
            return
        argv = self.executables.direct_argv(["rosrun", "rosout", "rosout"], space.core_env)
        space.rosout = self.table.spawn(space.key("rosout"), argv, space.core_env,
                                        f"{space.name}-rosout", core=True, user=self.run_as)
        space.rosout.listeners.append(lambda mp, old, new: self._core_changed(space, mp, new))
        space.master.listeners.append(lambda mp, old, new: self._core_changed(space, mp, new))
        # rosout only collects logs: pairing does not wait for it to register (its failure still unpairs)
        watching = self._confirm_when_registered(space, space.rosout, ["/rosout"])
        watching.addErrback(lambda failure: log.error("service space %s: watching rosout: %s", space.name,
                                                      failure.getTraceback()))

    def _call_master(self, space, method, *args, what):
        """One XML-RPC call to the space's master, retried until ``master_timeout``: a machine saturated by
        starting processes can make a single call time out although the master is fine."""
        proxy = self._proxy(space)

        def attempt():
            d = proxy.callRemote(method, "/rcmp_ms", *args)
            return d.addErrback(lambda failure: None if space.cancelled else failure)

        def give_up(exc):
            raise SpaceError(f"the ROS master on {space.ros_master_uri} could not {what} within "
                             f"{self.master_timeout:g} s: {exc}")
        return poll_until(self.reactor, attempt, 0.1, self.master_timeout, give_up)

    def _confirm_when_registered(self, space, managed, names, timeout=None):
        """Mark ``managed`` running as soon as every ROS node in ``names`` is registered with the space's
        master. Fires with the names still missing when it stopped looking: [] once all registered; the
        missing ones if the process ended, or (no ``timeout``) settled the slow way, or ``timeout`` passed."""
        proxy = self._proxy(space)
        missing = list(names)

        @defer.inlineCallbacks
        def attempt():
            nonlocal missing
            if space.cancelled or managed.state not in (STARTING, RUNNING):
                return missing
            still = []
            for name in missing:
                try:
                    code, _, _ = yield proxy.callRemote("lookupNode", "/rcmp_ms", name)
                except Exception:
                    code = 0
                if code != 1:
                    still.append(name)
            missing = still
            if not missing:
                managed.confirm_running("registered with the ROS master")
                managed.remember_descendants()  # afresh: its nodes now exist, they go wherever it goes
                return []
            if timeout is None and managed.state == RUNNING:
                return missing
            return AGAIN
        return poll_until(self.reactor, attempt, self.registration_poll, timeout, lambda exc: missing,
                          slowest=self.registration_poll_slowest)

    def _wait_for_master(self, space):
        """Poll the new master's XML-RPC getPid until it answers (no sleeping in place of waiting)."""
        proxy = self._proxy(space)

        def attempt():
            if space.cancelled:
                return None
            if space.master.state not in (STARTING, RUNNING):
                raise SpaceError(f"the ROS master on port {space.ros_master_port} {space.master.error}")
            if _PORT_TAKEN in space.master.tail(20):
                # rosmaster stays alive without its XML-RPC server when its port was taken between our check
                # and its bind: say so now rather than after master_timeout
                raise SpaceError(f"the ROS master could not listen on port {space.ros_master_port}: "
                                 f"{space.master.useful_output(2)}")
            d = proxy.callRemote("getPid", "/rcmp_ms")
            return d.addCallback(lambda _: log.info("service space %s: ROS master answers on %s", space.name,
                                                    space.ros_master_uri))

        def give_up(exc):
            raise SpaceError(f"the ROS master on {space.ros_master_uri} did not answer within "
                             f"{self.master_timeout:g} s: {exc}")
        return poll_until(self.reactor, attempt, 0.05, self.master_timeout, give_up,
                          slowest=self.registration_poll_slowest)

    @defer.inlineCallbacks
    def _core_settled(self, space):
        """Wait until the ROS master runs here (usually long since) and check that rosout has not failed;
        SpaceError if one did."""
        if space.master is not None:
            up = yield space.master.when_settled()
            if not up and not space.cancelled:
                raise SpaceError(f"the space's rosmaster {space.master.error}")
        if space.rosout is not None and space.rosout.state in DONE_STATES and not space.cancelled:
            raise SpaceError(f"the space's rosout {space.rosout.error}")

    def _core_changed(self, space, managed, new):
        if new == FAILED and not space.cancelled:
            space.reason = f"the space's {managed.key.rsplit('/', 1)[-1]} {managed.error}"
            self._pairing_may_have_changed(space)

    # -- the start sequence -----------------------------------------------------------------------------------
    @defer.inlineCallbacks
    def _bring_up(self, space, parts, master_on=None, master_port=None):
        """The start sequence of a service space, the one both sides run:

        1. its ROS master: started here on a free port from ``master_port`` upward (``master_on`` is ``HERE``),
           or by the remote agent ``master_on`` together with that agent's part, or none (the URI is known);
        2. once it answers (rospy nodes given private params need an answering master at once), every other
           part at once: the items here (``HERE``) and each remote agent's (robots, the server hosting the space);
        3. the special items' ``started`` hooks (rcm_driver: r_connection);
        4. the ROS master and rosout checked; then the space settles: paired or not.

        ``parts``: ``[(HERE or a RemoteAgent, [ServiceItem])]``; a remote part without items is skipped unless its
        agent starts the master (then it is that agent's whole part). A SpaceError, also from one of the parts
        started together, ends the sequence and becomes ``space.reason``; it is also what the Deferred fires with
        (None when there was none). Any other error propagates and the space is not settled.
        """
        try:
            if master_on is HERE or any(host is HERE for host, _ in parts):
                space.address = self.address   # what the children here advertise
            if master_on is HERE:
                self._spawn_master(space, master_port)
                yield self._master_ready(space)
            elif master_on is not None:
                yield self._start_part(space, master_on, _items_on(parts, master_on), master_port)
            if not space.cancelled:
                if not space.ros_master_uri:
                    raise SpaceError("no ROS master URI given and none started")
                yield defer.gatherResults([self._start_part(space, host, items) for host, items in parts
                                           if host is HERE or (items and host is not master_on)],
                                          consumeErrors=True)
            if not space.cancelled:
                yield self._items_started(space)
            yield self._core_settled(space)
            problem = None
        except SpaceError as exc:
            problem = space.reason = str(exc)
        except defer.FirstError as exc:
            if not exc.subFailure.check(SpaceError):
                exc.subFailure.raiseException()
            problem = space.reason = str(exc.subFailure.value)
        space.settle()
        return problem

    def _start_part(self, space, host, items, master_port=None):
        """Start ``items`` here (``host`` is ``HERE``) or on the remote agent ``host`` (which also starts the space's
        ROS master when given ``master_port``)."""
        if host is HERE:
            return self._start_local_items(space, items)
        return self._start_remote(space, host, items, master_port)

    @defer.inlineCallbacks
    def _start_remote(self, space, agent, remote, start_ros_master_port):
        """Start ``remote`` items on ``agent`` (the space's robot, or the server hosting the space; with
        ``start_ros_master_port`` it starts the space's ROS master too)."""
        who = getattr(agent, "name", space.name)
        what = "robot" if agent is space.robot else "server"
        try:
            result = yield agent.start_items(space.name, space.ros_master_uri, [i.to_dict() for i in remote],
                                             start_ros_master_port=start_ros_master_port)
        except Exception as exc:
            raise SpaceError(f"{what} {who} could not start its items: {shown(str(exc))}")
        if space.cancelled:
            return
        if result.get("reason"):   # the agent's own words: at most LOGGED_TEXT characters of them, as any peer's
            raise SpaceError(f"{what} {who}: {shown(str(result['reason']))}")
        if start_ros_master_port is not None:
            answer = result.get("ros_master_uri")
            if not answer:
                raise SpaceError(f"{what} {who} did not start the ROS master")
            address = getattr(agent, "address", None)
            space.ros_master_uri = remote_master_uri(answer, address)
            if space.ros_master_uri is None:
                raise SpaceError(f"{what} {who} answered that the space's ROS master is at "
                                 f"{shown(answer, SHOWN_URI)}, which is not on its own address: a {what}'s ROS "
                                 f"master is accepted only at http://{address}:PORT/; nothing of the space was "
                                 f"started against it")
        inbound_port = result.get("inbound_port")
        if isinstance(inbound_port, int) and not isinstance(inbound_port, bool) and 0 < inbound_port < 65536:
            space.inbound_port = inbound_port
        items = result.get("items")
        reports = {(r["kind"], r["name"]): r for r in (received_report(r) for r in items if isinstance(r, dict))
                   } if isinstance(items, list) else {}
        for item in remote:
            item.remote = reports.get((item.kind, item.name)) or {
                **item.report(), "state": FAILED, "error": f"the {what} did not report this item",
                "failure": "not_reported"}
            item.remote["i_name"] = item.remote.get("i_name") or item.i_name
            item.nodes = list(item.remote.get("nodes") or [])
            item.node_types = {n: tuple(t) for n, t in (item.remote.get("node_types") or {}).items()}

    # -- local items ----------------------------------------------------------------------------------------
    @defer.inlineCallbacks
    def _start_local_items(self, space, items):
        """Prepare (launcher node lists, ports), spawn every item, and wait until each started or failed."""
        yield defer.gatherResults([self._prepare(space, item) for item in items], consumeErrors=True)
        if space.cancelled:
            return
        env = self._child_env(space)
        for item in items:
            if item.error is None:
                self._spawn_item(space, item, env)
        yield defer.gatherResults([self._item_started(space, item) for item in items if item.process],
                                  consumeErrors=True)

    @defer.inlineCallbacks
    def _item_started(self, space, item):
        """An item has started when its ROS node(s) registered with the space's master (or, for a node that
        never registers under its name, when it stayed up for the settle time). A launcher must see every node
        it launches register: roslaunch keeps running when one of its nodes cannot start, so its liveness
        alone proves nothing."""
        if item.kind == "node":
            yield self._confirm_when_registered(space, item.process, [graph_name(item.name, item.params)])
            yield item.process.when_settled()
            return
        names = ["/" + n.lstrip("/") for n in item.nodes]
        missing = yield self._confirm_when_registered(space, item.process, names,
                                                      timeout=self.launcher_nodes_timeout)
        if missing and not space.cancelled and item.process.state in (STARTING, RUNNING):
            output = item.process.useful_output()
            item.fail(f"node(s) {', '.join(n.lstrip('/') for n in missing)} of launcher {item.name} did not "
                      f"register with the ROS master within {self.launcher_nodes_timeout:g} s"
                      + (f": {output}" if output else ""), "not_registered")

    @defer.inlineCallbacks
    def _prepare(self, space, item):
        if item.kind == "node":
            item.nodes = [item.name]
            if item.special is not None:
                try:
                    item.special.prepare(self, space, item)
                except SpaceError as exc:
                    item.fail(str(exc), "port")
                    space.reason = str(exc)
            return
        try:
            if self.run_as is not None:
                # roslaunch's loader runs what a launch file asks (<param command>, $(eval)): as the items' user
                nodes = yield threads.deferToThread(launcher_nodes_as, self.run_as, self._child_env(space),
                                                    item.package, item.type_or_file, item.params)
            elif self._roslaunch_imported:
                nodes = yield threads.deferToThread(launcher_nodes, item.package, item.type_or_file, item.params)
            else:
                # The first parse imports ~300 modules (roslaunch, rospkg, pkg_resources...). An import running
                # in a thread while the reactor forks a child deadlocks CPython (os.fork takes the import and
                # logging locks), so that first parse runs here, on the reactor thread, once per agent.
                _SpaceHost._roslaunch_imported = True
                nodes = launcher_nodes(item.package, item.type_or_file, item.params)
        except Exception as exc:  # roslaunch's RLException and its loader's errors: the message says why
            item.fail(f"roslaunch cannot load {item.package}/{item.type_or_file}: {exc}", "launch_file")
            return
        item.nodes = [n for n, _, _ in nodes]
        item.node_types = {n: (p, t) for n, p, t in nodes}

    def _child_env(self, space):
        """The environment of the space's processes (``child_env``), as the items' user when there is one."""
        return child_env(self.env, space.ros_master_uri, space.address, self.ros_log_dir, user=self.run_as,
                         agent_home=os.path.dirname(self.table.log_dir))

    def _spawn_item(self, space, item, env):
        try:
            argv = item.spawn_argv(env, self.executables)
        except CommandError as exc:  # params that do not split (validation lets none through)
            item.fail(f"cannot split the params {item.params!r}: {exc}", "params")
            return
        if item.special is not None:
            env = item.special.environment(item, env)
        item.process = self.table.spawn(space.key(item.kind, item.name), argv, env, f"{space.name}-{item.name}",
                                        user=self.run_as)
        item.process.listeners.append(lambda mp, old, new: self._item_changed(space, item, new))

    def _item_changed(self, space, item, new):
        if new == FAILED and not space.cancelled:
            self._pairing_may_have_changed(space)

    def _pairing_may_have_changed(self, space):
        """Hook: each side decides what a change means (master: on_state; robot: item-exited event)."""

    def _changed(self, space):
        """Hook: what ``describe`` says of ``space`` changed (the master tells its observers)."""

    # -- special items' hooks -------------------------------------------------------------------------------
    @defer.inlineCallbacks
    def _items_started(self, space):
        """The special items' ``started`` hooks, in item order (rcm_driver: connect, say r_connection)."""
        for item in space.items:
            if item.special is not None and item.process is not None:
                yield item.special.started(self, space, item)

    def connect_driver(self, space, item):
        """Connect to rcm_driver's port once it accepts and say r_connection for the robot."""
        def attempt():
            if space.cancelled or item.state not in (STARTING, RUNNING):
                return None
            link = ic.DriverLink(space.name, lambda cmd, r_name: self._driver_said(space, cmd, r_name),
                                 lambda lost: self._driver_lost(space, item, lost), key=item.driver_key)
            return ic.connect_driver(self.reactor, item.driver_port, link)

        def give_up(exc):
            raise SpaceError(f"rcm_driver did not accept connections on port {item.driver_port} "
                             f"within {self.driver_timeout:g} s: {exc}")

        def connected(link):
            if link is None:
                return
            space.driver_link = link
            link.send("r_connection", space.name)
            log.info("service space %s: told rcm_driver (port %s) r_connection", space.name, item.driver_port)
        return poll_until(self.reactor, attempt, 0.1, self.driver_timeout, give_up).addCallback(connected)

    def _driver_said(self, space, cmd, r_name):
        log.info("service space %s: rcm_driver says %s %s", space.name, shown(cmd, 40), shown(r_name, 80))
        space.driver_events.append({"rcm_d_cmd": cmd, "r_name": r_name})
        self._changed(space)
        waiters, space.driver_waiters = space.driver_waiters, []
        for wanted, d in waiters:
            if wanted == (cmd, r_name):
                d.callback(True)
            else:
                space.driver_waiters.append((wanted, d))

    def _driver_lost(self, space, item, link):
        """The link to rcm_driver closed. Unless we closed it (``say_goodbye_to_driver``) or the space or the driver
        is going, connect again and say r_connection again (rcm_driver closes a connection that has not shown its
        key in time, which a busy agent or a flood of other local connections can make ours), at most
        ``DRIVER_RECONNECTS`` times per space."""
        if space.driver_link is not link:
            return
        space.driver_link = None
        if space.cancelled or item.state not in (STARTING, RUNNING) or space.driver_reconnects >= DRIVER_RECONNECTS:
            return
        space.driver_reconnects += 1
        space.notes.warning("service space %s: the connection to rcm_driver closed; connecting again", space.name)
        self.connect_driver(space, item).addErrback(
            lambda failure: space.notes.warning("service space %s: %s", space.name, failure.getErrorMessage()))

    def _items_stopping(self, space):
        """The special items' ``stopping`` hooks (rcm_driver: r_disconnection, e_removed awaited with FIROS)."""
        return defer.gatherResults([defer.maybeDeferred(item.special.stopping, self, space, item)
                                    for item in space.items if item.special is not None], consumeErrors=True)

    @defer.inlineCallbacks
    def say_goodbye_to_driver(self, space):
        link, space.driver_link = space.driver_link, None
        if link is None:
            return
        link.send("r_disconnection", space.name)
        log.info("service space %s: told rcm_driver r_disconnection", space.name)
        announced = any(i.special is not None and i.special.announces_entities and i.state == RUNNING
                        for i in space.items)
        if announced:  # give FIROS the chance to remove the robot's entity before it is stopped
            waiter = defer.Deferred()
            space.driver_waiters.append((("e_removed", space.name), waiter))
            timeout = self.reactor.callLater(self.driver_goodbye_timeout, waiter.callback, False)
            removed = yield waiter
            if timeout.active():
                timeout.cancel()
            if not removed:
                log.warning("service space %s: no e_removed from rcm_driver within %g s", space.name,
                            self.driver_goodbye_timeout)
        link.transport.loseConnection()

    # -- stopping -------------------------------------------------------------------------------------------
    @defer.inlineCallbacks
    def _stop_local(self, space):
        """Stop the space's items here (together), then rosout, then the ROS master; forget them."""
        procs = [i.process for i in space.items if i.process is not None]
        yield defer.gatherResults([p.stop() for p in procs], consumeErrors=True)
        for managed in space.core_processes():
            yield managed.stop()
        for managed in procs + space.core_processes():
            self.table.forget(managed.key)


# ---------------------------------------------------------------------------------------------------------
# Master side.



class Server:
    """A place for service spaces (CONTRACTS §8): the master itself (``host`` None) or a connected server VM
    (``host``: its ``RemoteAgent``, which starts the space's ROS master and S items there).

    ``builds`` is how many of its spaces are built at once (their ROS masters and items starting on that
    machine), the others placed there wait for a turn (``building``): each machine its own count, so twenty
    server VMs build twenty times as many as one."""

    def __init__(self, name, capacity, address, host=None, builds=SERVER_STARTING_SPACES):
        self.name = name
        self.capacity = int(capacity)
        self.address = address
        self.host = host
        self.builds = max(1, int(builds))
        self.building = defer.DeferredSemaphore(self.builds)


def choose_server(servers, hosted):
    """The server a new service space goes to: the lowest load (spaces hosted ÷ its ``max_service_spaces``)
    among those below their limit; ties go to the master (the one without a host), then by name. None when no
    server has room. ``servers``: [Server]; ``hosted``: {name: spaces hosted now}."""
    best = None
    for server in servers:
        count = hosted.get(server.name, 0)
        if server.capacity <= 0 or count >= server.capacity:
            continue
        key = (count / server.capacity, server.host is not None, server.name)
        if best is None or key < best[0]:
            best = (key, server)
    return None if best is None else best[1]


class ServiceSpaceManager(_SpaceHost):
    """The master's service spaces, one per connected robot, each placed on a server (the master or a server
    VM, ``add_server``). See docs/SERVICE_SPACES.md."""

    key_prefix = "ss"
    GONE_KEPT = 100              # server VMs no longer connected that platform_instance/read?pi_type=S still lists

    def __init__(self, reactor, table, config, public_ip, env=None, on_state=None, address=None, run_as=None):
        super().__init__(reactor, table, config, env=env, address=address, run_as=run_as)
        self.public_ip = public_ip
        self.on_state = on_state
        self.observers = []   # fn(ss_name) whenever a space appears, changes what describe() says, or goes;
                              # fn(None) when a server joins or goes (the console)
        self.i_name = "master" if config.role == "master" else config.name
        self.name = config.name
        self.servers = {self.name: Server(self.name, config.max_service_spaces, public_ip,
                                          builds=config.max_starting_spaces or default_max_starting_spaces())}
        self._hosted = collections.Counter()        # server name -> spaces (ss_side S) it hosts now
        self._of_server = {}                         # server name -> {pi_name: None} of its spaces, in creation order
        self.unplaced = collections.OrderedDict()   # pi_name -> (service logic, robot): waiting for room
        self.gone = collections.OrderedDict()       # server VMs lost or left: name -> Server (the last GONE_KEPT)
        self._placing = None

    # -- servers and placement (CONTRACTS §8) --------------------------------------------------------------
    def hosted(self):
        """{server name: service spaces (ss_side S) it hosts now}; kept up to date as spaces come and go (a copy,
        as long as the servers are many, not the spaces)."""
        return collections.Counter(self._hosted)

    def spaces_of(self, server_name):
        """Names of the spaces ``server_name`` hosts, in creation order (kept per server: as long as their count)."""
        return list(self._of_server.get(server_name, ()))

    def _add_space(self, space):
        """``space`` is this manager's now: in ``spaces`` and in its server's counts."""
        self.spaces[space.name] = space
        self._of_server.setdefault(space.server, {})[space.name] = None
        if space.ss_side == "S":
            self._hosted[space.server] += 1

    def _drop_space(self, space):
        """``space`` is no longer this manager's (no effect when another space of its name took its place)."""
        if self.spaces.get(space.name) is not space:
            return
        del self.spaces[space.name]
        names = self._of_server.get(space.server)
        if names is not None:
            names.pop(space.name, None)
            if not names:
                del self._of_server[space.server]
        if space.ss_side == "S":
            self._hosted[space.server] -= 1
            if self._hosted[space.server] <= 0:
                del self._hosted[space.server]

    def add_server(self, name, host, capacity, address, builds=SERVER_STARTING_SPACES):
        """A server VM joined: it takes new spaces from now on (nothing moves to it), building at most ``builds``
        at once; waiting spaces are placed."""
        self.servers[name] = Server(name, capacity, address, host, builds=builds)
        self.gone.pop(name, None)
        log.info("server %s (%s) joined: it hosts up to %d service spaces, building up to %d at once", name,
                 address, capacity, self.servers[name].builds)
        self._changed_name(None)
        self._place_waiting_soon()

    def remove_server(self, name, why):
        """A server VM is lost (or leaving): its spaces are torn down (their robots' R items too) and created again
        on the servers with room; the rest wait for room. Fires when each was rebuilt or put in line."""
        if self.servers.get(name) is None or name == self.name:
            return defer.succeed(None)
        self.gone[name] = self.servers.pop(name)
        while len(self.gone) > self.GONE_KEPT:
            self.gone.popitem(last=False)
        self._changed_name(None)
        lost = [self.spaces[n] for n in self.spaces_of(name)]
        log.warning("server %s lost (%s): moving its %d service space(s): %s", name, why, len(lost),
                    ", ".join(s.name for s in lost) or "none")
        for space in lost:
            space.reason = f"its server {name} was lost ({why}); it is being moved"
            self._pairing_may_have_changed(space)
        return defer.gatherResults([self._move(space) for space in lost], consumeErrors=True)

    @defer.inlineCallbacks
    def _move(self, space):
        yield self.teardown(space.name)
        if getattr(space.robot, "ended", False) or space.name in self.spaces or space.name in self.unplaced:
            return                                          # the robot left meanwhile, or was already rebuilt
        yield self.create(space.name, space.logic, space.robot)

    def _place_waiting_soon(self):
        if self.unplaced and self._placing is None:
            self._placing = self.reactor.callLater(0, self._place_waiting)

    def _place_waiting(self):
        """Build the spaces waiting for room, in arrival order, while a server has room."""
        self._placing = None
        while self.unplaced and choose_server(self.servers.values(), self.hosted()) is not None:
            name, (logic, robot) = self.unplaced.popitem(last=False)
            d = self.create(name, logic, robot)
            d.addErrback(lambda f, name=name: log.error("service space %s not created: %s", name,
                                                        f.getErrorMessage()))

    def waiting_reason(self, ss_name):
        """Why ``ss_name`` waits for room (a sentence), or None when it does not."""
        if ss_name not in self.unplaced:
            return None
        hosted = self.hosted()
        limits = ", ".join(f"{s.name} {hosted.get(s.name, 0)}/{s.capacity}" for s in self.servers.values())
        place = list(self.unplaced).index(ss_name) + 1
        return (f"waiting for room: every server hosts as many service spaces as its max_service_spaces allows "
                f"({limits}); number {place} in line")

    def server_rows(self, master_address):
        """The ``platform_instance/read?pi_type=S`` rows: the master first, then the server VMs by name (those no
        longer connected too, with ``connected`` false, until they come back)."""
        master = self.servers[self.name]
        others = [s for s in self.servers.values() if s.host is not None] + list(self.gone.values())
        rows = []
        for server in [master] + sorted(others, key=lambda s: s.name):
            connected = self.servers.get(server.name) is server
            rows.append({"pi_name": server.name, "pi_type": "S", "connected": connected,
                         "address": master_address if server is master else server.address,
                         "max_service_spaces": server.capacity,
                         "service_spaces": self.spaces_of(server.name) if connected else []})
        return rows

    # -- create ---------------------------------------------------------------------------------------------
    @defer.inlineCallbacks
    def create(self, pi_name, service_logic, robot):
        """Build the space of robot ``pi_name``; fires with the ServiceSpace once everything settled.

        The Deferred fires (never fails) when the space is paired or known not to pair (``space.reason`` and
        the items' errors say why); a space that already exists is torn down first. Bad service logic
        (missing fields) fails the Deferred with ValueError before anything starts. A space whose ROS master
        runs on the server side (``ss_side`` S) is placed on the server with the lowest load
        (``choose_server``); with no room anywhere it waits in line (``waiting_reason``) and the Deferred
        fires with None.
        """
        ss_side = str(service_logic.get("ss_side") or "S").upper()
        if ss_side not in ("S", "R"):
            raise ValueError(f"ss_side must be S or R, got {service_logic.get('ss_side')!r}")
        robot_name = getattr(robot, "name", pi_name) if robot is not None else pi_name
        try:
            items = items_of_logic(service_logic)
        except CommandError as exc:
            raise ValueError(f"service logic of {pi_name}: {exc}") from None
        remote = [i for i in items if i.side == "R"]
        if (remote or ss_side == "R") and robot is None:
            raise ValueError(f"service space {pi_name} has robot-side parts but no robot to run them")
        if pi_name in self.spaces:
            yield self.teardown(pi_name)
        self.unplaced.pop(pi_name, None)
        server = self.servers[self.name]
        if ss_side == "S":
            server = choose_server(self.servers.values(), self.hosted())
            if server is None:
                self.unplaced[pi_name] = (service_logic, robot)
                log.warning("service space %s: %s", pi_name, self.waiting_reason(pi_name))
                self._changed_name(pi_name)
                return None
        s_name = self.i_name if server.host is None else server.name
        for item in items:
            item.i_name = s_name if item.side == "S" else robot_name
        space = ServiceSpace(pi_name, ss_side, self.key_prefix, None, s_name)
        space.items = items
        space.robot = robot
        space.logic = service_logic
        space.server, space.host = server.name, server.host
        space.public_ip = self.public_ip if server.host is None else server.address
        self._add_space(space)
        self._changed(space)
        log.info("service space %s: creating on %s (%d S items, %d R items, ROS master on the %s side)", pi_name,
                 server.name, len(items) - len(remote), len(remote), "robot" if ss_side == "R" else "server")
        here_or_server = HERE if server.host is None else server.host   # where the S side runs
        local = [i for i in items if i.side == "S"]
        if ss_side == "S":   # the ROS master where the S side runs; on a server VM, from its own ros_port_base
            parts, master_on = [(here_or_server, local), (robot, remote)], here_or_server
        else:                # the ROS master on the robot, the S items here once it answers
            parts, master_on = [(robot, remote), (HERE, local)], robot
        yield server.building.acquire()      # its turn among the spaces being built on that machine
        try:
            if not space.cancelled:
                yield self._bring_up(space, parts, master_on, self.config.ros_port_base)
        except Exception as exc:  # a bug: keep the space visible (and stoppable) with the reason
            space.reason = f"unexpected error: {exc!r}"
            log.exception("service space %s: unexpected error while creating", pi_name)
            space.settle()
        finally:
            server.building.release()
        if not space.cancelled:
            if space.paired:
                self._notify(space)
            self._changed(space)     # the robot's and server's item reports came with the answers
            level = logging.INFO if space.paired else logging.WARNING
            log.log(level, "service space %s: %s", pi_name,
                    "paired" if space.paired else f"not paired: {space.why_unpaired()}")
        return space

    # -- pairing --------------------------------------------------------------------------------------------
    def _changed(self, space):
        self._changed_name(space.name)

    def _changed_name(self, ss_name):
        for observer in list(self.observers):
            try:
                observer(ss_name)
            except Exception:
                log.exception("observer of service space %s failed", ss_name)

    def _pairing_may_have_changed(self, space):
        self._changed(space)
        if space.state not in (SPACE_PAIRED, SPACE_UNPAIRED):
            return
        paired = space.pairs()
        if paired != space.paired:
            space.transition(SPACE_PAIRED if paired else SPACE_UNPAIRED, "its processes changed")
            if not paired:
                log.warning("service space %s: no longer paired: %s", space.name, space.why_unpaired())
            self._notify(space)

    def _notify(self, space):
        if self.on_state is not None:
            try:
                self.on_state(space.name, space.paired, space)
            except Exception:
                log.exception("on_state callback for %s failed", space.name)

    def item_exited(self, ss_name, report):
        """The robot (or the server hosting the space) says an item (or, kind ``ros_master``, its ROS master)
        of ``ss_name`` ended. Kept as ``received_report`` keeps it; logged through the space's ``Budget`` (a robot
        may report as often as it likes)."""
        space = self.spaces.get(ss_name)
        if space is None or space.cancelled or not isinstance(report, dict):
            return
        report = received_report(report)
        if report["kind"] == "ros_master":
            space.reason = f"the ROS master on {report['i_name']} ended: {report['error']}"
        else:
            for item in space.items:
                if item.remote is not None and (item.kind, item.name) == (report["kind"], report["name"]):
                    item.remote = report
                    break
            else:
                space.notes.warning("service space %s: an unknown item was reported: %s %s", ss_name,
                                          shown(report["kind"], 40), shown(report["name"], 80))
                return
        space.notes.warning("service space %s: %s reports %s %s %s: %s", ss_name, shown(report["i_name"], 80),
                                  report["kind"], report["name"], report["state"], shown(report["error"]))
        self._pairing_may_have_changed(space)

    # -- teardown -------------------------------------------------------------------------------------------
    def teardown(self, pi_name):
        """Stop the space: R items on the robot, S items, then the ROS master. Fires when all are gone."""
        if self.unplaced.pop(pi_name, None) is not None:
            log.info("service space %s: no longer waiting for room", pi_name)
        space = self.spaces.get(pi_name)
        if space is None:
            return defer.succeed(None)
        d = defer.Deferred()
        if space.teardown_waiters is not None:
            space.teardown_waiters.append(d)
            return d
        space.teardown_waiters = [d]
        self._teardown(space)
        return d

    @defer.inlineCallbacks
    def _teardown(self, space):
        was_paired = space.paired
        space.transition(SPACE_STOPPING, "teardown")
        log.info("service space %s: tearing down", space.name)
        try:
            yield self._items_stopping(space)
            has_remote = any(i.side == "R" for i in space.items)
            if space.ss_side == "R":
                yield self._stop_local(space)          # S items first: the ROS master is on the robot
            if space.robot is not None and (has_remote or space.ss_side == "R"):
                yield self._stop_remote(space, space.robot)
            if space.ss_side == "S" and space.host is not None:
                yield self._stop_remote(space, space.host)
            elif space.ss_side == "S":
                yield self._stop_local(space)
        except Exception:
            log.exception("service space %s: teardown error", space.name)
        finally:
            self._drop_space(space)
            space.transition(SPACE_GONE, "torn down")
            log.info("service space %s: torn down", space.name)
            if was_paired:
                self._notify(space)
            self._changed(space)
            waiters, space.teardown_waiters = space.teardown_waiters, []
            for d in waiters:
                d.callback(None)
            self._place_waiting_soon()                 # its room goes to the next in line

    @defer.inlineCallbacks
    def _stop_remote(self, space, host):
        d = host.stop_items(space.name)
        timeout = self.reactor.callLater(self.robot_timeout, d.cancel)
        try:
            yield d
        except Exception as exc:
            log.warning("service space %s: %s did not confirm stopping its items: %s", space.name,
                        getattr(host, "name", "?"), exc)
        finally:
            if timeout.active():
                timeout.cancel()

    @defer.inlineCallbacks
    def teardown_all(self):
        self.unplaced.clear()
        yield defer.gatherResults([self.teardown(name) for name in list(self.spaces)], consumeErrors=True)


# ---------------------------------------------------------------------------------------------------------
# A robot's or a server VM's side.

class ItemRunner(_SpaceHost):
    """What the master asks this agent to run of its service spaces: on a robot, the R items (and the ROS master for
    ``ss_side`` R); on a server VM (``config.role`` "server"), the S side of the spaces the master placed there:
    their ROS master, started from the server's own ``ros_port_base``, and S items (FIROS takes the server's
    ``inbound_open_ports``). Items that die later are told to ``on_item_exited``."""

    key_prefix = "robot"

    def __init__(self, reactor, table, config, env=None, on_item_exited=None, address=None, run_as=None):
        super().__init__(reactor, table, config, env=env, address=address, run_as=run_as)
        self.on_item_exited = on_item_exited
        self.i_name = config.name

    @defer.inlineCallbacks
    def start_items(self, ss_name, ros_master_uri, items, start_ros_master_port=None):
        """Start R items against ``ros_master_uri`` (or a ROS master started here on a free port from
        ``start_ros_master_port`` upward); fires with {"ros_master_uri", "items": [reports]} once each item
        settled or failed. A space of the same name already here is stopped first. An item that is not a
        valid service item fails the Deferred with the sentence naming it (nothing starts)."""
        parsed = []
        for index, entry in enumerate(items or []):
            parsed.append(ServiceItem.from_entry(entry, self.i_name, index))
        if start_ros_master_port and self.config.role == "server":
            start_ros_master_port = self.config.ros_port_base  # the server's own
        if ss_name in self.spaces:
            yield self.stop_items(ss_name)
        space = ServiceSpace(ss_name, "R" if start_ros_master_port else "S", self.key_prefix, None,
                             self.i_name)
        space.items = parsed
        space.ros_master_uri = ros_master_uri
        self.spaces[ss_name] = space
        master_port = int(start_ros_master_port) if start_ros_master_port else None
        problem = yield self._bring_up(space, [(HERE, parsed)], HERE if master_port else None, master_port)
        if problem:
            for item in parsed:
                if item.process is None and item.error is None:
                    item.fail(problem, "space")
        space.told.update((i.kind, i.name) for i in parsed if i.state == FAILED)
        return {"ros_master_uri": space.ros_master_uri, "items": [i.report() for i in parsed],
                "reason": space.reason, "inbound_port": space.inbound_port}

    def _pairing_may_have_changed(self, space):
        if space.state not in (SPACE_PAIRED, SPACE_UNPAIRED) or self.on_item_exited is None:
            return
        for item in space.items:
            if item.state == FAILED and (item.kind, item.name) not in space.told:
                space.told.add((item.kind, item.name))
                self._tell(space, item.report())
        for managed in space.core_processes():
            if managed.state == FAILED and managed.key not in space.told:
                space.told.add(managed.key)
                self._tell(space, {"kind": "ros_master", "name": managed.key.rsplit("/", 1)[-1],
                                   "i_name": self.i_name, "state": FAILED, "error": managed.error})

    def _tell(self, space, report):
        try:
            self.on_item_exited(space.name, report)
        except Exception:
            log.exception("on_item_exited callback for %s failed", space.name)

    @defer.inlineCallbacks
    def stop_items(self, ss_name):
        """Stop every item (and the ROS master, if it runs here) of ``ss_name``; fires when all are gone."""
        space = self.spaces.pop(ss_name, None)
        if space is None:
            return
        log.info("service space %s: stopping the items here", ss_name)
        space.transition(SPACE_STOPPING, "the master asked")
        try:
            yield self._items_stopping(space)
        except Exception:
            log.exception("service space %s: the special items' stop hooks failed", ss_name)
        yield self._stop_local(space)
        space.transition(SPACE_GONE, "stopped")

    @defer.inlineCallbacks
    def stop_all(self):
        yield defer.gatherResults([self.stop_items(name) for name in list(self.spaces)], consumeErrors=True)
