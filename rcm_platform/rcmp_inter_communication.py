"""The agent-to-agent wire protocol: framing, version, request ids, timeouts, size limit, server and client.

One TCP connection per robot, opened by the robot and used both ways. Each frame is a 4-byte big-endian length
followed by a UTF-8 JSON object::

    {"v": 1, "id": <int>, "kind": "req" | "res" | "err", "op": <str>, "body": {...}}

A request (``req``) is answered by exactly one ``res`` (body = the result) or ``err`` (body =
``{"code", "reason"}``) carrying the same ``id`` and ``op``. Either side may send requests at any time.

Rules (``docs/PROTOCOL.md`` is the reference):
- a frame longer than ``MAX_FRAME`` bytes, a frame that is not a JSON object, or a frame without a usable
  ``id``/``kind``/``op`` is a protocol error: it is logged and the connection is closed;
- a request with an unknown version or an op the receiver does not serve gets an ``err`` answer and the
  connection stays open;
- every request has a timeout: its Deferred fails with ``RequestTimeout`` and a late answer is ignored;
- when the connection goes, every pending request fails with ``PeerGone``.

This module knows nothing of robots: what the ops mean is ``rcmp_event``'s business. A connection's owner gives
it a *handler* with ``request_received(peer, op, body) -> value | Deferred`` (raise ``Refused`` for an ``err``
answer) and, optionally, ``peer_connected(peer)`` and ``peer_lost(peer, reason)``.
"""

import json
import logging

from twisted.internet import defer, endpoints, protocol
from twisted.protocols.basic import Int32StringReceiver
from twisted.python import failure

log = logging.getLogger("rcmp.ic")

PROTOCOL_VERSION = 1
MAX_FRAME = 1024 * 1024          # bytes of JSON in one frame
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


def encode_frame(message):
    """The JSON bytes of one message (without the length prefix); ProtocolError when over MAX_FRAME."""
    data = json.dumps(message, separators=(",", ":"), ensure_ascii=False).encode("utf-8")
    if len(data) > MAX_FRAME:
        raise ProtocolError(f"a {message.get('op')!r} frame of {len(data)} bytes is over the "
                            f"{MAX_FRAME}-byte limit")
    return data


def decode_frame(data):
    """Parse one frame's bytes into a message dict; ProtocolError when it cannot be understood at all."""
    try:
        message = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise ProtocolError(f"frame is not UTF-8 JSON: {exc}") from None
    if not isinstance(message, dict):
        raise ProtocolError("frame is not a JSON object")
    msg_id = message.get("id")
    if not isinstance(msg_id, int) or isinstance(msg_id, bool) or msg_id < 0:
        raise ProtocolError("frame has no non-negative integer 'id'")
    if message.get("kind") not in KINDS:
        raise ProtocolError(f"frame has kind {message.get('kind')!r}, expected one of {', '.join(KINDS)}")
    if not isinstance(message.get("op"), str) or not message["op"]:
        raise ProtocolError("frame has no 'op' string")
    body = message.get("body", {})
    if not isinstance(body, dict):
        raise ProtocolError("frame 'body' is not a JSON object")
    message["body"] = body
    return message


class Peer(Int32StringReceiver):
    """One end of an agent-to-agent connection.

    ``request(op, body, timeout)`` sends a request and returns a Deferred firing with the answer's body.
    ``last_heard`` is the reactor time of the last frame received (or of the connection), for heartbeats.
    """

    MAX_LENGTH = MAX_FRAME

    def __init__(self, handler, reactor):
        self.handler = handler
        self.reactor = reactor
        self.next_id = 1
        self.pending = {}            # id -> (op, Deferred, timeout call)
        self.connected_at = None
        self.last_heard = None
        self.closed = False
        self.close_reason = None
        self.info = {}               # free for the owner (e.g. the robot's name once it said hello)
        self.remote = "?"

    # -- connection -------------------------------------------------------------------------------------
    def connectionMade(self):
        self.connected_at = self.last_heard = self.reactor.seconds()
        peer = self.transport.getPeer()
        self.remote = f"{getattr(peer, 'host', '?')}:{getattr(peer, 'port', '?')}"
        log.debug("connection with %s made", self.remote)
        connected = getattr(self.handler, "peer_connected", None)
        if connected:
            connected(self)

    def connectionLost(self, reason=protocol.connectionDone):
        self.closed = True
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
        if not self.closed and self.transport is not None:
            self.close_reason = reason
            self.transport.abortConnection()

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
    def lengthLimitExceeded(self, length):
        log.warning("protocol error from %s: frame of %d bytes is over the %d-byte limit; closing",
                    self.remote, length, MAX_FRAME)
        self.abort(f"protocol error: frame of {length} bytes over the limit")

    def stringReceived(self, data):
        if self.closed:
            return
        self.last_heard = self.reactor.seconds()
        try:
            message = decode_frame(data)
        except ProtocolError as exc:
            log.warning("protocol error from %s: %s; closing", self.remote, exc)
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
    """Builds a Peer per accepted (or made) connection, all sharing one handler."""

    noisy = False

    def __init__(self, handler, reactor):
        self.handler = handler
        self.reactor = reactor

    def buildProtocol(self, addr):
        peer = Peer(self.handler, self.reactor)
        peer.factory = self
        return peer


def listen(reactor, address, port, handler):
    """Listen on ``address:port`` now; returns the listening port (``stopListening()`` to stop).

    Raises ``twisted.internet.error.CannotListenError`` (its message names the address and port) at once.
    """
    return reactor.listenTCP(port, PeerFactory(handler, reactor), interface=address)


def connect(reactor, host, port, handler, timeout=5.0, bind_address=None):
    """Open a connection to ``host:port`` (from ``bind_address`` when given); the Deferred fires with the Peer."""
    bind = (bind_address, 0) if bind_address else None
    endpoint = endpoints.TCP4ClientEndpoint(reactor, host, port, timeout=timeout, bindAddress=bind)
    return endpoint.connect(PeerFactory(handler, reactor))


class Backoff:
    """Delays between reconnection attempts: ``initial``, doubling up to ``cap``; ``reset()`` after success."""

    def __init__(self, initial=0.25, factor=2.0, cap=5.0):
        self.initial = initial
        self.factor = factor
        self.cap = cap
        self.current = initial

    def next_delay(self):
        delay = self.current
        self.current = min(self.cap, self.current * self.factor)
        return delay

    def reset(self):
        self.current = self.initial
