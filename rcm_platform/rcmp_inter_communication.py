"""The agent-to-agent wire protocol: framing, version, request ids, timeouts, size limit, server and client.

One TCP connection per robot, opened by the robot and used both ways. Each frame is a 4-byte big-endian length
followed by a UTF-8 JSON object::

    {"v": 1, "id": <int>, "kind": "req" | "res" | "err", "op": <str>, "body": {...}}

A request (``req``) is answered by exactly one ``res`` (body = the result) or ``err`` (body =
``{"code", "reason"}``) carrying the same ``id`` and ``op``. Either side may send requests at any time.

Rules (``docs/PROTOCOL.md`` is the reference):
- a frame longer than ``MAX_FRAME`` bytes, a frame that is not a JSON object (or is nested too deeply to parse),
  or a frame without a usable ``id``/``kind``/``op`` is a protocol error: it is logged and the connection is
  closed;
- a connection a listener accepted is *not admitted* until its owner calls ``peer.admit()`` (the master does on
  an accepted hello): until then its frames are at most ``MAX_FRAME_BEFORE_ADMISSION`` bytes and it may send at
  most ``MAX_BYTES_BEFORE_ADMISSION`` bytes in all, so a stranger costs a few KB at most;
- a listener holds at most ``max_connections`` connections, and at most ``max_per_address`` from one source
  address; a connection over a cap is closed as soon as it is accepted, before anything is read. The counting
  is ``ConnectionCaps``, which the RDAPI's listener and the console's streams use too;
- a request with an unknown version or an op the receiver does not serve gets an ``err`` answer and the
  connection stays open;
- every request has a timeout: its Deferred fails with ``RequestTimeout`` and a late answer is ignored;
- when the connection goes, every pending request fails with ``PeerGone``;
- both ends set ``TCP_NODELAY``: frames are small and answered at once (a heartbeat held back by Nagle's algorithm
  waits for the peer's delayed acknowledgement, tens of milliseconds).

This module knows nothing of robots: what the ops mean is ``rcmp_event``'s business. A connection's owner gives
it a *handler* with ``request_received(peer, op, body) -> value | Deferred`` (raise ``Refused`` for an ``err``
answer) and, optionally, ``peer_connected(peer)`` and ``peer_lost(peer, reason)``.

Also the agent's other wire: ``DriverLink``, its end of the connection to a service space's ``rcm_driver``
(CONTRACTS §4: one JSON object per line, ``{"rcm_d_cmd", "r_name"}`` both ways, and the one-time ``key`` the
agent gave that rcm_driver), and ``connect_driver``; and the JSON every listener of the agent sends
(``strict_dumps``: never a bare ``NaN`` or ``Infinity``, which strict parsers such as a browser's ``JSON.parse``
refuse; ``json_safe`` writes such numbers as the strings ``"NaN"``, ``"Infinity"``, ``"-Infinity"``).
"""

import json
import logging
import math
import random
import re
import resource
import socket

from twisted.application.internet import backoffPolicy
from twisted.internet import defer, endpoints, protocol
from twisted.protocols.basic import Int32StringReceiver, LineReceiver
from twisted.python import failure

from .rcmp_log_guard import Budget, shown

log = logging.getLogger("rcmp.ic")

PROTOCOL_VERSION = 1
MAX_FRAME = 1024 * 1024          # bytes of JSON in one frame
MAX_FRAME_DEPTH = 16             # levels of JSON nesting in one frame (a message uses about 5)
MAX_FRAME_BEFORE_ADMISSION = 4096           # bytes of JSON in one frame from a peer not admitted yet
MAX_BYTES_BEFORE_ADMISSION = 64 * 1024      # bytes a peer may send in all before it is admitted
MAX_PER_ADDRESS = 8              # connections a listener accepts from one source address
MAX_UNANSWERED = 1024            # connections not admitted yet above which a listener stops accepting for a while
SOMAXCONN = "/proc/sys/net/core/somaxconn"   # the kernel's cap on a listener's accept queue
OP_RE = re.compile(r"[a-z][a-z_]{0,31}\Z")
DEFAULT_TIMEOUT = 10.0           # seconds a request waits for its answer
KINDS = ("req", "res", "err")


class ProtocolError(Exception):
    """The peer broke the framing rules; the connection is closed."""


class Refused(Exception):
    """Raised by a handler to answer a request with ``err``: ``code`` is a short word, str() a sentence."""

    def __init__(self, reason, code="refused"):
        super().__init__(reason)
        self.code = code
        self.reason = reason


