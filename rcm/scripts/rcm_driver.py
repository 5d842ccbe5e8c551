#!/usr/bin/env python3
"""rcm_driver: the ROS node (``rcmdriver``) between the local RCM agent and FIROS.

It owns three things and nothing else:

- the agent side: a TCP server on 127.0.0.1:PORT (default 9998) speaking newline-delimited JSON objects
  (``{"rcm_d_cmd": "r_connection"|"r_disconnection", "r_name": NAME}`` in,
  ``{"rcm_d_cmd": "e_created"|"e_removed", "r_name": NAME}`` out), a few agent connections at once. Started by
  the agent, it has a one-time key in ``RCM_DRIVER_KEY`` and obeys only connections whose first line carries it
  (``"key": KEY``); a connection without it yet is held at most ``PROOF_DEADLINE`` seconds, and when
  ``MAX_UNPROVEN`` such wait the oldest is closed, so other local users can neither speak for the agent nor keep
  it out. Started by hand without a key, it obeys any local connection, as it always did (README.md);
- the ROS side: publishing ``/rcm/robot_event`` (robotics_msgs/Robot_Event) for every agent command, and
  carrying ``/firos/cb_event`` (robotics_msgs/CB_Event) back to the agent connection(s) that announced the robot
  (to every connection when none did);
- the ``/rcm/firos_info`` service (robotics_msgs/FIROS_Info): the topics of the ROS graph the node lives in
  (one service space = one robot), read from the ROS master's API, as JSON text.

Run as ``rosrun rcm rcm_driver.py [port=N]`` (``port:=N`` works too). Every bad input from an agent is a log
line, never a crash; a port already in use is one error line and exit status 1. README.md says more.

What a peer sends reaches the log cut (``_preview``) and through ``WarningBudget``: at most ``WARNING_BURST``
such lines per ``WARNING_PERIOD`` seconds, then one line counting the rest. The RCM agent has the same rule in
``rcm_platform.rcmp_log_guard``, but this package runs on machines where that one is not installed (a robot or
server VM, or a ROS machine with FIROS alone), so it keeps its own few lines of it.
"""

import hmac
import json
import os
import queue
import re
import selectors
import signal
import socket
import sys
import threading
import time

import rosgraph
import rospy
from robotics_msgs.msg import CB_Event, Robot_Event
from robotics_msgs.srv import FIROS_Info, FIROS_InfoResponse

NODE_NAME = "rcmdriver"
LISTEN_HOST = "127.0.0.1"
DEFAULT_PORT = 9998
MAX_LINE_BYTES = 4096            # an agent line longer than this is discarded (a robot name is short)
MAX_PENDING_OUT_BYTES = 1 << 20  # an agent that stops reading is dropped rather than buffered forever
MAX_AGENTS = 8                   # agent connections obeyed at once (the agent opens one per service space)
MAX_UNPROVEN = 16                # connections waiting to show the key; the oldest goes when another comes
PROOF_DEADLINE = 10.0            # seconds a connection has to send its first line with the key
KEY_VARIABLE = "RCM_DRIVER_KEY"  # the one-time key the agent starts rcm_driver with (never on the command line)
WARNING_BURST = 10               # warnings an agent connection (or ROS peer) can cause per window ...
WARNING_PERIOD = 10.0            # ... of this many seconds; the rest are counted in one line
SUBSCRIBER_WAIT = 2.0            # seconds to wait for known subscribers to connect before publishing
STOP_POLL = 0.05                 # seconds between two looks of the main thread at a stop request

ROBOT_EVENT_TOPIC = "/rcm/robot_event"
CB_EVENT_TOPIC = "/firos/cb_event"
FIROS_INFO_SERVICE = "/rcm/firos_info"

# Left out of /rcm/firos_info: the plumbing of the platform itself, not topics of the robot.
EXCLUDED_NODES = frozenset({"/" + NODE_NAME, "/firos"})
EXCLUDED_TOPICS = frozenset({"/rosout", "/rosout_agg", ROBOT_EVENT_TOPIC, CB_EVENT_TOPIC,
                             "/firos/connect", "/firos/disconnect"})

