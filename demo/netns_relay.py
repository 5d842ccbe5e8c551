"""A loopback port of this machine forwarded into a network namespace: how ``./run demo-hosts`` lets this machine's
browser open the console of a master that listens only inside its own (namespace) machine.

``NetnsRelay(netns, host, port)`` listens on ``127.0.0.1`` (a free port, or the one asked for) in the namespace this
process runs in; each connection it accepts is joined to a new TCP connection to ``host:port`` made inside the
network namespace ``netns`` (``ip netns`` names it: ``/run/netns/NAME``). The outgoing socket is created by a thread
that enters the namespace with ``setns(2)`` and goes back before it returns (a socket stays in the namespace it was
made in), so nothing else of this process changes namespace and nothing is added to either network: no veth, no
route, no address. Bytes are passed on by Twisted's port forwarder with its flow control.

Bounded: at most ``max_connections`` relayed connections at once (more are closed at once), a connection idle in
both directions for ``idle_timeout`` seconds is closed (the console's event streams send a heartbeat every 15 s),
and a connection to the namespace that is not made within ``CONNECT_TIMEOUT`` seconds is given up. Twisted's
reactor runs in a thread of its own (the demo's main thread keeps its signals); ``stop()`` closes the listener and
every connection and ends that thread; the reactor cannot run twice in one process, so one relay per process.
Needs root (``setns`` into a network namespace needs CAP_SYS_ADMIN).

By hand (and in its tests): ``python3 -m demo.netns_relay --netns NAME --to HOST:PORT [--port N]`` prints
``forwarding 127.0.0.1:N to HOST:PORT in NAME`` and runs until SIGINT or SIGTERM.
"""

import argparse
import ctypes
import ctypes.util
import os
import signal
import socket
import sys
import threading

from twisted.internet import reactor, threads
from twisted.internet.error import ReactorNotRunning
from twisted.protocols import policies, portforward

CLONE_NEWNET = 0x40000000
CONNECT_TIMEOUT = 5.0
MAX_CONNECTIONS = 64
IDLE_TIMEOUT = 120.0
LOOPBACK = "127.0.0.1"


def _setns(fd):
    """Move the calling thread into the network namespace open at ``fd`` (``os.setns`` from Python 3.12 on)."""
    if hasattr(os, "setns"):
        os.setns(fd, CLONE_NEWNET)
        return
    libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
    if libc.setns(fd, CLONE_NEWNET) != 0:
        err = ctypes.get_errno()
        raise OSError(err, os.strerror(err))


def connect_in_netns(netns_path, address, timeout=CONNECT_TIMEOUT):
    """A TCP socket connected to ``address`` from inside the network namespace at ``netns_path``, non-blocking.

    The calling thread enters the namespace only to create the socket and is back in its own before connecting."""
    own = os.open("/proc/thread-self/ns/net", os.O_RDONLY | os.O_CLOEXEC)
    try:
        target = os.open(netns_path, os.O_RDONLY | os.O_CLOEXEC)
        try:
            _setns(target)
            try:
                sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            finally:
                _setns(own)
        finally:
            os.close(target)
    finally:
        os.close(own)
    try:
        sock.settimeout(timeout)
        sock.connect(address)
        sock.setblocking(False)
    except OSError:
        sock.close()
        raise
    return sock


class _RelayClient(portforward.ProxyClient):
    """The side inside the namespace."""

    def dataReceived(self, data):
        self.peer.resetTimeout()
        super().dataReceived(data)


class _RelayClientFactory(portforward.ProxyClientFactory):
    protocol = _RelayClient
    noisy = False


