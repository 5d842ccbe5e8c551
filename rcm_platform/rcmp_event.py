"""The messages agents exchange and the two sides' handlers: ``MasterAgent`` and ``RobotAgent``.

Owns: the table of ops (who serves each, required fields and their types) and their validation; the master's
side (hello → accepted / refused against the robotics data and the VPN's certificates and their roles, one
session per connected robot, heartbeats, the service space created on connection through the
``ServiceSpaceManager`` and torn down when the robot goes,
``disconnect`` for the RDAPI's r_provisioning) and the robot's side (wait for the platform address, hello with
backoff, serve ``start_items``/``stop_items`` with the ``ItemRunner``, report item exits, stop its
robot-side items and say hello again when the master is lost). The wire format is ``rcmp_inter_communication``'s;
``docs/PROTOCOL.md`` documents every op.

Live state the RDAPI shows (connected, paired, the service space row) is written through ``RoboticsData`` in a
thread, in the order the events happened, the writes that waited meanwhile together in one transaction
(``_BatchedWrites``).

About 1,000 lines, more than the 900 or so of most modules, because the master's and the robot's side of one
protocol are kept together (each op's validation, its sender and its handler change at once); the pieces that
are jobs of their own live beside it (the wire: ``rcmp_inter_communication``; placement and the space runtime:
``rcmp_ms``; heartbeats: ``rcmp_wd``; the process's own limits: ``rcmp_resources``).
"""

import collections
import logging
import random

from twisted.application import service
from twisted.internet import defer, threads
from twisted.python import failure

from rcm_platform import rcmp_inter_communication as ic
from rcm_platform import rcmp_wd
from rcm_platform.rcmp_command import BadRequest, validate_name
from rcm_platform.rcmp_config import SERVER_STARTING_SPACES, default_max_starting_spaces, master_address_from
from rcm_platform.rcmp_log_guard import Budget, shown
from rcm_platform.rcmp_service_command import describe, describe_waiting

log = logging.getLogger("rcmp.event")

VERSION = 1                      # version of this message set, sent in hello
START_TIMEOUT = 180.0            # seconds the master waits for the robot to start its items
STOP_TIMEOUT = 60.0              # seconds the master waits for the robot to stop them
HELLO_TIMEOUT = 300.0            # a robot's last resort; it waits for the answer while the master is heard
HELLO_WAIT = 10.0                # seconds a new connection has to send its hello before the master closes it
HELLO_PATIENCE = 5               # until hello is answered, a robot bears this many times the usual silence
RETRY_CAP = 5.0                  # longest wait between two hellos (plus up to RETRY_JITTER)
RETRY_JITTER = 1.0               # random seconds added to each wait, so that a fleet does not come back together
TAILS_TIMEOUT = 5.0               # seconds the master waits for the tails of a robot's item logs (the console)
MAX_TAIL_LINES = 50              # lines of each item's log an item_tails answer holds at most
MAX_TAIL_CHARS = 8192            # characters of each tail, the last ones kept
REFUSAL_QUIET = 3600.0           # seconds during which the same agent refused for the same reason is not logged again
MAX_REFUSALS_REMEMBERED = 1024   # (code, name, address) kept for that
ADDRESS_POLL = 0.5               # seconds between two looks for the platform address
AFTER_DISCONNECT = 2.0           # a robot told to go waits at least this long before saying hello again
HELLO_LINES = 20                 # accepted hellos logged per 10 s at most (then their count; a herd's are many)
BEATS_ITSELF = 2                 # a peer whose heartbeat came within this many intervals gets none from the master

_NONE = type(None)

# op -> (who serves it, {field: accepted types}); fields in OPTIONAL may be absent (then None)
OPS = {
    "hello": ("master", {"name": str, "address": str, "robot": bool, "version": int,
                         "max_service_spaces": (int, _NONE), "max_starting_spaces": (int, _NONE)}),
    "bye": ("master", {"reason": str}),
    "item_exited": ("master", {"ss_name": str, "report": dict}),
    "heartbeat": ("both", {}),
    "start_items": ("robot", {"ss_name": str, "ros_master_uri": (str, _NONE), "items": list,
                              "start_ros_master_port": (int, _NONE)}),
    "stop_items": ("robot", {"ss_name": str}),
    "item_tails": ("robot", {"ss_name": str, "lines": int}),
    "disconnect": ("robot", {"reason": str}),
}
OPTIONAL = {"ros_master_uri", "start_ros_master_port", "max_service_spaces", "max_starting_spaces"}
MAX_SERVICE_SPACES = 100         # a server VM's max_service_spaces when its hello does not say


def _type_names(types):
    types = types if isinstance(types, tuple) else (types,)
    names = {str: "a string", bool: "true or false", int: "an integer", list: "a list", dict: "an object",
             _NONE: "null"}
    return " or ".join(names.get(t, t.__name__) for t in types)


def validate(op, body, side):
    """Check that ``side`` ("master" or "robot") serves ``op`` and that ``body`` has its fields.

    Returns the body with optional fields filled in; raises ``ic.Refused`` with a sentence otherwise.
    """
    spec = OPS.get(op)
    if spec is None or spec[0] not in (side, "both"):
        raise ic.Refused(f"the {side} agent does not serve op {op!r}", code="unknown_op")
    fields = spec[1]
    checked = dict(body)
    for field, types in fields.items():
        if field not in body:
            if field in OPTIONAL:
                checked[field] = None
                continue
            raise ic.Refused(f"{op}: field {field!r} is missing", code="bad_request")
        value = body[field]
        accepted = types if isinstance(types, tuple) else (types,)
        ok = isinstance(value, accepted) and not (isinstance(value, bool) and bool not in accepted)
        if not ok:
            raise ic.Refused(f"{op}: field {field!r} must be {_type_names(types)}", code="bad_request")
    return checked