# agent command -> Robot_Event status, and CB_Event status -> answer to the agent
AGENT_COMMANDS = {"r_connection": Robot_Event.CONNECTED, "r_disconnection": Robot_Event.DISCONNECTED}
ENTITY_ANSWERS = {CB_Event.CREATED: "e_created", CB_Event.REMOVED: "e_removed"}
ROBOT_STATUS_WORDS = {Robot_Event.CONNECTED: "CONNECTED", Robot_Event.DISCONNECTED: "DISCONNECTED"}

# Robot names are platform instance names: a letter, then letters, digits and underscores (CONTRACTS §2).
ROBOT_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]*\Z")

USAGE = "usage: rosrun rcm rcm_driver.py [port=N]"


class UsageError(Exception):
    """The command line is wrong; str() is one line for the user."""


class BadLine(Exception):
    """An agent line that cannot be obeyed; str() says why, in one line."""


# ---------------------------------------------------------------------------------------------------------
# Pure helpers (no ROS, no sockets): the command line, the agent's line format, the firos_info answer.

def parse_port(argv):
    """The TCP port from the command line ``argv`` (without the program name).

    Accepts ``port=N`` and ``port:=N``; ROS's own special arguments (``__name:=...``, ``__log:=...``) and
    other remappings are left to rospy. Raises UsageError for anything else.
    """
    port_text = None
    for arg in argv:
        if arg.startswith("port=") or arg.startswith("port:="):
            port_text = arg.split("=", 1)[1]
        elif rosgraph.names.is_legal_remap(arg):
            continue
        else:
            raise UsageError(f"unknown argument {arg!r} ({USAGE})")
    if port_text is None:
        return DEFAULT_PORT
    if not port_text.isdigit() or not 1 <= int(port_text) <= 65535:
        raise UsageError(f"port must be a number from 1 to 65535, got {port_text!r} ({USAGE})")
    return int(port_text)


def rospy_argv(argv):
    """``argv`` without our ``port:=N`` argument, so that rospy does not take it for a topic remapping."""
    return [arg for arg in argv if not arg.startswith("port:=")]


def parse_agent_line(raw):
    """Decode one agent line (bytes, no newline) into ``(command, robot_name)``; raise BadLine if it is bad."""
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise BadLine("line is not UTF-8 text") from None
    try:
        obj = json.loads(text)
    except ValueError as exc:
        raise BadLine(f"line is not JSON ({exc})") from None
    if not isinstance(obj, dict):
        raise BadLine(f"line is JSON {type(obj).__name__}, expected an object")
    command = obj.get("rcm_d_cmd")
    name = obj.get("r_name")
    if command is None:
        raise BadLine('field "rcm_d_cmd" is missing')
    if command not in AGENT_COMMANDS:
        raise BadLine(f"unknown command {_preview(command, 40)} (known: {', '.join(sorted(AGENT_COMMANDS))})")
    if name is None:
        raise BadLine('field "r_name" is missing')
    if not isinstance(name, str) or not ROBOT_NAME.match(name):
        raise BadLine(f"r_name {_preview(name, 60)} is not a robot name (a letter, then letters, digits and "
                      f"underscores)")
    return command, name


def entity_line(robot_name, answer):
    """The line sent to the agent for an entity event: ``{"rcm_d_cmd": answer, "r_name": robot_name}\\n``."""
    return (json.dumps({"rcm_d_cmd": answer, "r_name": robot_name}) + "\n").encode("utf-8")


def graph_topics(system_state, topic_types, excluded_nodes=EXCLUDED_NODES, excluded_topics=EXCLUDED_TOPICS):
    """The robot's topics from the master's ``getSystemState()`` and ``getTopicTypes()`` answers.

    A topic is listed with ``"type": "publisher"`` when a node other than the excluded ones publishes it and
    with ``"type": "subscriber"`` when one subscribes to it (so possibly twice). Topics without a known type
    (only wildcard subscribers) cannot be mapped by FIROS and are left out. Sorted by name, then type.
    """
    publishers, subscribers, _services = system_state
    types = dict(topic_types)
    topics = []
    for role, entries in (("publisher", publishers), ("subscriber", subscribers)):
        for name, nodes in entries:
            msg = types.get(name)
            if name in excluded_topics or not msg or msg == "*":
                continue
            if any(node not in excluded_nodes for node in nodes):
                topics.append({"name": name, "msg": msg, "type": role})
    topics.sort(key=lambda t: (t["name"], t["type"]))
    return topics