class _RelayServer(portforward.ProxyServer, policies.TimeoutMixin):
    """The side a browser connected to: held (not read) until its peer inside the namespace is connected."""

    noisy = False

    def connectionMade(self):
        relay = self.factory.relay
        if relay.open >= relay.max_connections:
            self.transport.abortConnection()
            return
        relay.open += 1
        self.counted = True
        self.setTimeout(relay.idle_timeout)
        self.transport.pauseProducing()
        d = threads.deferToThread(connect_in_netns, relay.netns_path, relay.target)
        d.addCallbacks(self._connected, self._failed)

    def _connected(self, sock):
        if self.transport.disconnected:
            sock.close()
            return
        client = _RelayClientFactory()
        client.setServer(self)
        try:
            reactor.adoptStreamConnection(sock.fileno(), socket.AF_INET, client)
        finally:
            sock.close()   # the reactor holds its own copy of the descriptor

    def _failed(self, failure):
        self.transport.loseConnection()

    def dataReceived(self, data):
        self.resetTimeout()
        super().dataReceived(data)

    def timeoutConnection(self):
        self.transport.loseConnection()

    def connectionLost(self, reason):
        self.setTimeout(None)
        if getattr(self, "counted", False):
            self.factory.relay.open -= 1
            self.counted = False
        portforward.Proxy.connectionLost(self, reason)


class _RelayFactory(portforward.ProxyFactory):
    protocol = _RelayServer
    noisy = False

    def __init__(self, relay):
        super().__init__(*relay.target)
        self.relay = relay


class NetnsRelay:
    """``127.0.0.1:listen_port`` here, forwarded to ``host:port`` inside network namespace ``netns``."""

    def __init__(self, netns, host, port, listen_port=0, max_connections=MAX_CONNECTIONS,
                 idle_timeout=IDLE_TIMEOUT):
        self.netns_path = os.path.join("/run/netns", netns)
        self.target = (host, port)
        self.listen_port = listen_port
        self.max_connections = max_connections
        self.idle_timeout = idle_timeout
        self.open = 0
        self._listener = None
        self._thread = None

    def start(self):
        """Start the reactor thread and listen; returns the port listened on. OSError when it cannot listen."""
        if not os.path.exists(self.netns_path):
            raise OSError(f"there is no network namespace {self.netns_path}")
        self._thread = threading.Thread(target=reactor.run, kwargs={"installSignalHandlers": False},
                                        name="netns-relay", daemon=True)
        self._thread.start()
        try:
            self._listener = threads.blockingCallFromThread(
                reactor, reactor.listenTCP, self.listen_port, _RelayFactory(self), interface=LOOPBACK)
        except Exception:
            self.stop()
            raise
        return self._listener.getHost().port

    def stop(self, timeout=10.0):
        """Close the listener and every relayed connection, stop the reactor and wait for its thread."""
        if self._thread is None:
            return
        if self._listener is not None:
            threads.blockingCallFromThread(reactor, self._listener.stopListening)
            self._listener = None

        def stop_reactor():
            try:
                reactor.stop()
            except ReactorNotRunning:
                pass
        reactor.callFromThread(stop_reactor)
        self._thread.join(timeout)
        self._thread = None


def main(argv=None):
    parser = argparse.ArgumentParser(prog="python3 -m demo.netns_relay", description=__doc__.split("\n\n")[0])
    parser.add_argument("--netns", required=True, help="the network namespace (a name 'ip netns list' shows)")
    parser.add_argument("--to", required=True, metavar="HOST:PORT", help="where to connect inside it")
    parser.add_argument("--port", type=int, default=0, help="the port on 127.0.0.1 (default: a free one)")
    parser.add_argument("--max-connections", type=int, default=MAX_CONNECTIONS)
    parser.add_argument("--idle-timeout", type=float, default=IDLE_TIMEOUT)
    args = parser.parse_args(argv)
    host, _, port = args.to.rpartition(":")
    if not host or not port.isdigit() or "/" in args.netns:
        parser.error("--to must be HOST:PORT and --netns a namespace's name")
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    relay = NetnsRelay(args.netns, host, int(port), listen_port=args.port, max_connections=args.max_connections,
                       idle_timeout=args.idle_timeout)
    try:
        listening = relay.start()
    except OSError as exc:
        print(f"netns_relay: {exc}", file=sys.stderr)
        return 1
    print(f"forwarding {LOOPBACK}:{listening} to {host}:{port} in {args.netns}", flush=True)
    try:
        while not stop.wait(1.0):
            pass
    finally:
        relay.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