class _BatchedWrites:
    """Runs blocking RoboticsData writes in a thread, in the order they were asked for, batched: the writes asked
    for while a batch runs go together into the next one, one transaction (``RoboticsData.write_batch``, a
    savepoint each: one that fails is rolled back alone and logged). A fleet pairing asks for thousands; one
    transaction each, with the reactor holding the interpreter, fell behind by minutes."""

    MAX_BATCH = 1000             # writes in one transaction at most (the rest go into the next)

    def __init__(self, data):
        self.data = data
        self._pending = []           # (fn, args, Deferred) asked for since the running batch started
        self._running = None         # the Deferred of the batch in its thread, or None

    def __call__(self, fn, *args):
        """Queue ``fn(*args)`` (a write method of the data); the Deferred fires with its result, or fails."""
        done = defer.Deferred()
        self._pending.append((fn, args, done))
        if self._running is None:
            self._next()
        done.addErrback(lambda f: log.error("robotics data %s%r failed: %s", getattr(fn, "__name__", fn), args,
                                            f.getErrorMessage()) or None)
        return done

    def flush(self):
        """A Deferred that fires once every write asked for so far is done."""
        if self._running is None and not self._pending:
            return defer.succeed(None)
        done = defer.Deferred()
        self._pending.append((None, (), done))
        if self._running is None:
            self._next()
        return done

    def _next(self):
        batch, self._pending = self._pending[:self.MAX_BATCH], self._pending[self.MAX_BATCH:]
        calls = [(fn, args) for fn, args, _ in batch if fn is not None]
        self._running = threads.deferToThread(self.data.write_batch, calls) if calls else defer.succeed([])
        self._running.addCallbacks(self._finished, self._failed, callbackArgs=(batch,), errbackArgs=(batch,))

    def _finished(self, results, batch):
        outcomes = iter(results)
        for fn, _, done in batch:
            if fn is None:
                done.callback(None)
                continue
            ok, value = next(outcomes)
            done.callback(value) if ok else done.errback(value)
        self._done()

    def _failed(self, reason, batch):
        for fn, _, done in batch:     # the transaction failed as a whole: nothing of the batch was kept
            done.callback(None) if fn is None else done.errback(reason)
        self._done()

    def _done(self):
        self._running = None
        if self._pending:
            self._next()


def _address_function(config, address):
    """``address`` (a function giving the agent's platform address now, or None while there is none), or
    one giving ``config.vpn_address``."""
    if address is not None:
        return address
    return lambda: config.vpn_address


# ------------------------------------------------------------------------------------------------------------
# master side

class AgentSession:
    """One connected agent as the master sees it: a robot (``robot`` true; ``MasterAgent.sessions``) or a server
    VM (``MasterAgent.servers``); the ``rcmp_ms.RemoteAgent`` the ServiceSpaceManager starts items through.

    ``address`` is the connection's source address, never what the hello body claims.
    """

    def __init__(self, agent, peer, name, address, robot):
        self.agent = agent
        self.peer = peer
        self.name = name
        self.address = address
        self.robot = robot
        self.ended = False
        self.hello_at = peer.info.get("hello_at", agent.reactor.seconds())   # when its hello arrived
        self.paired_once = False     # its first pairing in this session was timed
        self.watchdog = rcmp_wd.Watchdog(
            agent.reactor, agent.config.heartbeat_interval, agent.config.heartbeat_misses,
            send_beat=self._beat, last_heard=lambda: peer.last_heard, on_gone=self._gone,
            name=f"{self.what} {name}", on_miss=lambda: self._count("heartbeat_misses"))

    def _beat(self):
        """The master's own heartbeat, sent only when the peer needs it: every agent beats the master and hears
        the answers, so beating it too only doubled the frames (and the master's work) per peer. Sent to a peer
        that does not beat itself (no ``heartbeat`` request from it, ``peer.info["beat_at"]``, within the last
        ``BEATS_ITSELF`` intervals: an agent that never beats, or one that stopped) and to one not heard from for
        ``rcmp_wd.MISSED_AFTER`` intervals (its beats are late: ours makes it answer before the limit)."""
        now = self.agent.reactor.seconds()
        interval = self.watchdog.interval
        beat_at = self.peer.info.get("beat_at")
        beats_itself = beat_at is not None and now - beat_at < BEATS_ITSELF * interval
        if beats_itself and now - (self.peer.last_heard or 0) < rcmp_wd.MISSED_AFTER * interval:
            return None
        self._count("heartbeats_sent")
        return self.peer.request("heartbeat", {}, timeout=self.watchdog.limit)

    def _count(self, what):
        self.agent.counters[f"{what}_{self.what}"] += 1

    def start_items(self, ss_name, ros_master_uri, items, start_ros_master_port=None):
        return self.peer.request("start_items", {
            "ss_name": ss_name, "ros_master_uri": ros_master_uri, "items": items,
            "start_ros_master_port": start_ros_master_port}, timeout=START_TIMEOUT)

    def stop_items(self, ss_name):
        if self.peer.closed or self.peer.aborted:
            return defer.succeed({})
        return self.peer.request("stop_items", {"ss_name": ss_name}, timeout=STOP_TIMEOUT)

    def item_tails(self, ss_name, lines):
        """The last ``lines`` lines of the log of each item the robot runs for ``ss_name`` (the console)."""
        if self.peer.closed or self.peer.aborted:
            return defer.succeed({})
        d = self.peer.request("item_tails", {"ss_name": ss_name, "lines": lines}, timeout=TAILS_TIMEOUT)
        return d.addCallback(lambda body: body.get("tails") if isinstance(body.get("tails"), dict) else {})

    def _gone(self, silent):
        self._count("heartbeat_timeouts")
        self.peer.abort(f"no heartbeat for {silent:.1f} s")

    def __repr__(self):
        return f"<AgentSession {self.what} {self.name} at {self.address}>"

    @property
    def what(self):
        """``robot`` or ``server``, for sentences."""
        return "robot" if self.robot else "server"