def firos_info_json(instance_name, topics):
    """The ``json_format`` answer of /rcm/firos_info."""
    return json.dumps({instance_name: {"topics": topics}})


def line_key(raw):
    """The ``key`` field of an agent line (bytes), or None when it has none or is not a JSON object."""
    try:
        obj = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, ValueError):
        return None
    key = obj.get("key") if isinstance(obj, dict) else None
    return key if isinstance(key, str) else None


class WarningBudget:
    """At most ``burst`` warnings per window of ``period`` seconds; the first warning of a later window first says
    how many were left out. (The agent's ``rcmp_log_guard.Budget`` in a dozen lines: see the module docstring.)"""

    def __init__(self, burst=WARNING_BURST, period=WARNING_PERIOD, clock=time.monotonic):
        self.burst, self.period, self.clock = burst, period, clock
        self.start, self.written, self.left_out = None, 0, 0

    def warn(self, message, *args):
        now = self.clock()
        if self.start is None or now >= self.start + self.period:
            if self.left_out:
                rospy.logwarn("rcm_driver: %d more warnings were left out of the log in the last %.0f s",
                              self.left_out, self.period)
            self.start, self.written, self.left_out = now, 0, 0
        if self.written < self.burst:
            self.written += 1
            rospy.logwarn(message, *args)
        else:
            self.left_out += 1


# ---------------------------------------------------------------------------------------------------------
# The agent side: one thread with a selector, every socket non-blocking, all socket work in that thread.

class AgentConnection:
    """One agent's TCP connection: what it sent so far, what waits to be sent, which robots it announced, and
    whether it showed the key (``proven``; always, when rcm_driver has none) or must by ``deadline``."""

    def __init__(self, sock, peer, proven, deadline):
        self.sock = sock
        self.peer = peer
        self.proven = proven
        self.deadline = deadline
        self.inbuf = bytearray()
        self.outbuf = bytearray()
        self.discarding = False      # inside an overlong line: drop bytes until its newline
        self.announced = set()       # robot names this connection sent a command about