class RemoteError(Exception):
    """The peer answered our request with ``err``."""

    def __init__(self, op, code, reason):
        super().__init__(f"{op}: {reason} ({code})")
        self.op = op
        self.code = code
        self.reason = reason


class RequestTimeout(Exception):
    """No answer to our request within its timeout."""


class PeerGone(Exception):
    """The connection closed before our request was answered."""


NON_FINITE = {"nan": "NaN", "inf": "Infinity", "-inf": "-Infinity"}   # how JSON out shows such floats


def json_safe(value):
    """``value`` (JSON-like: dicts, lists, tuples, scalars) with every float JSON cannot carry (NaN, Infinity,
    -Infinity) written as the strings ``"NaN"``, ``"Infinity"``, ``"-Infinity"`` (as FIROS writes them), keys too."""
    if isinstance(value, float):
        return value if math.isfinite(value) else NON_FINITE[repr(value)]
    if isinstance(value, dict):
        return {json_safe(k) if isinstance(k, float) else k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    return value


def strict_dumps(value, **kwargs):
    """``json.dumps(value, allow_nan=False, **kwargs)`` of ``json_safe(value)``: what any listener of the agent
    sends. Values without such floats (nearly all) are encoded once, as they are."""
    try:
        return json.dumps(value, allow_nan=False, **kwargs)
    except ValueError:
        return json.dumps(json_safe(value), allow_nan=False, **kwargs)


def encode_frame(message):
    """The JSON bytes of one message (without the length prefix); ProtocolError when over MAX_FRAME."""
    data = strict_dumps(message, separators=(",", ":"), ensure_ascii=False).encode("utf-8")
    if len(data) > MAX_FRAME:
        raise ProtocolError(f"a {message.get('op')!r} frame of {len(data)} bytes is over the "
                            f"{MAX_FRAME}-byte limit")
    return data


def json_depth(value, limit):
    """How deeply ``value`` (a decoded JSON value) nests lists and objects, counted without recursion and
    without looking further down than ``limit + 1`` levels (enough to tell that it is over ``limit``)."""
    deepest, pending = 0, [(value, 1)]
    while pending:
        item, level = pending.pop()
        if isinstance(item, dict):
            item = list(item.values())
        if isinstance(item, list):
            deepest = max(deepest, level)
            if level <= limit:
                pending.extend((child, level + 1) for child in item)
    return deepest


def decode_frame(data):
    """Parse one frame's bytes into a message dict; ProtocolError when it cannot be understood at all."""
    try:
        message = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise ProtocolError(f"frame is not UTF-8 JSON: {exc}") from None
    except RecursionError:
        raise ProtocolError("frame is JSON nested too deeply to parse") from None
    if json_depth(message, MAX_FRAME_DEPTH) > MAX_FRAME_DEPTH:   # Python 3.13 parses what 3.12 refused
        raise ProtocolError(f"frame is JSON nested too deeply (more than {MAX_FRAME_DEPTH} levels)")
    if not isinstance(message, dict):
        raise ProtocolError("frame is not a JSON object")
    msg_id = message.get("id")
    if not isinstance(msg_id, int) or isinstance(msg_id, bool) or msg_id < 0:
        raise ProtocolError("frame has no non-negative integer 'id'")
    if message.get("kind") not in KINDS:
        raise ProtocolError(f"frame has kind {message.get('kind')!r}, expected one of {', '.join(KINDS)}")
    if not isinstance(message.get("op"), str) or not OP_RE.match(message["op"]):
        raise ProtocolError("frame has no 'op' string of 1 to 32 lowercase letters and underscores")
    body = message.get("body", {})
    if not isinstance(body, dict):
        raise ProtocolError("frame 'body' is not a JSON object")
    message["body"] = body
    return message


class Peer(Int32StringReceiver):
    """One end of an agent-to-agent connection.

    ``request(op, body, timeout)`` sends a request and returns a Deferred firing with the answer's body.
    ``last_heard`` is the reactor time of the last frame received (or of the connection), for heartbeats.
    ``admitted`` is False for a connection a listener accepted until its owner calls ``admit()``: until then
    frames are limited to ``MAX_FRAME_BEFORE_ADMISSION`` bytes and the whole connection to
    ``MAX_BYTES_BEFORE_ADMISSION`` bytes received. Connections we open are admitted from the start.
    """

    MAX_LENGTH = MAX_FRAME

    def __init__(self, handler, reactor, admitted=True):
        self.handler = handler
        self.reactor = reactor
        self.admitted = admitted
        self.MAX_LENGTH = MAX_FRAME if admitted else MAX_FRAME_BEFORE_ADMISSION
        self.received = 0            # bytes received before admission
        self.aborted = False
        self.next_id = 1
        self.pending = {}            # id -> (op, Deferred, timeout call)
        self.connected_at = None
        self.last_heard = None
        self.closed = False
        self.close_reason = None
        self.info = {}               # free for the owner (e.g. the robot's name once it said hello)
        self.host = "?"              # the connection's source address (never what the peer claims)
        self.remote = "?"

    # -- connection -------------------------------------------------------------------------------------
    def connectionMade(self):
        # frames are small and answered at once: Nagle's algorithm would hold each behind the peer's delayed ack
        no_delay = getattr(self.transport, "setTcpNoDelay", None)
        if no_delay is not None:
            no_delay(True)
        self.connected_at = self.last_heard = self.reactor.seconds()
        peer = self.transport.getPeer()
        self.host = getattr(peer, "host", "?")
        self.remote = f"{self.host}:{getattr(peer, 'port', '?')}"
        log.debug("connection with %s made", self.remote)
        connected = getattr(self.handler, "peer_connected", None)
        if connected:
            connected(self)

    def connectionLost(self, reason=protocol.connectionDone):
        self.closed = True
        self._unprocessed = b""      # an unfinished frame's bytes go now, not when the Peer is collected
        gone = getattr(self.factory, "peer_gone", None) if hasattr(self, "factory") else None
        if gone:
            gone(self)
        why = self.close_reason or reason.getErrorMessage()
        pending, self.pending = self.pending, {}
        for op, d, call in pending.values():
            if call.active():
                call.cancel()
            d.errback(PeerGone(f"connection to {self.remote} closed before {op!r} was answered: {why}"))
        lost = getattr(self.handler, "peer_lost", None)
        if lost:
            lost(self, why)

    def close(self, reason="closed"):
        """Close the connection (flushing what was written); pending requests fail with PeerGone."""
        if not self.closed and self.transport is not None:
            self.close_reason = reason
            self.transport.loseConnection()

    def abort(self, reason):
        """Drop the connection at once (nothing more is read or written)."""
        if not self.closed and not self.aborted and self.transport is not None:
            self.aborted = True
            self.close_reason = reason
            self.transport.abortConnection()

    def admit(self):
        """The owner trusts this peer now: full-size frames, no byte budget."""
        if not self.admitted:
            admitted = getattr(getattr(self, "factory", None), "peer_admitted", None)
            if admitted is not None:
                admitted(self)
        self.admitted = True
        self.MAX_LENGTH = MAX_FRAME

    # -- sending ----------------------------------------------------------------------------------------
    def _send(self, message):
        self.sendString(encode_frame(message))

    def request(self, op, body=None, timeout=DEFAULT_TIMEOUT):
        """Send request ``op`` with ``body``; the Deferred fires with the answer's body.

        It fails with RemoteError (``err`` answer), RequestTimeout, PeerGone or ProtocolError (our frame too big).
        """
        if self.closed:
            return defer.fail(PeerGone(f"connection to {self.remote} is closed; {op!r} not sent"))
        msg_id = self.next_id
        self.next_id += 1
        try:
            self._send({"v": PROTOCOL_VERSION, "id": msg_id, "kind": "req", "op": op, "body": body or {}})
        except ProtocolError as exc:
            return defer.fail(exc)
        d = defer.Deferred()
        call = self.reactor.callLater(timeout, self._timed_out, msg_id)
        self.pending[msg_id] = (op, d, call)
        return d

    def _timed_out(self, msg_id):
        op, d, _ = self.pending.pop(msg_id)
        d.errback(RequestTimeout(f"no answer from {self.remote} to {op!r} (request {msg_id})"))

    def _answer(self, msg_id, op, kind, body):
        if self.closed:
            return
        try:
            self._send({"v": PROTOCOL_VERSION, "id": msg_id, "kind": kind, "op": op, "body": body})
        except ProtocolError as exc:
            log.error("answer to %s request %s from %s not sent: %s", op, msg_id, self.remote, exc)
            self._send({"v": PROTOCOL_VERSION, "id": msg_id, "kind": "err", "op": op,
                        "body": {"code": "too_large", "reason": str(exc)}})

    # -- receiving --------------------------------------------------------------------------------------
    def _warn(self, message, *args):
        """A warning about this peer; for a peer not admitted yet, through the listener's rate limit (strangers
        must not be able to roll the log over)."""
        limited = getattr(getattr(self, "factory", None), "warn_limited", None)
        if limited is not None and not self.admitted:
            limited(message, *args)
        else:
            log.warning(message, *args)

    def dataReceived(self, data):
        if self.closed or self.aborted:
            return
        if not self.admitted:
            self.received += len(data)
            if self.received > MAX_BYTES_BEFORE_ADMISSION:
                self._warn("closing the connection from %s: over %d bytes sent before being admitted",
                           self.remote, MAX_BYTES_BEFORE_ADMISSION)
                self.abort("too much sent before being admitted")
                return
        super().dataReceived(data)

    def lengthLimitExceeded(self, length):
        self._warn("protocol error from %s: frame of %d bytes is over the %d-byte limit%s; closing",
                   self.remote, length, self.MAX_LENGTH, "" if self.admitted else " before admission")
        self._unprocessed = b""
        self.abort(f"protocol error: frame of {length} bytes over the limit")

    def stringReceived(self, data):
        if self.closed or self.aborted:
            return
        self.last_heard = self.reactor.seconds()
        try:
            message = decode_frame(data)
        except ProtocolError as exc:
            self._warn("protocol error from %s: %s; closing", self.remote, exc)
            self.abort(f"protocol error: {exc}")
            return
        msg_id, kind, op, body = message["id"], message["kind"], message["op"], message["body"]
        if kind == "req":
            if message.get("v") != PROTOCOL_VERSION:
                self._answer(msg_id, op, "err", {
                    "code": "unsupported_version",
                    "reason": f"protocol version {message.get('v')!r} is not supported; this agent speaks "
                              f"version {PROTOCOL_VERSION}"})
                return
            self._dispatch(msg_id, op, body)
            return
        entry = self.pending.pop(msg_id, None)
        if entry is None:
            log.debug("answer %s %s from %s matches no pending request (late or unknown); ignored",
                      kind, msg_id, self.remote)
            return
        sent_op, d, call = entry
        if call.active():
            call.cancel()
        if kind == "res":
            d.callback(body)
        else:
            d.errback(RemoteError(sent_op, str(body.get("code", "error")), str(body.get("reason", body))))

    def _dispatch(self, msg_id, op, body):
        d = defer.maybeDeferred(self.handler.request_received, self, op, body)

        def answered(result):
            self._answer(msg_id, op, "res", result if isinstance(result, dict) else {})

        def failed(reason: failure.Failure):
            if reason.check(Refused):
                err = reason.value
                self._answer(msg_id, op, "err", {"code": err.code, "reason": err.reason})
            else:
                log.error("handling %s request from %s failed: %s", op, self.remote,
                          reason.getTraceback())
                self._answer(msg_id, op, "err", {"code": "internal",
                                                 "reason": f"{op} failed: {reason.getErrorMessage()}"})

        d.addCallbacks(answered, failed)
        d.addErrback(lambda f: log.error("answering %s to %s: %s", op, self.remote, f.getErrorMessage()))


class PeerFactory(protocol.Factory):
    """Builds a Peer per made connection, all sharing one handler."""

    noisy = False

    def __init__(self, handler, reactor):
        self.handler = handler
        self.reactor = reactor

    def buildProtocol(self, addr):
        peer = Peer(self.handler, self.reactor)
        peer.factory = self
        return peer


class ConnectionCaps:
    """The caps of one listener on its open connections: in all (``max_connections``) and from one source address
    (``max_per_address``). The agent port (``ListeningFactory``), the RDAPI's listener
    (``rcmp_ext_connector.RdapiSite``) and the console's streams (``rcmp_console.Console``) count their connections
    here; each words its own refusal."""

    def __init__(self, max_connections, max_per_address):
        self.max_connections = max_connections
        self.max_per_address = max_per_address
        self.open = {}               # connection -> its source address
        self.per_address = {}        # source address -> connections open from it

    def over(self, host):
        """The cap a new connection from ``host`` would pass, ``"total"`` or ``"address"``; None when it may open."""
        if len(self.open) >= self.max_connections:
            return "total"
        if self.per_address.get(host, 0) >= self.max_per_address:
            return "address"
        return None

    def opened(self, connection, host):
        self.open[connection] = host
        self.per_address[host] = self.per_address.get(host, 0) + 1

    def closed(self, connection):
        """``connection`` is gone (no effect for one that was never counted, or already was)."""
        host = self.open.pop(connection, None)
        if host is None:
            return
        left = self.per_address.get(host, 1) - 1
        if left > 0:
            self.per_address[host] = left
        else:
            self.per_address.pop(host, None)


UNLIMITED_FILES = 65536          # the open-file limit counted for a process whose limit is infinite


def default_max_connections():
    """A quarter of this process's open-file limit (the rest is for child pipes, the RDAPI, files), at least 64.
    The agent raises its limit at start (``rcmp_resources.raise_open_files``), so the cap follows what the
    machine allows: 5,000 under a hard limit of 20,000, 256 where only 1,024 descriptors may be open."""
    soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY:
        soft = UNLIMITED_FILES
    return max(64, soft // 4)


class ListeningFactory(PeerFactory):
    """Builds a not-yet-admitted Peer per accepted connection, within the listener's caps.

    A connection over ``max_connections`` in all or ``max_per_address`` from its source address is refused
    (``buildProtocol`` returns None: Twisted closes it before reading anything). Both the refusals (one line per
    window, then their count) and the warnings about connections not admitted yet (protocol errors, limits,
    refused hellos: ``warn_limited``) go into the log through ``rcmp_log_guard.Budget``s.

    A herd (a fleet saying hello at once): while ``max_unanswered`` connections or more are open and not admitted
    (their hello unanswered), the listening port stops accepting (``stopReading``); the kernel's accept queue
    holds the others (``listen`` asks for ``somaxconn()``) until half of those are answered or gone. One turn of
    the event loop then serves a few hundred hellos, not thousands, and the heartbeats' timers run between turns.
    """

    def __init__(self, handler, reactor, max_connections=None, max_per_address=None, max_unanswered=None):
        super().__init__(handler, reactor)
        self.caps = ConnectionCaps(max_connections or default_max_connections(), max_per_address or MAX_PER_ADDRESS)
        self.refused_total = 0
        self.refusals = Budget(log, "refused connections on the agent port", clock=reactor.seconds, burst=1)
        self.warnings = Budget(log, "warnings about connections not admitted", clock=reactor.seconds)
        self.max_unanswered = max_unanswered or MAX_UNANSWERED
        self.unanswered = 0          # connections open and not admitted
        self.port = None             # the listening port (``listen`` sets it): paused and resumed
        self.paused = False
        self.pauses = 0
        self.pause_notes = Budget(log, "lines about accepts paused", clock=reactor.seconds, burst=1)

    @property
    def peers(self):
        """The connections open now."""
        return self.caps.open.keys()

    def buildProtocol(self, addr):
        host = getattr(addr, "host", "?")
        caps = self.caps
        over = caps.over(host)
        if over == "total":
            self._refuse(f"{len(caps.open)} connections open, the cap is {caps.max_connections}", host)
            return None
        if over == "address":
            self._refuse(f"{caps.per_address[host]} connections open from {host}, the cap per address is "
                         f"{caps.max_per_address}", host)
            return None
        peer = Peer(self.handler, self.reactor, admitted=False)
        peer.factory = self
        peer.host = host
        caps.opened(peer, host)
        self.unanswered += 1
        if self.unanswered >= self.max_unanswered and not self.paused:
            self._pause()
        return peer

    def peer_admitted(self, peer):
        self._answered()

    def peer_gone(self, peer):
        if peer in self.caps.open and not peer.admitted:
            self._answered()
        self.caps.closed(peer)

    def _answered(self):
        self.unanswered -= 1
        if self.paused and self.unanswered <= self.max_unanswered // 2:
            self._resume()

    def _pause(self):
        if self.port is None:
            return
        self.paused = True
        self.pauses += 1
        self.port.stopReading()
        self.pause_notes.info("agent port: %d connections wait for their hello's answer; accepting the next ones "
                              "once half of them are answered (the kernel queues them meanwhile)", self.unanswered)

    def _resume(self):
        self.paused = False
        port = self.port
        if port is not None and port.connected and not port.disconnecting:
            port.startReading()

    def warn_limited(self, message, *args):
        self.warnings.warning(message, *args)

    def _refuse(self, why, host):
        self.refused_total += 1
        self.refusals.warning("refusing connections on the agent port (this one from %s): %s", host, why)


def somaxconn():
    """The kernel's cap on a listener's accept queue (``net.core.somaxconn``; Python's ``SOMAXCONN`` if unread)."""
    try:
        with open(SOMAXCONN) as f:
            return max(1, int(f.read().strip()))
    except (OSError, ValueError):
        return socket.SOMAXCONN


def listen(reactor, address, port, handler, max_connections=None, max_per_address=None, max_unanswered=None):
    """Listen on ``address:port`` now; returns the listening port (``stopListening()`` to stop). The caps
    default (None) to ``default_max_connections()``, ``MAX_PER_ADDRESS`` and ``MAX_UNANSWERED``.

    ``port.factory`` is the ``ListeningFactory`` (its caps and counters). Raises
    ``twisted.internet.error.CannotListenError`` (its message names the address and port) at once.
    """
    factory = ListeningFactory(handler, reactor, max_connections, max_per_address, max_unanswered)
    # a fleet arriving at once (a master restarted under its robots) must not overflow the accept queue: a
    # dropped SYN is retried by the robot's kernel only after a second or more. The kernel's own cap is the most
    # it will queue; while the listener pauses accepting (a herd), the queue holds the fleet
    listening = reactor.listenTCP(port, factory, backlog=min(factory.caps.max_connections, somaxconn()),
                                  interface=address)
    factory.port = listening
    return listening


def connect(reactor, host, port, handler, timeout=5.0, bind_address=None):
    """Open a connection to ``host:port`` (from ``bind_address`` when given); the Deferred fires with the Peer."""
    bind = (bind_address, 0) if bind_address else None
    endpoint = endpoints.TCP4ClientEndpoint(reactor, host, port, timeout=timeout, bindAddress=bind)
    return endpoint.connect(PeerFactory(handler, reactor))


class Backoff:
    """Delays between reconnection attempts: Twisted's ``backoffPolicy`` (``initial`` growing by ``factor`` up to
    ``cap``, plus a random 0 to ``jitter`` seconds so that a fleet that lost its master together does not come
    back in lockstep); ``reset()`` after a success."""

    def __init__(self, initial=0.25, factor=2.0, cap=5.0, jitter=1.0, rng=random.random):
        self.policy = backoffPolicy(initialDelay=initial, maxDelay=cap, factor=factor,
                                    jitter=lambda: jitter * rng())
        self.attempts = 0

    def next_delay(self):
        delay = self.policy(self.attempts)
        self.attempts += 1
        return delay

    def reset(self):
        self.attempts = 0


class DriverLink(LineReceiver):
    """The agent's end of the rcm_driver connection (CONTRACTS §4): one JSON object per line.

    ``on_message(cmd, r_name)`` is called for each well-formed line the driver sends (garbage is logged, through
    a ``Budget``, and skipped); ``on_lost(link)`` when the connection ends. ``send(cmd, r_name)`` writes one line,
    carrying ``key`` (the one-time key the agent gave the rcm_driver it started) when there is one.
    """

    delimiter = b"\n"
    MAX_LENGTH = 65536

    def __init__(self, name, on_message, on_lost=None, key=None):
        self.name = name            # whose link this is, for the log (the service space)
        self.on_message = on_message
        self.on_lost = on_lost
        self.key = key
        self.garbage = Budget(log, f"lines of garbage from the rcm_driver of service space {name}")

    def send(self, cmd, r_name):
        line = {"rcm_d_cmd": cmd, "r_name": r_name}
        if self.key is not None:
            line["key"] = self.key
        self.sendLine(strict_dumps(line).encode())

    def lineReceived(self, line):
        try:
            message = json.loads(line.decode("utf-8"))
            cmd, r_name = message["rcm_d_cmd"], message["r_name"]
            if not isinstance(cmd, str) or not isinstance(r_name, str):
                raise TypeError("not strings")
        except (ValueError, KeyError, TypeError):
            self.garbage.warning("service space %s: rcm_driver sent garbage: %s", self.name, shown(line))
            return
        self.on_message(cmd, r_name)

    def lineLengthExceeded(self, line):
        self.garbage.warning("service space %s: rcm_driver sent a line over %d bytes; closing", self.name,
                             self.MAX_LENGTH)
        self.transport.loseConnection()

    def connectionLost(self, reason=protocol.connectionDone):
        if self.on_lost is not None:
            self.on_lost(self)


def connect_driver(reactor, port, link, timeout=1.0):
    """One attempt to connect ``link`` (a DriverLink) to rcm_driver on ``127.0.0.1:port``; fires with it."""
    endpoint = endpoints.TCP4ClientEndpoint(reactor, "127.0.0.1", port, timeout=timeout)
    return endpoints.connectProtocol(endpoint, link)