class MasterAgent(service.Service):
    """The master's agent-to-agent server: hello, sessions, heartbeats, service spaces.

    ``spaces`` is the ``rcmp_ms.ServiceSpaceManager`` (``create``, ``teardown``, ``item_exited``; it reports
    pairing changes through ``on_state``, which the agent sets); ``describe()`` answers service_space/read (a
    space still waiting to be built is described as such; ``rcmp_service_command`` renders both);
    ``remove(pi_name, reason, remove)`` ends a robot's session and removes its provisioning under the robot's
    lock (the RDAPI's r_provisioning); ``disconnect(pi_name, reason)`` only ends the session.
    ``certificate_of(name)`` (optional) is what the managed VPN says of ``name``: None without a managed VPN,
    else an object with ``address`` (the only address a hello naming it may come from; None: no address is its
    own, ``missing`` says why), ``role`` (``robot`` or ``server``: what its certificate lets it say hello as)
    and ``revoked`` (``rcmp_vpn.certificate_of``). ``address()`` gives the platform address to listen on (None
    while the VPN has none). ``rcmp_node`` builds them and passes them in.

    Admission of a hello (docs/PROTOCOL.md, docs/SECURITY.md): the name is checked against the name rule, then
    with a managed VPN against its certificate's address (``wrong_address``) and role (``wrong_role``: a robot's
    certificate cannot say hello as a server VM, nor a server's as a robot), and a server VM's name against the
    ``servers`` allow-list when it is set (``wrong_role``); then, under the robot's lock, its provisioning
    (``not_provisioned``) and its live session (``in_use`` when a session heard from within the heartbeat window
    comes from another source address). Space creation is queued after the answer: each machine builds its own
    count at once (``max_starting_spaces`` for the master's; a server VM's from its hello, ``SERVER_STARTING_SPACES``
    when it does not say), so the platform builds at most their sum at once (``build_limit``) and the other
    spaces wait in arrival order; a space placed on a server whose count is taken waits there for its turn
    (``rcmp_ms.Server.building``).
    """

    name = "ic-master"

    def __init__(self, config, data, table, reactor, public_ip, spaces, address=None, certificate_of=None):
        self.config = config
        self.certificate_of = certificate_of       # name -> what the managed VPN says of it, or None
        self.data = data
        self.table = table
        self.reactor = reactor
        self.public_ip = public_ip
        spaces.on_state = self._on_state
        self.spaces = spaces
        self._platform_address = _address_function(config, address)
        self.sessions = {}           # robot name -> AgentSession
        self.servers = {}            # server VM name -> its session (robot false): it hosts service spaces
        self._locks = {}             # robot name -> DeferredLock: one hello / teardown at a time per robot
        self._write = _BatchedWrites(data)
        self.max_starting_spaces = config.max_starting_spaces or default_max_starting_spaces()
        self._waiting = collections.OrderedDict()    # robot name -> (session, provisioning row), in arrival order
        self._starting = {}          # robot name -> session whose space is being built now
        self.counters = collections.Counter()        # sessions opened / ended, hellos refused by code, heartbeats
                                                     # missed and timed out per kind of peer (robot, server), ...
        self.timing_observers = []   # fn(what, seconds): "hello" (an accepted hello, answered in seconds) and
                                     # "pairing" (a robot's first pairing in a session, seconds after its hello)
        # provisioned robots known to exist (name -> {"pi_name", "service_logic"}), so that a fleet's hellos after
        # a restart need no SQLite read: filled at start and on each successful lookup; a removal (only through
        # remove(), under the robot's lock, like the hello's check) takes its name out first
        self._provisioned = {}
        self._removals = 0
        self._refreshing = None      # callers waiting for the read in flight, or None
        self._refusals_logged = collections.OrderedDict()   # (code, name, address) -> when it was last logged
        # a fleet saying hello together would write a line per robot: the first few, then their count
        self._hello_lines = Budget(log, "lines about accepted hellos", clock=reactor.seconds, burst=HELLO_LINES,
                                   count_level=logging.INFO)
        self.listening = None
        self.address = None
        self._address_call = None

    # -- service ----------------------------------------------------------------------------------------
    def startService(self):
        """Listen on the platform address; raises CannotListenError at once when the port is taken."""
        super().startService()
        self._preload_provisioning()
        self.address = self.address or self._platform_address()
        if self.address is not None:
            self._listen()
        else:  # the VPN is not up yet: listen as soon as its address exists
            log.warning("waiting for the platform address (interface %s has no IPv4 address yet)",
                        self.config.vpn_interface)
            self._address_call = self.reactor.callLater(ADDRESS_POLL, self._wait_for_address)

    def _preload_provisioning(self):
        d = self._refresh_provisioning()
        d.addErrback(lambda f: log.warning("provisioned robots not preloaded: %s", f.getErrorMessage()))

    def _refresh_provisioning(self):
        """Read every provisioned robot in one query (in a thread) into ``_provisioned``; fires with the rows.

        Concurrent callers share one read: a fleet arriving together costs one query, not one per robot. The
        rows go into the cache only if no removal happened meanwhile (a removed robot must not come back);
        the caller, holding its robot's lock, may use its own row either way (it cannot have been removed)."""
        if self._refreshing is not None:
            waiter = defer.Deferred()
            self._refreshing.append(waiter)
            return waiter
        self._refreshing = waiters = []
        removals = self._removals

        def done(result):
            self._refreshing = None
            if not isinstance(result, failure.Failure) and self._removals == removals:
                for row in result:
                    self._provisioned.setdefault(row["pi_name"], {"pi_name": row["pi_name"],
                                                                  "service_logic": row["service_logic"]})
            for waiter in waiters:
                waiter.callback(result) if not isinstance(result, failure.Failure) else waiter.errback(result)
            return result
        return threads.deferToThread(self.data.platform_instances).addBoth(done)

    @defer.inlineCallbacks
    def _provisioning_of(self, name):
        """``{"pi_name", "service_logic"}`` of a provisioned ``name`` or None; call under ``name``'s lock."""
        pi = self._provisioned.get(name)
        if pi is None:
            rows = yield self._refresh_provisioning()
            row = next((r for r in rows if r["pi_name"] == name), None)
            pi = None if row is None else {"pi_name": name, "service_logic": row["service_logic"]}
        return pi

    def _wait_for_address(self):
        self._address_call = None
        if not self.running:
            return
        self.address = self._platform_address()
        if self.address is None:
            self._address_call = self.reactor.callLater(ADDRESS_POLL, self._wait_for_address)
            return
        try:
            self._listen()
        except Exception as exc:
            log.error("cannot listen for robots: %s", exc)

    def _listen(self):
        self.listening = ic.listen(self.reactor, self.address, self.config.ic_port, self,
                                   max_connections=self.config.ic_max_connections,
                                   max_per_address=self.config.ic_max_per_address)
        log.info("agent-to-agent server listening on %s:%d (at most %d connections)", self.address,
                 self.config.ic_port, self.listening.factory.caps.max_connections)

    @defer.inlineCallbacks
    def stopService(self):
        super().stopService()
        if self._address_call is not None and self._address_call.active():
            self._address_call.cancel()
        if self.listening is not None:
            listening, self.listening = self.listening, None
            yield listening.stopListening()
            for peer in list(listening.factory.peers):   # connections without a session go now
                if peer.info.get("session") is None:
                    peer.abort("the master is stopping")
        yield defer.gatherResults([
            self._locked(name, self._end_session, self.sessions.get(name), "the master is stopping",
                         tell_robot=True) for name in list(self.sessions)], consumeErrors=True)
        yield self.spaces.teardown_all()
        yield defer.gatherResults([
            self._locked(name, self._end_server, self.servers.get(name), "the master is stopping", tell=True)
            for name in list(self.servers)], consumeErrors=True)
        yield self._write.flush()

    # -- public -----------------------------------------------------------------------------------------
    def disconnect(self, pi_name, reason):
        """Tear down ``pi_name``'s service space and mark it disconnected (no-op when it is not connected)."""
        return self._locked(pi_name, lambda: self._end_session(self.sessions.get(pi_name), reason,
                                                                 tell_robot=True))

    def remove(self, pi_name, reason, remove):
        """Under ``pi_name``'s lock: end its session (if any), then run ``remove()`` (blocking, in a thread).

        Fires with True when a session was ended. A hello for ``pi_name`` runs its provisioning check and opens
        its session under the same lock, so it either comes before (and its session is ended here) or after
        (and finds no provisioning)."""
        @defer.inlineCallbacks
        def work():
            session = self.sessions.get(pi_name)
            yield self._end_session(session, reason, tell_robot=True)
            self._provisioned.pop(pi_name, None)
            self._removals += 1
            yield threads.deferToThread(remove)
            return session is not None
        return self._locked(pi_name, work)

    def certificate_advice(self, pi_name):
        """A sentence for the operator when the managed VPN still holds a valid certificate for ``pi_name`` (removing
        a robot does not revoke it: docs/VPN.md), else None."""
        certificate = self.certificate_of(pi_name) if self.certificate_of is not None else None
        if certificate is None or certificate.address is None or certificate.revoked:
            return None
        return (f"its VPN certificate still lets it join the platform's VPN as a {certificate.role}: run "
                f"'rcmp_n vpn revoke {pi_name}' on the master to cut it off")

    def server_rows(self):
        """``platform_instance/read?pi_type=S``: the master and the connected server VMs (CONTRACTS §8)."""
        return self.spaces.server_rows(self.address)

    def server_of(self, pi_name):
        """The name of the server hosting ``pi_name``'s service space, or None while it has none."""
        space = self.spaces.spaces.get(pi_name)
        return getattr(space, "server", None)

    def describe(self, ss_name):
        """The service_space/read payload: the space manager's space, or, for a space waiting to be built, why."""
        if ss_name in self._waiting:
            return describe_waiting(list(self._waiting).index(ss_name) + 1, self.build_limit(), self.public_ip)
        return describe(self.spaces, ss_name)

    # -- protocol handler -------------------------------------------------------------------------------
    def request_received(self, peer, op, body):
        body = validate(op, body, "master")
        session = peer.info.get("session")
        if op == "heartbeat":
            peer.info["beat_at"] = self.reactor.seconds()       # it beats itself: the master need not (_beat)
            return {}
        if op == "hello":
            return self._hello(peer, body)
        if session is None or session.ended:
            raise ic.Refused(f"{op} before an accepted hello", code="no_session")
        if op == "item_exited":
            hosts = (session.robot and body["ss_name"] == session.name) or (
                not session.robot and body["ss_name"] in self.spaces.spaces_of(session.name))
            if not hosts:
                raise ic.Refused(f"{session.what} {session.name} cannot report items "
                                 f"of service space {shown(body['ss_name'], 80)}", code="bad_request")
            self.spaces.item_exited(body["ss_name"], body["report"])
            return {}
        if op == "bye":
            log.info("%s %s is leaving: %s", session.what, session.name, shown(body["reason"]))
            peer.info["said_bye"] = True
            self.reactor.callLater(0, peer.close, f"robot said bye: {shown(body['reason'])}")
            return {}
        raise ic.Refused(f"the master agent does not serve op {op!r}", code="unknown_op")

    def peer_connected(self, peer):
        """A connection that has not sent its hello within HELLO_WAIT is closed (it holds a slot for nothing)."""
        peer.info["hello_call"] = self.reactor.callLater(HELLO_WAIT, self._hello_overdue, peer)

    def _hello_overdue(self, peer):
        peer.info["hello_call"] = None
        if peer.closed or peer.info.get("session") is not None:
            return
        if peer.info.get("hello_pending"):     # being answered: look again later
            peer.info["hello_call"] = self.reactor.callLater(HELLO_WAIT, self._hello_overdue, peer)
            return
        self._log_refusal("closing the connection from %s: no hello within %.0f s", peer.remote, HELLO_WAIT)
        peer.abort("no hello in time")

    def peer_lost(self, peer, why):
        call = peer.info.get("hello_call")
        if call is not None and call.active():
            call.cancel()
        session = peer.info.get("session")
        if session is None or session.ended:
            return
        if peer.info.get("said_bye"):
            log.info("%s %s left: %s", session.what, session.name, why)
        else:
            log.warning("lost %s %s: %s", session.what, session.name, why)
        end = self._end_session if session.robot else self._end_server
        self._locked(session.name, end, session, f"connection lost: {why}")

    # -- hello ------------------------------------------------------------------------------------------
    @defer.inlineCallbacks
    def _hello(self, peer, body):
        if peer.info.get("session") is not None or peer.info.get("hello_pending"):
            raise ic.Refused("hello was already said on this connection", code="bad_request")
        started = peer.info["hello_at"] = self.reactor.seconds()
        peer.info["hello_pending"] = True
        try:
            answer = yield self._accept(peer, body)
        except ic.Refused as exc:
            self.counters[f"refused_{exc.code}"] += 1
            self._refuse_later(peer)
            raise
        finally:
            peer.info["hello_pending"] = False
        took = self.reactor.seconds() - started
        self._hello_lines.info("%s %s connected from %s (hello answered in %.3f s)",
                               "robot" if body["robot"] else "server", body["name"], peer.host, took)
        self._timed("hello", took)
        return answer

    def _timed(self, what, seconds):
        for observer in list(self.timing_observers):
            try:
                observer(what, seconds)
            except Exception:
                log.exception("timing observer of %s failed", what)

    @defer.inlineCallbacks
    def _accept(self, peer, body):
        """Check a hello in the order docs/PROTOCOL.md gives; the answer, or ic.Refused."""
        try:
            name = validate_name(body["name"], "name")
        except BadRequest as exc:
            self._log_refusal("refused hello from %s: %s", peer.remote, exc)
            raise ic.Refused(f"hello: {exc}", code="bad_request") from None
        if not self.running:
            raise ic.Refused("the master is stopping", code="gone")
        if body["version"] != VERSION:
            raise ic.Refused(f"message version {body['version']} is not supported; the master speaks "
                             f"version {VERSION}", code="unsupported_version")
        if name == self.config.name:
            raise ic.Refused(f"{name!r} is the master's own name; give the robot another name",
                             code="not_provisioned")
        certificate = None
        if self.certificate_of is not None:
            certificate = yield defer.maybeDeferred(self.certificate_of, name)
        if certificate is not None and certificate.address != peer.host:
            expected = certificate.address or f"none ({certificate.missing})"
            self._log_refusal("refused hello for %s from %s: %s's VPN address is %s", name, peer.remote, name,
                              expected)
            raise ic.Refused(f"a hello for {name!r} must come from its VPN address {expected}, not from "
                             f"{peer.host}", code="wrong_address")
        self._check_role(peer, name, "robot" if body["robot"] else "server", certificate)
        if not body["robot"]:
            session = yield self._locked(name, self._admit_server, peer, name, body["max_service_spaces"],
                                         body["max_starting_spaces"])
            if session is None:
                raise ic.Refused("the connection closed during hello", code="gone")
            self.spaces.add_server(name, session, session.capacity, peer.host, builds=session.builds)
            self.reactor.callLater(0, self._next_spaces)      # the platform builds more at once now
            return {"accepted": True, "master": self.config.name,
                    "heartbeat_interval": self.config.heartbeat_interval,
                    "heartbeat_misses": self.config.heartbeat_misses}
        pi = yield self._locked(name, self._admit, peer, name, body["robot"])
        if pi is None:
            raise ic.Refused("the connection closed during hello", code="gone")
        self._queue_space(peer.info["session"], pi)
        return {"accepted": True, "master": self.config.name, "heartbeat_interval": self.config.heartbeat_interval,
                "heartbeat_misses": self.config.heartbeat_misses}

    def _log_refusal(self, message, *args):
        """A refused hello goes into the log through the listener's rate limit: a stranger repeating hellos
        must not roll the log over."""
        factory = getattr(self.listening, "factory", None)
        (factory.warn_limited if factory is not None else log.warning)(message, *args)

    def _check_role(self, peer, name, role, certificate):
        """The role rule (docs/SECURITY.md): with a managed VPN, a hello as ``role`` (robot or server) only from a
        certificate issued for that role; a server VM's name only from the ``servers`` allow-list when it is set
        (and, when the list gives one, only from that address). ``ic.Refused`` (``wrong_role``) otherwise."""
        if certificate is not None and certificate.role != role:
            other = "a server VM (robot=no)" if certificate.role == "server" else "a robot"
            fix = (f"issue it a server certificate on the master: rcmp_n vpn client {name} --server"
                   if role == "server" else
                   f"to make it a robot, issue it a robot certificate on the master: rcmp_n vpn client {name} "
                   f"--change-role")
            self._refused_once("wrong_role", name, peer, "refused hello as a %s for %s from %s: its VPN certificate "
                               "is a %s certificate", role, name, peer.remote, certificate.role)
            raise ic.Refused(f"{name!r} holds a {certificate.role} certificate, which lets it join only as {other}, "
                             f"not as a {role}; {fix}", code="wrong_role")
        servers = self.config.servers
        if role != "server" or servers is None:
            return
        if name not in servers:
            self._refused_once("wrong_role", name, peer, "refused hello as a server for %s from %s: not in the "
                               "master's servers list", name, peer.remote)
            raise ic.Refused(f"{name!r} is not one of this master's server VMs (key 'servers' of its .init.cfg)",
                             code="wrong_role")
        pinned = servers[name]
        if pinned is not None and pinned != peer.host:
            self._refused_once("wrong_address", name, peer, "refused hello as a server for %s from %s: the "
                               "master's servers list gives it address %s", name, peer.remote, pinned)
            raise ic.Refused(f"server VM {name!r} must say hello from {pinned} (key 'servers' of the master's "
                             f".init.cfg), not from {peer.host}", code="wrong_address")

    def _refused_once(self, code, name, peer, message, *args):
        """Log a refusal the first time it happens, quietly (debug) when the same agent is refused again for the
        same reason within ``REFUSAL_QUIET`` seconds: a refused agent says hello again every few seconds."""
        key = (code, name, peer.host)
        now = self.reactor.seconds()
        last = self._refusals_logged.pop(key, None)
        if last is not None and now - last < REFUSAL_QUIET:
            self._refusals_logged[key] = last
            log.debug(message + " (again)", *args)
            return
        self._refusals_logged[key] = now
        while len(self._refusals_logged) > MAX_REFUSALS_REMEMBERED:
            self._refusals_logged.popitem(last=False)
        self._log_refusal(message, *args)

    def _refuse_later(self, peer):
        """Close a refused robot's connection once the answer is written."""
        self.reactor.callLater(0, peer.close, "hello refused")

    @defer.inlineCallbacks
    def _take_over(self, old, peer, end):
        """The takeover rule (CONTRACTS §10), for robots and server VMs alike: a hello for a name whose session
        ``old`` is alive (heard from within the heartbeat window, its connection open) is refused (``in_use``)
        unless it comes from that session's own source address (a restarted agent). Otherwise the old session is
        ended (``end``: ``_end_session`` or ``_end_server``) before the new one opens. Call under the name's lock."""
        if old is None or old.ended:
            return
        silent = self.reactor.seconds() - (old.peer.last_heard or 0)
        if old.address != peer.host and not old.peer.closed and silent < old.watchdog.limit:
            self._log_refusal("refused hello for %s from %s: its session from %s is alive (heard %.1f s ago)",
                              old.name, peer.remote, old.address, silent)
            raise ic.Refused(f"{old.what} {old.name!r} has a live session from {old.address} (heard {silent:.1f} s "
                             f"ago); a hello from {peer.host} cannot take it over", code="in_use")
        log.info("%s %s said hello again from %s: replacing its session from %s", old.what, old.name, peer.host,
                 old.address)
        # an agent says hello on a new connection only once it gave up the old one (and stopped its items):
        # drop the old connection first, so the teardown does not wait for answers that cannot come
        why = f"replaced by a new hello from the {old.what}"
        old.peer.abort(why)
        yield end(old, why)

    @defer.inlineCallbacks
    def _admit(self, peer, name, robot):
        """Under ``name``'s lock: its provisioning, the takeover rule, then the new session; the provisioning row
        (None when the connection closed meanwhile)."""
        pi = yield self._provisioning_of(name)
        if pi is None:
            self._log_refusal("refused hello from %s (%s): not provisioned", name, peer.remote)
            raise ic.Refused(f"robot {name!r} is not provisioned on this platform; provision it with "
                             f"platform_instance/provisioning", code="not_provisioned")
        yield self._take_over(self.sessions.get(name), peer, self._end_session)
        if peer.closed:
            return None
        session = AgentSession(self, peer, name, peer.host, robot)
        peer.admit()
        peer.info["session"] = session
        self.sessions[name] = session
        self.counters["sessions_opened"] += 1
        self._write(self.data.set_connected, name, peer.host)     # in order, but the answer does not wait for it
        # the robot's silence is counted from our answer, not from its hello (the lock or lookup may be slow)
        peer.last_heard = max(peer.last_heard, self.reactor.seconds())
        session.watchdog.start()
        return pi

    @defer.inlineCallbacks
    def _admit_server(self, peer, name, capacity, builds):
        """Under ``name``'s lock: a server VM joins by itself (CONTRACTS §8). Refused when ``name`` is a provisioned
        robot's or a live server's from another address; the new session."""
        if capacity is not None and not 0 <= capacity <= 100000:
            raise ic.Refused(f"hello: max_service_spaces must be between 0 and 100000, not {capacity}",
                             code="bad_request")
        if builds is not None and not 1 <= builds <= 1000:
            raise ic.Refused(f"hello: max_starting_spaces must be between 1 and 1000, not {builds}",
                             code="bad_request")
        pi = yield threads.deferToThread(self.data.platform_instance, name)
        if pi is not None or name in self.sessions:
            self._log_refusal("refused hello from server %s (%s): a robot has that name", name, peer.remote)
            raise ic.Refused(f"{name!r} is provisioned as a robot; give the server VM another name",
                             code="name_taken")
        yield self._take_over(self.servers.get(name), peer, self._end_server)
        if peer.closed:
            return None
        session = AgentSession(self, peer, name, peer.host, False)
        session.capacity = MAX_SERVICE_SPACES if capacity is None else capacity
        session.builds = SERVER_STARTING_SPACES if builds is None else builds    # an older server does not say
        peer.admit()
        peer.info["session"] = session
        self.servers[name] = session
        self.counters["servers_joined"] += 1
        peer.last_heard = max(peer.last_heard, self.reactor.seconds())
        session.watchdog.start()
        return session

    @defer.inlineCallbacks
    def _end_server(self, session, reason, tell=False):
        """A server VM is gone (or the master stops): its spaces move to the servers with room."""
        if session is None or session.ended:
            return
        session.ended = True
        session.watchdog.stop()
        if self.servers.get(session.name) is session:
            del self.servers[session.name]
        log.info("ending server %s's session: %s", session.name, reason)
        if tell and not session.peer.closed:
            try:
                yield session.peer.request("disconnect", {"reason": reason}, timeout=self._quick())
            except Exception as exc:
                log.debug("server %s not told of its disconnection: %s", session.name, exc)
        session.peer.close(reason)
        yield self.spaces.remove_server(session.name, reason)

    # -- service space admission ------------------------------------------------------------------------
    def _queue_space(self, session, pi):
        """Build the robot's space when its turn comes: at most ``build_limit()`` at once, in arrival order."""
        self._waiting[session.name] = (session, pi)
        self._next_spaces()

    def build_limit(self):
        """Spaces the platform builds at once: the master's own count and each connected server VM's."""
        return self.max_starting_spaces + sum(server.builds for server in self.servers.values())

    def _next_spaces(self):
        limit = self.build_limit()
        while self._waiting and len(self._starting) < limit:
            name, (session, pi) = self._waiting.popitem(last=False)
            if session.ended:
                continue
            self._starting[name] = session
            d = self._create_space(session, pi)
            d.addBoth(self._space_built, name, session)

    def _space_built(self, result, name, session):
        if self._starting.get(name) is session:
            del self._starting[name]
        self.reactor.callLater(0, self._next_spaces)
        return None

    @defer.inlineCallbacks
    def _create_space(self, session, pi):
        """Build the robot's service space; not under the robot's lock, so that a teardown can cancel it."""
        logic = yield threads.deferToThread(self.data.service_logic, pi["service_logic"])
        if session.ended:
            return
        if logic is None:
            log.error("robot %s: its service logic %r is gone; not creating a service space", session.name,
                      pi["service_logic"])
            return
        try:
            yield self.spaces.create(session.name, logic, session)
        except Exception as exc:
            log.error("service space of robot %s not created: %s", session.name, exc)

    # -- teardown ---------------------------------------------------------------------------------------
    @defer.inlineCallbacks
    def _end_session(self, session, reason, tell_robot=False):
        if session is None or session.ended:
            return
        session.ended = True
        session.watchdog.stop()
        self.counters["sessions_ended"] += 1
        if self.sessions.get(session.name) is session:
            del self.sessions[session.name]
        waiting = self._waiting.get(session.name)
        if waiting is not None and waiting[0] is session:
            del self._waiting[session.name]
        log.info("ending robot %s's session: %s", session.name, reason)
        disconnected = self._write(self.data.set_disconnected, session.name)
        if tell_robot and not session.peer.closed:
            try:
                yield session.peer.request("disconnect", {"reason": reason}, timeout=self._quick())
            except Exception as exc:
                log.debug("robot %s not told of its disconnection: %s", session.name, exc)
        try:
            yield self.spaces.teardown(session.name)
        except Exception as exc:
            log.error("tearing down robot %s's service space: %s", session.name, exc)
        session.peer.close(reason)
        yield disconnected

    def _quick(self):
        return max(1.0, self.config.heartbeat_interval)

    def _on_state(self, pi_name, paired, space):
        """ServiceSpaceManager callback: pairing of ``pi_name`` changed."""
        session = self.sessions.get(pi_name)
        if session is None:
            return
        log.info("robot %s %s", pi_name, "paired" if paired else "not paired")
        if paired and not session.paired_once:
            session.paired_once = True
            self._timed("pairing", self.reactor.seconds() - session.hello_at)
        if space is not None:
            self._write(self.data.set_service_space, pi_name, getattr(space, "ros_master_uri", None),
                        getattr(space, "inbound_port", None))
        self._write(self.data.set_paired, pi_name, bool(paired))

    def _locked(self, name, fn, *args, **kwargs):
        lock = self._locks.setdefault(name, defer.DeferredLock())
        return lock.run(fn, *args, **kwargs)