class AgentServer:
    """The TCP server for local RCM agents.

    ``on_command(command, robot_name)`` is called (in the server thread) for every good line of a connection that
    showed ``key`` (every connection's, without a key). ``send_entity_event`` may be called from any thread; the
    server thread does the sending.
    """

    def __init__(self, listen_sock, on_command, max_pending_out=MAX_PENDING_OUT_BYTES, key=None,
                 proof_deadline=PROOF_DEADLINE):
        self.listen_sock = listen_sock
        self.on_command = on_command
        self.max_pending_out = max_pending_out
        self.key = key
        self.proof_deadline = proof_deadline
        self.warnings = WarningBudget()
        self.selector = selectors.DefaultSelector()
        self.clients = {}                          # socket -> AgentConnection (in the order they came)
        self.pending = []                          # (robot_name, answer) waiting for the server thread
        self.lock = threading.Lock()
        self.stopping = False
        self.failed = False                        # the server thread ended on an unexpected error
        self.wake_r, self.wake_w = socket.socketpair()
        self.wake_r.setblocking(False)
        self.wake_w.setblocking(False)
        self.thread = threading.Thread(target=self._run, name="agent-server", daemon=True)

    @staticmethod
    def bind(port, host=LISTEN_HOST):
        """A listening socket on host:port; raises OSError (address in use, ...) for the caller to report."""
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((host, port))
            sock.listen(16)
            sock.setblocking(False)
        except OSError:
            sock.close()
            raise
        return sock

    def start(self):
        self.selector.register(self.listen_sock, selectors.EVENT_READ, "listen")
        self.selector.register(self.wake_r, selectors.EVENT_READ, "wake")
        self.thread.start()

    def send_entity_event(self, robot_name, answer):
        """Queue an entity event for the agent(s); thread-safe."""
        with self.lock:
            self.pending.append((robot_name, answer))
        self._wake()

    def stop(self, timeout=5.0):
        """Close every connection and the listening socket; returns when the server thread has ended."""
        self.stopping = True
        self._wake()
        if self.thread.is_alive():
            self.thread.join(timeout)

    def _wake(self):
        try:
            self.wake_w.send(b"x")
        except (BlockingIOError, OSError):
            pass  # already woken (buffer full) or closing

    def _run(self):
        try:
            while not self.stopping:
                ready = self.selector.select(self._until_next_deadline())
                # what connections sent first, then new connections: an agent's first line is read before a
                # flood of new connections can push its connection out of the waiting ones
                for key, events in sorted(ready, key=lambda pair: pair[0].data == "listen"):
                    if key.data == "listen":
                        self._accept()
                    elif key.data == "wake":
                        self._drain_wake()
                    else:
                        client = key.data
                        if events & selectors.EVENT_READ and client.sock in self.clients:
                            self._read(client)
                        if events & selectors.EVENT_WRITE and client.sock in self.clients:
                            self._flush(client)
                self._deliver_pending()
                self._drop_overdue()
        except Exception as exc:  # a bug here must be visible, must not leave sockets open, and stops the node
            rospy.logerr("rcm_driver: agent server stopped by an unexpected error: %r; stopping the node", exc)
            self.failed = True
        finally:
            self._close_all()

    def _drain_wake(self):
        try:
            while self.wake_r.recv(4096):
                pass
        except BlockingIOError:
            pass

    def _accept(self):
        try:
            sock, addr = self.listen_sock.accept()
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            self.warnings.warn("rcm_driver: accepting an agent connection failed: %s", exc)
            return
        sock.setblocking(False)
        proven = self.key is None
        client = AgentConnection(sock, f"{addr[0]}:{addr[1]}", proven, time.monotonic() + self.proof_deadline)
        if proven and self._count(proven=True) >= MAX_AGENTS:
            sock.close()
            self.warnings.warn("rcm_driver: connection from %s refused: %d agent connections are open already",
                               client.peer, MAX_AGENTS)
            return
        unproven = [c for c in self.clients.values() if not c.proven]
        if not proven and len(unproven) >= MAX_UNPROVEN:
            self._close(unproven[0], "another connection came while it still had not shown the key", warn=True)
        self.clients[sock] = client
        self.selector.register(sock, selectors.EVENT_READ, client)
        if proven:
            rospy.loginfo("rcm_driver: agent %s connected (%d connection(s))", client.peer, self._count(True))
        else:
            self._read(client)       # an agent writes its first line as it connects: often it is here already

    def _count(self, proven):
        return sum(1 for c in self.clients.values() if c.proven == proven)

    def _until_next_deadline(self):
        deadlines = [c.deadline for c in self.clients.values() if not c.proven]
        return max(0.0, min(deadlines) - time.monotonic()) if deadlines else None

    def _drop_overdue(self):
        now = time.monotonic()
        for client in [c for c in self.clients.values() if not c.proven and c.deadline <= now]:
            self._close(client, f"no line with the key within {self.proof_deadline:g} s", warn=True)

    def _read(self, client):
        try:
            data = client.sock.recv(65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            self._close(client, f"read failed: {exc}", warn=True)
            return
        if not data:
            self._close(client, "closed by the agent")
            return
        client.inbuf += data
        while client.sock in self.clients:
            end = client.inbuf.find(b"\n")
            if end < 0:
                break
            line = bytes(client.inbuf[:end])
            del client.inbuf[:end + 1]
            if client.discarding:
                client.discarding = False  # the rest of an overlong line, already reported
                continue
            self._handle_line(client, line)
        if client.sock in self.clients and len(client.inbuf) > MAX_LINE_BYTES:
            if not client.proven:
                self._close(client, f"a first line longer than {MAX_LINE_BYTES} bytes", warn=True)
                return
            self.warnings.warn("rcm_driver: agent %s: line longer than %d bytes discarded",
                               client.peer, MAX_LINE_BYTES)
            client.inbuf.clear()
            client.discarding = True

    def _handle_line(self, client, line):
        line = line.rstrip(b"\r")
        if not line.strip():
            return
        if len(line) > MAX_LINE_BYTES:
            if not client.proven:
                self._close(client, f"a first line longer than {MAX_LINE_BYTES} bytes", warn=True)
                return
            self.warnings.warn("rcm_driver: agent %s: line longer than %d bytes discarded",
                               client.peer, MAX_LINE_BYTES)
            return
        if not client.proven and not self._prove(client, line):
            return
        try:
            command, name = parse_agent_line(line)
        except BadLine as exc:
            self.warnings.warn("rcm_driver: agent %s: bad line ignored: %s: %s", client.peer, exc, _preview(line))
            return
        client.announced.add(name)
        rospy.loginfo("rcm_driver: agent %s: %s %s", client.peer, command, name)
        self.on_command(command, name)

    def _prove(self, client, line):
        """The first line of a connection: it carries the key (the connection is an agent's from now on), or the
        connection is closed. False when closed."""
        key = line_key(line)
        if key is None or not hmac.compare_digest(key.encode("utf-8"), self.key.encode("utf-8")):
            self._close(client, "its first line does not carry the key the agent started rcm_driver with", warn=True)
            return False
        if self._count(proven=True) >= MAX_AGENTS:
            self._close(client, f"{MAX_AGENTS} agent connections are open already", warn=True)
            return False
        client.proven = True
        rospy.loginfo("rcm_driver: agent %s connected with the key (%d agent connection(s))", client.peer,
                      self._count(proven=True))
        return True

    def _deliver_pending(self):
        with self.lock:
            pending, self.pending = self.pending, []
        for robot_name, answer in pending:
            agents = [c for c in self.clients.values() if c.proven]
            targets = [c for c in agents if robot_name in c.announced] or agents
            if not targets:
                self.warnings.warn("rcm_driver: %s for %s not delivered: no agent is connected", answer, robot_name)
                continue
            data = entity_line(robot_name, answer)
            for client in targets:
                client.outbuf += data
                self._flush(client)
            rospy.loginfo("rcm_driver: %s %s sent to %s", answer, robot_name,
                          ", ".join(c.peer for c in targets))

    def _flush(self, client):
        if client.sock not in self.clients:
            return
        try:
            while client.outbuf:
                sent = client.sock.send(client.outbuf)
                del client.outbuf[:sent]
        except (BlockingIOError, InterruptedError):
            pass
        except OSError as exc:
            self._close(client, f"write failed: {exc}", warn=True)
            return
        if len(client.outbuf) > self.max_pending_out:
            self._close(client, f"it does not read its answers ({len(client.outbuf)} bytes waiting)", warn=True)
            return
        events = selectors.EVENT_READ | (selectors.EVENT_WRITE if client.outbuf else 0)
        self.selector.modify(client.sock, events, client)

    def _close(self, client, why, warn=False):
        if self.clients.pop(client.sock, None) is None:
            return
        try:
            self.selector.unregister(client.sock)
        except (KeyError, ValueError):
            pass
        client.sock.close()
        if not client.proven:   # anyone can cause these: through the budget
            self.warnings.warn("rcm_driver: connection from %s closed: %s", client.peer, why)
            return
        log = self.warnings.warn if warn else rospy.loginfo
        log("rcm_driver: agent %s disconnected (%s); %d connection(s) left", client.peer, why, self._count(True))

    def _close_all(self):
        for client in list(self.clients.values()):
            self._close(client, "rcm_driver is stopping")
        for sock in (self.listen_sock, self.wake_r):
            try:
                self.selector.unregister(sock)
            except (KeyError, ValueError):
                pass
            sock.close()
        self.wake_w.close()
        self.selector.close()


def _preview(value, limit=120):
    """A peer's line (bytes) or name (str) for the log: its repr, cut to ``limit`` characters."""
    text = value.decode("utf-8", "replace") if isinstance(value, bytes) else str(value)
    return repr(text if len(text) <= limit else text[:limit] + "...")


# ---------------------------------------------------------------------------------------------------------
# The ROS side.

class RobotEventPublisher:
    """Publishes Robot_Event on /rcm/robot_event, in order, from its own thread.

    The topic is latched, so a FIROS that subscribes later still gets the newest event. And since a rospy
    Publisher drops what is published while a subscriber is still connecting, each event first waits (up to
    SUBSCRIBER_WAIT seconds) until every subscriber the master knows of is connected to us.
    """

    def __init__(self):
        self.publisher = rospy.Publisher(ROBOT_EVENT_TOPIC, Robot_Event, queue_size=100, latch=True)
        self.events = queue.Queue()
        self.stopping = threading.Event()
        self.thread = threading.Thread(target=self._run, name="robot-event-publisher", daemon=True)

    def start(self):
        self.thread.start()

    def submit(self, robot_name, status):
        self.events.put((robot_name, status))

    def stop(self, timeout=5.0):
        self.stopping.set()
        self.events.put(None)
        if self.thread.is_alive():
            self.thread.join(timeout)

    def _run(self):
        while True:
            event = self.events.get()
            if event is None or self.stopping.is_set():
                return
            robot_name, status = event
            try:
                self._wait_for_subscribers()
                self.publisher.publish(Robot_Event(instance_name=robot_name, instance_status=status))
            except Exception as exc:  # rospy raises ROSException subclasses once shutting down
                rospy.logerr("rcm_driver: publishing Robot_Event for %s failed: %s", robot_name, exc)
                continue
            rospy.loginfo("rcm_driver: published Robot_Event %s %s on %s (%d subscriber(s))",
                          robot_name, ROBOT_STATUS_WORDS[status], ROBOT_EVENT_TOPIC,
                          self.publisher.get_num_connections())

    def _wait_for_subscribers(self):
        try:
            _pubs, subs, _srvs = rosgraph.Master(rospy.get_name()).getSystemState()
        except Exception as exc:
            rospy.logwarn("rcm_driver: cannot ask the ROS master for subscribers of %s: %s",
                          ROBOT_EVENT_TOPIC, exc)
            return
        expected = len(next((nodes for name, nodes in subs if name == ROBOT_EVENT_TOPIC), []))
        deadline = time.monotonic() + SUBSCRIBER_WAIT
        while self.publisher.get_num_connections() < expected and time.monotonic() < deadline:
            if self.stopping.wait(0.02):
                return
        if self.publisher.get_num_connections() < expected:
            rospy.logwarn("rcm_driver: only %d of %d subscriber(s) of %s connected after %.0f s; publishing anyway",
                          self.publisher.get_num_connections(), expected, ROBOT_EVENT_TOPIC, SUBSCRIBER_WAIT)


class RcmDriver:
    """The node: the agent server, the Robot_Event publisher, the CB_Event subscriber, the firos_info service."""

    def __init__(self, listen_sock, key=None):
        self.robot_events = RobotEventPublisher()
        self.server = AgentServer(listen_sock, self._on_agent_command, key=key)
        self.subscriber = rospy.Subscriber(CB_EVENT_TOPIC, CB_Event, self._on_cb_event, queue_size=100)
        self.service = rospy.Service(FIROS_INFO_SERVICE, FIROS_Info, self._on_firos_info)

    def start(self):
        self.robot_events.start()
        self.server.start()

    def stop(self):
        self.server.stop()
        self.robot_events.stop()
        try:
            self.subscriber.unregister()
            self.service.shutdown("rcm_driver is stopping")
        except Exception as exc:  # rospy may already have let go of them while shutting down
            rospy.logdebug("rcm_driver: releasing ROS handles: %s", exc)

    def _on_agent_command(self, command, robot_name):
        self.robot_events.submit(robot_name, AGENT_COMMANDS[command])

    def _on_cb_event(self, msg):
        answer = ENTITY_ANSWERS.get(msg.entity_status)
        if answer is None:
            self.server.warnings.warn("rcm_driver: CB_Event for %s with unknown entity_status %d ignored (expected %d "
                                      "or %d)", _preview(msg.entity_name), msg.entity_status, CB_Event.CREATED,
                                      CB_Event.REMOVED)
            return
        if not ROBOT_NAME.match(msg.entity_name):
            self.server.warnings.warn("rcm_driver: CB_Event with entity_name %s ignored: not a robot name",
                                      _preview(msg.entity_name))
            return
        self.server.send_entity_event(msg.entity_name, answer)

    def _on_firos_info(self, request):
        try:
            master = rosgraph.Master(rospy.get_name())
            state = master.getSystemState()
            types = master.getTopicTypes()
        except Exception as exc:
            rospy.logerr("rcm_driver: firos_info for %s: cannot read the ROS graph: %s",
                         _preview(request.instance_name), exc)
            raise rospy.ServiceException(f"cannot read the ROS graph from the master: {exc}") from None
        excluded = EXCLUDED_NODES | {rospy.get_name()}
        topics = graph_topics(state, types, excluded_nodes=excluded)
        rospy.loginfo("rcm_driver: firos_info for %s: %d topic entries", _preview(request.instance_name), len(topics))
        return FIROS_InfoResponse(json_format=firos_info_json(request.instance_name, topics))


class StopSignals:
    """SIGINT/SIGTERM handling that is safe in a threaded rospy process.

    rospy's own handlers run its whole shutdown inside the signal handler, on the main thread, wherever that
    thread was interrupted. We saw it hang for good: the main thread was inside rospy.loginfo, whose /rosout
    handler was in an XML-RPC call to the master holding rospy's non-reentrant ServerProxy lock
    (rospy/core.py _LockedServerProxy); the handler's shutdown made its own XML-RPC call (unregistering) and
    waited on that lock forever. Here the handler only records the signal and the main loop shuts down in
    ordinary code. Before the node is up (rospy.init_node waits for the master for as long as it takes) the
    handler ends the process at once instead: nothing of ours is running yet.
    """

    def __init__(self):
        self.received = None
        self.node_up = False

    def install(self):
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, self._handle)

    def _handle(self, signum, _frame):
        if not self.node_up:
            os.write(2, f"rcm_driver: stopped by signal {signum} before the node started\n".encode())
            os._exit(0)
        self.received = signum