# ------------------------------------------------------------------------------------------------------------
# robot side

class RobotAgent(service.Service):
    """A robot's (or server VM's) agent: hello to the master, robot-side items on its request, heartbeats.

    ``runner`` is the ``rcmp_ms.ItemRunner`` (the agent sets its ``on_item_exited``); ``address()`` gives
    the platform address (None while the VPN has none). ``rcmp_node`` builds them and passes them in.
    """

    name = "ic-robot"

    def __init__(self, config, table, reactor, runner, address=None):
        self.config = config
        self.table = table
        self.reactor = reactor
        runner.on_item_exited = self._item_exited
        self.runner = runner
        self._platform_address = _address_function(config, address)
        self.backoff = ic.Backoff(initial=0.25, factor=2.0, cap=RETRY_CAP, jitter=RETRY_JITTER)
        self.peer = None
        self.accepted = False
        self.address = None
        self.watchdog = None
        self._call = None
        self._told_to_go = False
        self._last_problem = None
        self._stopped = defer.succeed(None)

    # -- service ----------------------------------------------------------------------------------------
    def startService(self):
        super().startService()
        self._schedule(0)

    @defer.inlineCallbacks
    def stopService(self):
        super().stopService()
        if self._call is not None and self._call.active():
            self._call.cancel()
        self._call = None
        self._stop_watchdog()
        peer = self.peer
        if peer is not None and not peer.closed:
            if self.accepted:
                try:
                    yield peer.request("bye", {"reason": "the robot agent is stopping"}, timeout=2.0)
                except Exception as exc:
                    log.debug("bye not answered: %s", exc)
            peer.close("the robot agent is stopping")
        yield self._stopped
        yield self.runner.stop_all()

    # -- connection loop --------------------------------------------------------------------------------
    def _schedule(self, delay):
        if not self.running or self._call is not None:
            return
        self._call = self.reactor.callLater(delay, self._attempt)

    def _problem(self, message, *args):
        """Log a connection problem: a warning the first time, then quietly while it stays the same."""
        text = message % args
        (log.warning if text != self._last_problem else log.debug)("%s", text)
        self._last_problem = text

    @defer.inlineCallbacks
    def _attempt(self):
        self._call = None
        if not self.running:
            return
        self.address = self._platform_address()
        if self.address is None:
            self._problem("waiting for the platform address (interface %s has no IPv4 address yet)",
                          self.config.vpn_interface)
            self._schedule(ADDRESS_POLL)
            return
        ip_master = self.config.ip_master or master_address_from(self.address)
        master = f"{ip_master}:{self.config.ic_port}"
        try:
            peer = yield ic.connect(self.reactor, ip_master, self.config.ic_port, self,
                                    timeout=5.0, bind_address=self.address)
        except Exception as exc:
            self._problem("master %s unreachable (%s); retrying", master, exc)
            self._schedule(self.backoff.next_delay())
            return
        if not self.running:
            peer.close("the robot agent is stopping")
            return
        self.peer = peer
        self.accepted = False
        # heartbeats from the start: a master that is slow to answer hello but still answers beats is waited
        # for (hanging up would throw its work away and queue us again). Until the answer, even a silent master
        # gets HELLO_PATIENCE times the usual window: one flooded by a fleet (forking the processes of many
        # spaces) may not read for seconds, and we have nothing running yet that its silence would put at risk
        self._watch(peer, self.config.heartbeat_misses * HELLO_PATIENCE)
        asked = self.reactor.seconds()
        try:
            hello = {"name": self.config.name, "address": self.address, "robot": self.config.role == "robot",
                     "version": VERSION}
            if self.config.role == "server":
                hello["max_service_spaces"] = self.config.max_service_spaces
                hello["max_starting_spaces"] = self.config.max_starting_spaces or default_max_starting_spaces()
            answer = yield peer.request("hello", hello, timeout=HELLO_TIMEOUT)
        except ic.RemoteError as exc:
            self._problem("master %s refused hello: %s", master, shown(exc.reason))
            peer.close("hello refused")
            return
        except Exception as exc:
            self._problem("hello to master %s failed: %s", master, exc)
            peer.abort("hello failed")
            return
        if peer.closed:
            return
        self.accepted = True
        self._last_problem = None
        self._told_to_go = False
        self.backoff.reset()
        self._stop_watchdog()
        self._watch(peer, self.config.heartbeat_misses)
        log.info("connected to master %s as %s (%s); hello answered in %.3f s", master, self.config.name,
                 self.address, self.reactor.seconds() - asked)
        return answer

    def _watch(self, peer, misses):
        self.watchdog = rcmp_wd.Watchdog(
            self.reactor, self.config.heartbeat_interval, misses,
            send_beat=lambda: peer.request("heartbeat", {}, timeout=self.config.heartbeat_interval *
                                           self.config.heartbeat_misses),
            last_heard=lambda: peer.last_heard,
            on_gone=lambda silent: peer.abort(f"no heartbeat from the master for {silent:.1f} s"),
            name="the master")
        self.watchdog.start()

    def _stop_watchdog(self):
        if self.watchdog is not None:
            self.watchdog.stop()
            self.watchdog = None

    def peer_lost(self, peer, why):
        if peer is not self.peer:
            return
        self.peer = None
        self._stop_watchdog()
        was_accepted, self.accepted = self.accepted, False
        delay = self.backoff.next_delay()
        if self._told_to_go:
            # a master that stops tells every robot at once: their jitter must survive this floor
            delay = max(delay, AFTER_DISCONNECT + random.random() * RETRY_JITTER)
        if not self.running:         # stopService stops the items itself
            return
        if not was_accepted:
            self._schedule(delay)
            return
        log.warning("lost the master (%s): stopping robot-side items", why)
        self._stopped = self.runner.stop_all()
        self._stopped.addErrback(lambda f: log.error("stopping robot-side items: %s", f.getErrorMessage()))
        self._stopped.addCallback(lambda _: self._schedule(delay))

    # -- requests from the master -----------------------------------------------------------------------
    def request_received(self, peer, op, body):
        body = validate(op, body, "robot")
        if op == "heartbeat":
            return {}
        if not self.accepted and op != "disconnect":
            raise ic.Refused(f"{op} before the master accepted hello", code="no_session")
        if op == "start_items":
            log.info("master asks to start %d item(s) of service space %s", len(body["items"]),
                     shown(body["ss_name"], 80))
            return self.runner.start_items(body["ss_name"], body["ros_master_uri"], body["items"],
                                           body["start_ros_master_port"])
        if op == "stop_items":
            log.info("master asks to stop the items of service space %s", shown(body["ss_name"], 80))
            return self.runner.stop_items(body["ss_name"]).addCallback(lambda _: {})
        if op == "item_tails":
            return {"tails": self._item_tails(body["ss_name"], body["lines"])}
        if op == "disconnect":
            log.warning("the master disconnects this robot: %s", shown(body["reason"]))
            self._told_to_go = True
            return {}
        raise ic.Refused(f"the robot agent does not serve op {op!r}", code="unknown_op")

    def _item_tails(self, ss_name, lines):
        """``{item name: its log's last lines}`` of the items this agent runs for ``ss_name``, bounded."""
        space = self.runner.spaces.get(ss_name)
        lines = max(1, min(int(lines), MAX_TAIL_LINES))
        tails = {}
        for item in getattr(space, "items", []) or []:
            if item.process is not None:
                tails[item.name] = item.process.tail(lines)[-MAX_TAIL_CHARS:]
        return tails

    def _item_exited(self, ss_name, report):
        """ItemRunner callback: an R item of ``ss_name`` exited; tell the master."""
        peer = self.peer
        if peer is None or peer.closed or not self.accepted:
            return
        d = peer.request("item_exited", {"ss_name": ss_name, "report": report},
                         timeout=self.config.heartbeat_interval * self.config.heartbeat_misses)
        d.addErrback(lambda f: log.warning("could not report the exit of %s to the master: %s",
                                           report.get("name"), f.getErrorMessage()))