def main(argv=None):
    argv = sys.argv if argv is None else argv
    key = os.environ.pop(KEY_VARIABLE, "") or None   # the agent's; nothing this node starts needs it
    try:
        port = parse_port(argv[1:])
    except UsageError as exc:
        print(f"rcm_driver: {exc}", file=sys.stderr)
        return 2
    try:
        listen_sock = AgentServer.bind(port)
    except OSError as exc:
        reason = exc.strerror or str(exc)
        print(f"rcm_driver: cannot listen on {LISTEN_HOST}:{port}: {reason}", file=sys.stderr)
        return 1
    # rospy's console handler does not flush; when our output goes to a file, flush each line
    sys.stdout.reconfigure(line_buffering=True)
    stop = StopSignals()
    stop.install()
    try:
        rospy.init_node(NODE_NAME, argv=rospy_argv(argv), disable_signals=True)
    except rospy.ROSException as exc:
        listen_sock.close()
        print(f"rcm_driver: cannot start the ROS node: {exc}", file=sys.stderr)
        return 1
    driver = RcmDriver(listen_sock, key)
    driver.start()
    stop.node_up = True
    rospy.loginfo("rcm_driver: listening for RCM agents on %s:%d; publishing %s, subscribed to %s, serving %s",
                  LISTEN_HOST, port, ROBOT_EVENT_TOPIC, CB_EVENT_TOPIC, FIROS_INFO_SERVICE)
    if key is None:
        rospy.logwarn("rcm_driver: started without %s: any local user may send r_connection and r_disconnection "
                      "on port %d (the RCM agent always starts it with a key)", KEY_VARIABLE, port)
    while stop.received is None and not rospy.is_shutdown() and not driver.server.failed:
        time.sleep(STOP_POLL)
    if stop.received is not None:
        reason = f"signal {stop.received}"
    elif driver.server.failed:
        reason = "agent server failed"
    else:
        reason = "ROS shut the node down"
    rospy.loginfo("rcm_driver: stopping (%s)", reason)
    driver.stop()
    rospy.signal_shutdown(reason)
    rospy.loginfo("rcm_driver: stopped")
    return 1 if driver.server.failed else 0


if __name__ == "__main__":
    sys.exit(main())
