"""The console: the platform in a browser at ``/console/`` on the master's RDAPI server (CONTRACTS §9).

Owns the console's resources and its live data, nothing else:

- the static files of ``rcm_platform/console/`` (a fixed list read at start, served read-only, never a path
  built from the request);
- the event stream ``/console/api/events`` (Server-Sent Events): a ``Console`` broadcaster is told by small
  observer hooks that something may have changed (``RoboticsData.observers``: every committed write;
  ``ProcessTable.observers``: every state transition of a child; ``ServiceSpaceManager.observers``: a space
  appears, changes or goes). It coalesces them (``COALESCE`` seconds), rebuilds a snapshot with the code the
  RDAPI reads use (``PlatformCommands.read``, ``RoboticsData.service_logic``, ``ServiceSpaceManager.describe``)
  and pushes each stream only what differs from the last snapshot. A new stream gets the whole snapshot first.
  A rebuild costs what changed, not the fleet: the robots' addresses come in one query (``addresses``), only the
  spaces the observers named are described again (all of them when a server joins or goes, or a process that is
  no space's changes), and a patch carries the robot and server rows that changed (``rows_patch``), never the
  whole lists.
  Streams (event and topic streams alike) are a pool with a share per source address: at most ``MAX_CLIENTS``
  in all and ``MAX_PER_ADDRESS`` from one address (``rcmp_inter_communication.ConnectionCaps``; 503 beyond), so
  one address holding its share leaves the others served. A stream must be read: one whose connection stays
  full for ``DRAIN_DEADLINE`` seconds, or that queues ``MAX_BUFFER`` bytes, is dropped; and each lasts at most
  ``STREAM_LIFETIME`` seconds (the page opens the next one at once and gets a fresh snapshot), since Twisted's
  idle timeout does not run while a request is answered. Streams get a heartbeat comment every ``HEARTBEAT``
  seconds. What they carry is strict JSON (``rcmp_inter_communication.strict_dumps``: a NaN or infinite number
  of a topic is the string ``"NaN"``, ``"Infinity"`` or ``"-Infinity"``);
- live topic views (``/console/api/topic``): the agent keeps no rospy. Per watched service space it starts one
  small ROS node, this module run as ``python3 -m rcm_platform.rcmp_console watch`` under the master's process
  table with the space's ``ROS_MASTER_URI``. The node connects to a Unix socket the agent listens on (in a
  folder of its own, the socket readable by the agent's and the watchers' user only; ``_WatcherFactory``), where
  a connection is kept only when the kernel says it comes from a watcher process the agent started
  (``SO_PEERCRED``), before anything is read; it then proves with a one-time key that it is that space's
  watcher, and hands back JSON lines: the space's topics, and for the
  topics pages watch at most ``WATCH_RATE`` samples a second, each already reduced to a point, a number or a
  bounded text. The node is stopped ``WATCH_GRACE`` seconds after the last page stops watching, or when the
  space goes.

About 1,100 lines, more than the 900 or so of the other modules: the agent's side of the topic watchers and the
watcher node's side (``watch_main``, the only place rospy is imported) are the two ends of one private line
protocol, kept in one module so that they change together.
"""

import argparse
import collections
import json
import logging
import mimetypes
import os
import secrets
import shutil
import socket
import struct
import sys
import tempfile
import time

from twisted.application import service
from twisted.internet import defer, protocol, task, threads
from twisted.protocols.basic import LineReceiver
from twisted.web import resource, server
from twisted.internet.interfaces import IPushProducer
from zope.interface import implementer

from .rcmp_command import CommandError, validate_name
from .rcmp_inter_communication import ConnectionCaps, strict_dumps
from .rcmp_log_guard import Budget, shown
from .rcmp_process import DONE_STATES, LIVE_STATES
from .rcmp_service_item import child_env

log = logging.getLogger("rcm_platform.console")

STATIC_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "console")
COALESCE = 0.05          # seconds between the first change and the snapshot pushed for it
HEARTBEAT = 15.0         # seconds between two comments on an idle stream
MAX_CLIENTS = 64         # event streams at once (topic streams included)
MAX_PER_ADDRESS = 8      # of which from one source address (an operator's page opens one or two)
MAX_BUFFER = 1 << 20     # bytes queued for one stream that does not read before it is dropped
DRAIN_DEADLINE = 30.0    # seconds a stream's connection may stay full (its client not reading) before it is dropped
STREAM_LIFETIME = 1800.0  # seconds a stream lasts; the page then opens the next one at once
TAIL_LINES = 12          # log lines per item in a space's detail
DETAIL_REFRESH = 1.0     # seconds between two looks at the log tails of the spaces pages look at
MAX_WATCHES = 8          # service spaces whose topics are watched at once
MAX_TOPICS = 4           # topics one watched space streams at once
WATCH_RATE = 10.0        # samples per second and topic at most
WATCH_HISTORY = 300      # samples kept per topic for a page that starts watching
WATCH_GRACE = 10.0       # seconds a watcher lives on after the last page stopped watching
MAX_LINE = 64 * 1024     # bytes of one line from a watcher
MAX_TEXT = 2000          # characters of a message shown as text


def sse(event, payload):
    """One Server-Sent Event: ``event:`` line and the payload as one strict JSON ``data:`` line."""
    data = strict_dumps(payload, sort_keys=True, separators=(",", ":"))
    return f"event: {event}\ndata: {data}\n\n".encode("utf-8")


def rows_patch(old, new):
    """What a patch says of a list of rows named by ``pi_name`` (robots, servers) going from ``old`` to ``new``,
    or None when nothing changed: ``{"changed": {name: row}, "gone": [name]}``, the rows new or different and the
    names no longer there. A reader drops the gone rows, replaces the changed ones where they are and appends the
    new ones in the order of ``changed`` (by name); when that would not give ``new``'s order, the patch also
    carries ``"order"``: every name in order."""
    if new is old:
        return None
    before = {row["pi_name"]: row for row in old}
    changed = {}
    for row in new:
        if before.get(row["pi_name"]) != row:
            changed[row["pi_name"]] = row
    names = [row["pi_name"] for row in new]
    gone = sorted(set(before).difference(names))
    patch = {"changed": changed, "gone": gone}
    dropped = set(gone)
    expected = [row["pi_name"] for row in old if row["pi_name"] not in dropped]
    expected += sorted(name for name in changed if name not in before)
    if expected != names:
        patch["order"] = names
    elif not changed and not gone:
        return None
    return patch


# -- one stream -------------------------------------------------------------------------------------------------

def client_host(request):
    """The source address of ``request``'s connection (never a header)."""
    return getattr(request.getClientAddress(), "host", None) or "?"


@implementer(IPushProducer)
class Stream:
    """One open event stream of ``console``'s pool: writes while the connection keeps up, queues up to
    ``console.max_buffer`` bytes while the transport says it is full, and drops the client beyond that or when the
    connection stays full for ``console.drain_deadline`` seconds; ends normally after ``console.stream_lifetime``.
    Counted in ``console.caps`` (under its client's address) from here until it closes."""

    def __init__(self, request, on_close, console):
        self.request = request
        self.console = console
        self.paused = False
        self.closed = False
        self.pending = []
        self.pending_bytes = 0
        self._on_close = on_close
        self._drain = None
        self._end = console.reactor.callLater(console.stream_lifetime, self.end)
        console.caps.opened(self, client_host(request))
        request.setResponseCode(200)
        request.setHeader(b"Content-Type", b"text/event-stream; charset=utf-8")
        request.setHeader(b"Cache-Control", b"no-cache, no-store")
        request.setHeader(b"X-Accel-Buffering", b"no")
        request.registerProducer(self, True)
        request.notifyFinish().addBoth(self._finished)
        request.write(b"retry: 1000\n\n")

    def send(self, data):
        if self.closed:
            return
        if self.paused:
            self.pending.append(data)
            self.pending_bytes += len(data)
            if self.pending_bytes > self.console.max_buffer:
                self.console.notes.info("console: dropping a stream that does not read (%d bytes queued)",
                                        self.pending_bytes)
                self.abort()
            return
        self.request.write(data)

    def pauseProducing(self):
        self.paused = True
        if self._drain is None and not self.closed:
            self._drain = self.console.reactor.callLater(self.console.drain_deadline, self._not_read)

    def _not_read(self):
        self._drain = None
        self.console.notes.info("console: dropping a stream whose client has not read for %g s",
                                self.console.drain_deadline)
        self.abort()

    def resumeProducing(self):
        self.paused = False
        self._cancel("_drain")
        pending, self.pending, self.pending_bytes = self.pending, [], 0
        for data in pending:
            self.send(data)

    def stopProducing(self):
        self._close()

    def abort(self):
        transport = getattr(self.request, "transport", None) or getattr(self.request.channel, "transport", None)
        self._close()
        if transport is not None and hasattr(transport, "abortConnection"):
            transport.abortConnection()

    def end(self):
        """Finish the stream normally (the server stops, or what it showed is gone)."""
        if not self.closed:
            self._close()
            try:
                self.request.unregisterProducer()
                self.request.finish()
            except Exception:  # the connection went at the same moment
                pass

    def _finished(self, _):
        self._close()

    def _cancel(self, name):
        call = getattr(self, name)
        setattr(self, name, None)
        if call is not None and call.active():
            call.cancel()

    def _close(self):
        if self.closed:
            return
        self.closed = True
        self._cancel("_drain")
        self._cancel("_end")
        self.pending = []
        self.pending_bytes = 0
        self.console.caps.closed(self)
        self._on_close(self)


# -- the broadcaster ----------------------------------------------------------------------------------------

class Console:
    """The console's live state and its streams (master only). ``start()`` hooks it into the agent."""

    def __init__(self, reactor, data, platform, spaces, table, describe=None, env=None, coalesce=COALESCE,
                 heartbeat=HEARTBEAT, max_clients=MAX_CLIENTS, max_buffer=MAX_BUFFER, detail_refresh=DETAIL_REFRESH,
                 watch_grace=WATCH_GRACE, max_per_address=MAX_PER_ADDRESS, drain_deadline=DRAIN_DEADLINE,
                 stream_lifetime=STREAM_LIFETIME):
        """``spaces``: the ServiceSpaceManager (its ``spaces`` and ``observers``); ``describe``: what answers
        ``service_space/read`` (the master agent's ``describe``; default the manager's)."""
        self.reactor = reactor
        self.data = data
        self.platform = platform
        self.spaces = spaces
        self.describe = describe or spaces.describe
        self.table = table
        self.env = env
        self.coalesce = coalesce
        self.heartbeat = heartbeat
        self.max_clients = max_clients
        self.caps = ConnectionCaps(max_clients, max_per_address)   # every stream, event and topic alike
        self.max_buffer = max_buffer
        self.drain_deadline = drain_deadline
        self.stream_lifetime = stream_lifetime
        self.notes = Budget(log, "notes about console streams and watchers", clock=reactor.seconds)
        self.detail_refresh = detail_refresh
        self.watch_grace = watch_grace
        self.streams = {}           # Stream -> ss_name it shows in detail, or None
        self.snapshot = None        # {"robots", "servers", "logics", "spaces", "seq", "at"}
        self.details = {}           # ss_name -> last detail pushed
        self.watches = {}           # ss_name -> TopicWatch
        self.seq = 0
        self.running = False
        self._call = None
        self._building = False
        self._again = False
        self._data_seen = None
        self._data_part = None      # (logics, robot addresses) of generation _data_seen
        self._dirty = None          # names of the spaces changed since the last rebuild; None: every space
        self._robots_from = None    # (robot rows, addresses, the snapshot's robots made of them)
        self._snapshot_event = None  # the current snapshot as one "snapshot" event (sent to every new stream)
        self._heartbeat = None
        self._detail_loop = None
        self._listener = None
        self._waiting = []          # Deferreds of next_snapshot()
        self._remote_tails = {}     # ss_name -> {item name: tail} the robot sent last
        self._asking = set()        # ss_names whose robot is being asked for its tails

    # -- hooks ------------------------------------------------------------------------------------------
    def start(self):
        self.running = True
        self.data.observers.append(self._data_changed)
        self.table.observers.append(self._process_changed)
        if self.spaces is not None and hasattr(self.spaces, "observers"):
            self.spaces.observers.append(self._space_changed)
        self._heartbeat = task.LoopingCall(self._beat)
        self._heartbeat.clock = self.reactor
        self._heartbeat.start(self.heartbeat, now=False)
        self._detail_loop = task.LoopingCall(lambda: (self._refresh_details(), self._ask_robots()))
        self._detail_loop.clock = self.reactor
        self._detail_loop.start(self.detail_refresh, now=False)
        self._listen_for_watchers()
        self.changed()

    def _listen_for_watchers(self):
        """The watchers' Unix socket, in a folder of its own (0700, or 0711 when the watchers run as another user:
        they may reach the socket by its name, nobody may list the folder); the socket is the watchers' user's,
        0600: no other local user can connect, and ``_WatcherLink`` keeps only the watchers' own processes."""
        self.watch_dir = tempfile.mkdtemp(prefix="rcmp-console-")
        self.watch_socket = os.path.join(self.watch_dir, "watchers")
        self._listener = self.reactor.listenUNIX(self.watch_socket, _WatcherFactory(self), mode=0o600)
        run_as = getattr(self.spaces, "run_as", None)
        if run_as is not None and run_as.uid != os.geteuid():
            os.chown(self.watch_socket, run_as.uid, run_as.gid)
            os.chmod(self.watch_dir, 0o711)

    @defer.inlineCallbacks
    def stop(self):
        self.running = False
        for hooks, fn in ((self.data.observers, self._data_changed), (self.table.observers, self._process_changed),
                          (getattr(self.spaces, "observers", []), self._space_changed)):
            if fn in hooks:
                hooks.remove(fn)
        for loop in (self._heartbeat, self._detail_loop):
            if loop is not None and loop.running:
                loop.stop()
        if self._call is not None and self._call.active():
            self._call.cancel()
        for stream in list(self.streams):
            stream.end()
        yield defer.gatherResults([w.stop() for w in list(self.watches.values())], consumeErrors=True)
        if self._listener is not None:
            yield self._listener.stopListening()
            self._listener = None
            shutil.rmtree(self.watch_dir, ignore_errors=True)

    def _data_changed(self, generation):
        """RoboticsData observer: runs on the writing thread."""
        self.reactor.callFromThread(self.changed)

    def _process_changed(self, managed, old, new):
        key = str(getattr(managed, "key", ""))
        prefix = f"{getattr(self.spaces, 'key_prefix', 'ss')}/"
        if key.startswith(prefix):
            self._space_dirty(key[len(prefix):].split("/", 1)[0])    # a process of that space's
        elif not key.startswith("console/watch/"):
            self._space_dirty(None)                                   # not known to be no space's: all
        self.changed()
        if managed.key.startswith("console/watch/") and new in DONE_STATES:
            watch = self.watches.get(managed.key[len("console/watch/"):])
            if watch is not None and watch.process is managed and not watch.stopping:
                watch.failed(f"the topic watcher {managed.error or 'ended'}")

    def _space_changed(self, ss_name):
        """ServiceSpaceManager observer: ``ss_name`` changed (None: a server joined or went)."""
        self._space_dirty(ss_name)
        self.changed()
        watch = self.watches.get(ss_name) if ss_name else None
        if watch is not None and self.spaces.spaces.get(ss_name) is None:
            watch.space_gone()

    def _space_dirty(self, ss_name):
        """The next rebuild describes ``ss_name`` again (None: every space, e.g. a server joined or went)."""
        if ss_name is None:
            self._dirty = None
        elif self._dirty is not None:
            self._dirty.add(ss_name)

    def changed(self):
        """Something may have changed: rebuild and push within ``coalesce`` seconds (once for many changes)."""
        if not self.running:
            return
        if not self.streams and not self._waiting:
            self.snapshot = None    # nobody looks: no work; the next stream gets a fresh snapshot
            self._snapshot_event = None
            self._dirty = None
            return
        if self._building:
            self._again = True
        elif self._call is None:
            self._call = self.reactor.callLater(self.coalesce, self._rebuild)

    # -- snapshots --------------------------------------------------------------------------------------
    def _read_data(self):
        """On a thread: every service logic and the robots' addresses (one query), from RoboticsData."""
        logics = {}
        for name in self.data.service_logic_names():
            logic = self.data.service_logic(name)
            if logic is not None:
                logics[name] = logic
        return logics, self.data.addresses()

    @defer.inlineCallbacks
    def _rebuild(self):
        self._call = None
        self._building = True
        dirty, self._dirty = self._dirty, set()
        try:
            generation = self.data.generation
            if generation != self._data_seen:
                self._data_part = yield threads.deferToThread(self._read_data)
                self._data_seen = generation
            logics, addresses = self._data_part
            # the robots' rows (the same object while the data and the placement stay) carry live state
            # (server), and the servers are live
            robots = self._robots(addresses, (yield self.platform.read()))
            servers = yield self._servers()
            spaces, described = self._spaces(dirty)
            self._publish({"robots": robots, "servers": servers, "logics": logics, "spaces": spaces}, described)
        except Exception:
            self._dirty = None      # what this rebuild was told is lost with it: the next describes every space
            log.exception("console: cannot build a snapshot")
        finally:
            self._building = False
            if self._again:
                self._again = False
                self.changed()

    def _robots(self, addresses, rows):
        """The snapshot's robots: the RDAPI's rows, each with its address; the same list while neither changed."""
        last = self._robots_from
        if last is not None and last[0] is rows and last[1] is addresses:
            return last[2]
        robots = [dict(row, address=addresses.get(row["pi_name"])) for row in rows]
        self._robots_from = (rows, addresses, robots)
        return robots

    def _spaces(self, dirty):
        """The snapshot's spaces (the running ones and those waiting for a server with room, CONTRACTS §8) and the
        names described again: those in ``dirty``, those the last snapshot did not have and those waiting for
        room (their sentence counts every server's spaces); all of them when ``dirty`` is None or there is no
        last snapshot. The others keep the description of the last snapshot."""
        running = getattr(self.spaces, "spaces", {}) or {}
        waiting = getattr(self.spaces, "unplaced", {}) or {}
        old = self.snapshot["spaces"] if self.snapshot is not None and dirty is not None else None
        if old is not None and not dirty and not waiting and len(old) == len(running):
            return old, set()       # nothing said it changed (a data write, say): the same spaces
        spaces = {}
        described = set()
        for name in list(running) + [n for n in waiting if n not in running]:
            if old is not None and name in old and name not in dirty and name not in waiting:
                spaces[name] = old[name]
                continue
            described.add(name)
            payload = self.describe(name)
            if payload is not None:
                spaces[name] = payload
        return spaces, (None if old is None else described)

    def _servers(self):
        """The servers' rows (CONTRACTS §8) where the RDAPI has them; [] where it does not."""
        try:
            d = self.platform.read(pi_type="S")
        except TypeError:
            return defer.succeed([])
        d.addErrback(lambda failure: [])
        return d

    def _publish(self, new, described=None):
        """Make ``new`` the snapshot and push what differs from the last one (``described``: the only spaces that
        may differ besides those gone; None: any may)."""
        old = self.snapshot
        self.seq += 1
        new["seq"] = self.seq
        new["at"] = time.time()
        self.snapshot = new
        self._snapshot_event = None
        self._push(old, new, described)
        waiting, self._waiting = self._waiting, []
        for d in waiting:
            d.callback(new)

    def _push(self, old, new, described):
        """Send every stream the snapshot ``new`` (no last one) or what differs from ``old``."""
        if old is None:
            event = self.snapshot_event()
            for stream in list(self.streams):
                stream.send(event)
            return
        patch = {}
        for key in ("robots", "servers"):
            rows = rows_patch(old[key], new[key])
            if rows is not None:
                patch[key] = rows
        for key in ("logics", "spaces"):
            if new[key] is old[key]:
                continue
            names = new[key] if key == "logics" or described is None else described
            changed = {n: new[key][n] for n in names if n in new[key] and old[key].get(n) != new[key][n]}
            gone = sorted(n for n in old[key] if n not in new[key])
            if changed or gone:
                patch[key] = {"changed": changed, "gone": gone}
        if not patch:
            return
        patch["seq"] = new["seq"]
        patch["at"] = new["at"]
        event = sse("patch", patch)
        for stream in list(self.streams):
            stream.send(event)
        if "spaces" in patch:
            self._refresh_details()

    def snapshot_event(self):
        """The current snapshot as a ``snapshot`` event, encoded once per snapshot."""
        if self._snapshot_event is None:
            self._snapshot_event = sse("snapshot", self.snapshot)
        return self._snapshot_event

    def next_snapshot(self):
        """A Deferred firing with the next snapshot published (tests and the benchmark)."""
        d = defer.Deferred()
        self._waiting.append(d)
        self.changed()
        return d

    # -- details: log tails of the spaces pages look at -------------------------------------------------
    def detail(self, ss_name):
        """Every item of ``ss_name`` with its log tail: this agent's from its process, the robot's as the robot
        last sent them (``item_tails``); an item whose tail is not known yet says only where it runs."""
        space = getattr(self.spaces, "spaces", {}).get(ss_name)
        if space is None:
            return None
        remote = self._remote_tails.get(ss_name, {})
        items = []
        for item in space.items:
            entry = {"kind": item.kind, "name": item.name, "i_name": item.i_name, "side": item.side}
            process = getattr(item, "process", None)
            if process is not None:
                entry["tail"] = process.tail(TAIL_LINES)
            elif isinstance(remote.get(item.name), str):
                entry["tail"] = remote[item.name]
            items.append(entry)
        return {"ss_name": ss_name, "items": items}

    def _ask_robot(self, ss_name):
        """Ask the robot of ``ss_name`` for its items' log tails (one request at a time per space)."""
        space = getattr(self.spaces, "spaces", {}).get(ss_name)
        robot = getattr(space, "robot", None)
        if ss_name in self._asking or not hasattr(robot, "item_tails") or \
                not any(getattr(i, "process", None) is None for i in space.items):
            return
        self._asking.add(ss_name)

        def got(tails):
            self._remote_tails[ss_name] = {str(k): str(v) for k, v in (tails or {}).items()}
            if ss_name in self.details:
                self._refresh_details()

        d = robot.item_tails(ss_name, TAIL_LINES)
        d.addCallbacks(got, lambda failure: log.debug("console: no log tails from %s: %s", ss_name,
                                                      failure.getErrorMessage()))
        d.addBoth(lambda _: self._asking.discard(ss_name))

    def _refresh_details(self):
        watched = {name for name in self.streams.values() if name}
        for name in list(self.details):
            if name not in watched:
                del self.details[name]
        for name in list(self._remote_tails):
            if name not in watched:
                del self._remote_tails[name]
        for name in watched:
            detail = self.detail(name)
            if detail != self.details.get(name):
                self.details[name] = detail
                self._send_detail(name, detail)

    def _send_detail(self, name, detail):
        event = sse("detail", {"ss_name": name, "detail": detail})
        for stream, showing in list(self.streams.items()):
            if showing == name:
                stream.send(event)

    def _ask_robots(self):
        for name in {name for name in self.streams.values() if name}:
            self._ask_robot(name)

    def _beat(self):
        streams = list(self.streams) + [s for w in self.watches.values() for s in w.streams]
        for stream in streams:
            stream.send(b": heartbeat\n\n")

    # -- streams ----------------------------------------------------------------------------------------
    def refusal(self, request):
        """Why the pool cannot take a stream from ``request``'s address (a sentence for a 503), or None."""
        host = client_host(request)
        over = self.caps.over(host)
        if over == "total":
            return f"the console already serves {self.caps.max_connections} streams; try again later"
        if over == "address":
            return (f"the console already serves {self.caps.max_per_address} streams to {host}; close some (other "
                    f"tabs or windows of the console) first")
        return None

    def open_stream(self, request, detail=None):
        """Start an event stream on ``request``: the current snapshot first (or as soon as there is one)."""
        stream = Stream(request, self._stream_closed, self)
        self.streams[stream] = detail
        if self.snapshot is not None:
            stream.send(self.snapshot_event())
        else:
            self.changed()
        if detail:
            d = self.detail(detail)
            self.details[detail] = d
            stream.send(sse("detail", {"ss_name": detail, "detail": d}))
            self._ask_robot(detail)
        return stream

    def _stream_closed(self, stream):
        self.streams.pop(stream, None)

    # -- topics -----------------------------------------------------------------------------------------
    def watch(self, ss_name):
        """The TopicWatch of ``ss_name`` (started if needed), or None when the space has no ROS master yet."""
        watch = self.watches.get(ss_name)
        if watch is not None and not watch.stopping:
            return watch
        space = getattr(self.spaces, "spaces", {}).get(ss_name)
        if space is None or not space.ros_master_uri:
            return None
        if len([w for w in self.watches.values() if not w.stopping]) >= MAX_WATCHES:
            raise WatchLimit(f"the console already watches {MAX_WATCHES} service spaces; close a topic view first")
        old = self.table.get(f"console/watch/{ss_name}")
        if old is not None and old.state in LIVE_STATES:
            raise WatchLimit(f"the topic watcher of '{ss_name}' is still stopping; try again in a moment")
        watch = TopicWatch(self, ss_name, space.ros_master_uri, getattr(self.spaces, "address", None))
        self.watches[ss_name] = watch
        watch.start(self.watch_socket)
        return watch

    def watch_of_process(self, pid):
        """The live TopicWatch whose watcher process has ``pid``, or None."""
        return next((w for w in self.watches.values()
                     if not w.stopping and w.process is not None and w.process.pid == pid), None)


class ConsoleService(service.Service):
    """Starts the console with the agent and stops its streams and watchers with it."""

    name = "console"

    def __init__(self, console):
        self.console = console

    def startService(self):
        super().startService()
        self.console.start()

    def stopService(self):
        super().stopService()
        return self.console.stop()


class WatchLimit(Exception):
    """Too many service spaces watched at once."""


# -- topic watching: the agent's side -----------------------------------------------------------------------

class TopicWatch:
    """One watched service space: its watcher node, its topics, recent samples, and the pages watching."""

    def __init__(self, console, ss_name, ros_master_uri, address):
        self.console = console
        self.ss_name = ss_name
        self.ros_master_uri = ros_master_uri
        self.address = address or "127.0.0.1"
        self.key = secrets.token_hex(16)
        self.process = None
        self.link = None
        self.topics = []
        self.samples = {}           # topic -> deque of samples
        self.types = {}
        self.streams = {}           # Stream -> topic it shows (or None)
        self.stopping = False
        self._grace = None
        self._sent_watch = None

    def start(self, socket_path):
        package_root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
        run_as = getattr(self.console.spaces, "run_as", None)   # it reads robots' traffic: never as root
        env = child_env(self.console.env, self.ros_master_uri, self.address,
                        os.path.join(self.console.table.log_dir, "ros"), user=run_as)
        env["PYTHONPATH"] = package_root + (":" + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        argv = ["/usr/bin/python3", "-m", "rcm_platform.rcmp_console", "watch", "--socket", socket_path,
                "--name", self.ss_name]
        env["RCMP_CONSOLE_KEY"] = self.key   # not on the command line, where any local user could read it
        self.process = self.console.table.spawn(f"console/watch/{self.ss_name}", argv, env,
                                                f"console-watch-{self.ss_name}", user=run_as)
        log.info("console: watching the topics of service space %s", self.ss_name)

    def open_stream(self, request, topic):
        stream = Stream(request, self._stream_closed, self.console)
        self.streams[stream] = topic
        if self._grace is not None and self._grace.active():
            self._grace.cancel()
        self._grace = None
        stream.send(sse("topics", {"ss_name": self.ss_name, "topics": self.topics}))
        if topic:
            history = list(self.samples.get(topic, ()))
            stream.send(sse("samples", {"topic": topic, "type": self.types.get(topic), "samples": history}))
        self._tell_watcher()
        return stream

    def _stream_closed(self, stream):
        self.streams.pop(stream, None)
        self._tell_watcher()
        if not self.streams and not self.stopping and self.console.running:
            self._grace = self.console.reactor.callLater(self.console.watch_grace, self.stop)

    def wanted(self):
        return sorted({t for t in self.streams.values() if t})[:MAX_TOPICS]

    def _tell_watcher(self):
        wanted = self.wanted()
        if self.link is not None and wanted != self._sent_watch:
            self._sent_watch = wanted
            self.link.sendLine(strict_dumps({"watch": wanted}).encode())
        for topic in list(self.samples):
            if topic not in wanted:
                del self.samples[topic]

    def linked(self, link):
        self.link = link
        self._sent_watch = None
        self._tell_watcher()

    def topics_received(self, topics):
        self.topics = topics
        event = sse("topics", {"ss_name": self.ss_name, "topics": topics})
        for stream in list(self.streams):
            stream.send(event)

    def sample_received(self, topic, type_name, sample):
        if topic not in self.wanted():
            return
        self.types[topic] = type_name
        self.samples.setdefault(topic, collections.deque(maxlen=WATCH_HISTORY)).append(sample)
        event = sse("sample", {"topic": topic, "type": type_name, "sample": sample})
        for stream, showing in list(self.streams.items()):
            if showing == topic:
                stream.send(event)

    def space_gone(self):
        self.failed("the service space was torn down")

    def failed(self, reason):
        event = sse("gone", {"ss_name": self.ss_name, "reason": reason})
        for stream in list(self.streams):
            stream.send(event)
            stream.end()
        self.stop()

    def stop(self):
        if self._grace is not None and self._grace.active():
            self._grace.cancel()
        self._grace = None
        self.stopping = True
        if self.console.watches.get(self.ss_name) is self:
            del self.console.watches[self.ss_name]
        for stream in list(self.streams):
            stream.end()
        if self.link is not None:
            self.link.transport.loseConnection()
        key = f"console/watch/{self.ss_name}"
        d = self.console.table.stop(key)
        d.addCallback(lambda _: self.console.table.forget(key))
        log.info("console: stopped watching the topics of service space %s", self.ss_name)
        return d


def peer_pid(transport):
    """The process id the kernel gives for the other end of a Unix socket connection (``SO_PEERCRED``), or None."""
    try:
        creds = transport.getHandle().getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
        return struct.unpack("3i", creds)[0]
    except (AttributeError, OSError, struct.error):
        return None


class _WatcherLink(LineReceiver):
    """The agent's end of one watcher's connection: kept only when its process is a watcher the agent started (the
    kernel's word, before anything is read); then a hello with that watch's name and key, then JSON lines."""

    delimiter = b"\n"
    MAX_LENGTH = MAX_LINE
    HELLO_WAIT = 5.0

    def __init__(self, console):
        self.console = console
        self.expected = None        # the TopicWatch whose process connected
        self.watch = None           # the same, once its hello came
        self._hello_timeout = None

    def connectionMade(self):
        pid = peer_pid(self.transport)
        watch = self.console.watch_of_process(pid) if pid is not None else None
        if watch is None or watch.link is not None:
            self.console.notes.warning("console: closed a connection to the watchers' socket from process %s, "
                                       "which is not a topic watcher waiting to link", pid)
            self.transport.abortConnection()
            return
        self.expected = watch
        self._hello_timeout = self.console.reactor.callLater(self.HELLO_WAIT, self.transport.abortConnection)

    def lineReceived(self, line):
        if self.expected is None:
            return
        try:
            message = json.loads(line.decode("utf-8"))
            if not isinstance(message, dict):
                raise ValueError("not an object")
        except ValueError:
            self.transport.loseConnection()
            return
        if self.watch is None:
            self._hello(message)
            return
        if "topics" in message and isinstance(message["topics"], list):
            topics = [[str(t[0])[:256], str(t[1])[:256]] for t in message["topics"][:1000]
                      if isinstance(t, list) and len(t) == 2]
            self.watch.topics_received(topics)
        elif isinstance(message.get("topic"), str) and isinstance(message.get("sample"), dict):
            self.watch.sample_received(message["topic"], str(message.get("type"))[:256], message["sample"])

    def _hello(self, message):
        self._cancel_hello_timeout()
        watch = self.expected
        if watch.stopping or message.get("name") != watch.ss_name or \
                not secrets.compare_digest(str(message.get("key")), watch.key):
            self.console.notes.warning("console: closed the connection of the watcher of %s: its hello does not "
                                       "carry its name and key", watch.ss_name)
            self.transport.loseConnection()
            return
        self.watch = watch
        watch.linked(self)

    def _cancel_hello_timeout(self):
        if self._hello_timeout is not None and self._hello_timeout.active():
            self._hello_timeout.cancel()
        self._hello_timeout = None

    def lineLengthExceeded(self, line):
        self.transport.loseConnection()

    def connectionLost(self, reason=protocol.connectionDone):
        self._cancel_hello_timeout()
        if self.watch is not None and self.watch.link is self:
            self.watch.link = None


class _WatcherFactory(protocol.Factory):
    """The watchers' Unix socket: every connection is a ``_WatcherLink``, which keeps it only for a watcher's own
    process (so at most one per watched space, ``MAX_WATCHES``)."""

    noisy = False

    def __init__(self, console):
        self.console = console

    def buildProtocol(self, addr):
        link = _WatcherLink(self.console)
        link.factory = self
        return link


# -- web resources ------------------------------------------------------------------------------------------

def _json_error(request, status, reason):
    request.setResponseCode(status)
    request.setHeader(b"Content-Type", b"application/json")
    return strict_dumps({"result": "ERROR", "reason": reason}, sort_keys=True).encode("utf-8")


def _one_arg(request, name):
    values = (request.args or {}).get(name.encode())
    if not values:
        return None
    try:
        return values[0].decode("utf-8")
    except UnicodeDecodeError:
        return ""


class ConsoleResource(resource.Resource):
    """``/console/...``: static files and the console's API. Everything below /console/ comes here."""

    isLeaf = True
    SECURITY_HEADERS = (
        (b"Content-Security-Policy", b"default-src 'self'; img-src 'self' data:; style-src 'self'; "
                                     b"script-src 'self'; connect-src 'self'; frame-ancestors 'none'; "
                                     b"base-uri 'none'; form-action 'none'"),
        (b"X-Content-Type-Options", b"nosniff"),
        (b"Referrer-Policy", b"no-referrer"),
    )

    def __init__(self, console, static_dir=STATIC_DIR):
        super().__init__()
        self.console = console
        self.files = {}
        for name in sorted(os.listdir(static_dir)):
            path = os.path.join(static_dir, name)
            if os.path.isfile(path) and not name.startswith("."):
                with open(path, "rb") as f:
                    kind = mimetypes.guess_type(name)[0] or "application/octet-stream"
                    if kind.startswith("text/") or kind in ("application/javascript",):
                        kind += "; charset=utf-8"
                    self.files[name] = (f.read(), kind.encode())

    def render(self, request):
        path = request.path.decode("latin-1")
        for name, value in self.SECURITY_HEADERS:
            request.setHeader(name, value)
        if path == "/console":
            request.setResponseCode(301)
            request.setHeader(b"Location", b"/console/")
            return b""
        rest = path[len("/console/"):]
        method = request.method.decode("latin-1")
        if not rest.startswith("api/"):
            name = rest or "index.html"
            if method not in ("GET", "HEAD"):
                request.setHeader(b"Allow", b"GET, HEAD")
                return _json_error(request, 405, f"{path} takes GET only")
            found = self.files.get(name)
            if found is None:
                return _json_error(request, 404, f"there is no console file {shown(path, 100)}")
            request.setHeader(b"Content-Type", found[1])
            request.setHeader(b"Cache-Control", b"no-cache")
            return found[0]
        if method != "GET":
            request.setHeader(b"Allow", b"GET")
            return _json_error(request, 405, f"{path} takes GET only")
        refusal = self.console.refusal(request)
        if refusal is not None:
            request.setHeader(b"Retry-After", b"5")
            return _json_error(request, 503, refusal)
        try:
            if rest == "api/events":
                detail = _one_arg(request, "ss_name")
                if detail is not None:
                    validate_name(detail, "ss_name")
                self.console.open_stream(request, detail)
                return server.NOT_DONE_YET
            if rest == "api/topic":
                ss_name = validate_name(_one_arg(request, "ss_name"), "ss_name")
                topic = _one_arg(request, "topic")
                if topic is not None and (not topic.startswith("/") or len(topic) > 256
                                          or any(c.isspace() for c in topic)):
                    return _json_error(request, 400, "'topic' must be a ROS topic name such as /pose")
                try:
                    watch = self.console.watch(ss_name)
                except WatchLimit as exc:
                    return _json_error(request, 503, str(exc))
                if watch is None:
                    return _json_error(request, 404, f"there is no running service space named '{ss_name}'")
                watch.open_stream(request, topic)
                return server.NOT_DONE_YET
        except CommandError as exc:
            return _json_error(request, exc.status, str(exc))
        return _json_error(request, 404, f"unknown console call {shown(path, 100)}")


# -- topic watching: the watcher node (a child process; the only place rospy is imported) -------------------

def sample_of(type_name, msg):
    """What a page draws of one message: a point, a number or text (bounded)."""
    point = None
    if type_name == "geometry_msgs/Pose2D":
        return {"x": float(msg.x), "y": float(msg.y), "theta": float(msg.theta)}
    if type_name == "geometry_msgs/Pose":
        point = msg.position
    elif type_name == "geometry_msgs/PoseStamped":
        point = msg.pose.position
    elif type_name in ("nav_msgs/Odometry", "geometry_msgs/PoseWithCovarianceStamped"):
        point = msg.pose.pose.position
    elif type_name == "geometry_msgs/Point":
        point = msg
    elif type_name == "geometry_msgs/PointStamped":
        point = msg.point
    if point is not None:
        return {"x": float(point.x), "y": float(point.y)}
    data = getattr(msg, "data", None)
    if isinstance(data, (int, float)) and not isinstance(data, bool) and len(getattr(msg, "__slots__", ())) == 1:
        return {"value": float(data)}
    return {"text": str(msg)[:MAX_TEXT]}


def watch_main(argv):
    """The watcher node: connect to the agent, subscribe to what it asks, send topics and samples (strict JSON: a
    NaN or infinite number as the string "NaN", "Infinity" or "-Infinity")."""
    import signal
    import threading

    parser = argparse.ArgumentParser(prog="rcmp_console watch")
    parser.add_argument("--socket", required=True)
    parser.add_argument("--name", required=True)
    args = parser.parse_args(argv)
    key = os.environ.pop("RCMP_CONSOLE_KEY", "")
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())

    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.settimeout(10)
    sock.connect(args.socket)
    sock.settimeout(None)
    out = sock.makefile("wb")
    lock = threading.Lock()

    def send(message):
        data = strict_dumps(message, separators=(",", ":")).encode() + b"\n"
        with lock:
            out.write(data)
            out.flush()

    send({"name": args.name, "key": key})
    wanted = {"topics": []}

    def read_commands():
        try:
            for line in sock.makefile("rb"):
                try:
                    message = json.loads(line)
                except ValueError:
                    continue
                if isinstance(message, dict) and isinstance(message.get("watch"), list):
                    wanted["topics"] = [t for t in message["watch"] if isinstance(t, str)][:MAX_TOPICS]
        finally:
            stop.set()
    threading.Thread(target=read_commands, daemon=True).start()

    import rospy
    import roslib.message
    rospy.init_node("rcmp_console_watch", anonymous=True, disable_signals=True, log_level=rospy.WARN)
    latest = {}
    subscribers = {}
    last_topics = None
    next_topics = 0.0
    period = 1.0 / WATCH_RATE

    def subscribe(topic, type_name):
        cls = roslib.message.get_message_class(type_name)
        if cls is None:
            return None

        def got(msg):
            try:
                latest[topic] = (type_name, sample_of(type_name, msg))
            except Exception as exc:  # a message that cannot be shown: say so instead of nothing
                latest[topic] = (type_name, {"text": f"cannot show this message: {exc}"[:MAX_TEXT]})
        return rospy.Subscriber(topic, cls, got, queue_size=1)

    try:
        while not stop.is_set() and not rospy.is_shutdown():
            now = time.monotonic()
            if now >= next_topics:
                next_topics = now + 1.0
                try:
                    topics = sorted([t, ty] for t, ty in rospy.get_published_topics())
                except Exception:
                    topics = last_topics or []
                if topics != last_topics:
                    last_topics = topics
                    send({"topics": topics})
            types = dict(last_topics or [])
            for topic in list(subscribers):
                if topic not in wanted["topics"]:
                    subscribers.pop(topic).unregister()
                    latest.pop(topic, None)
            for topic in wanted["topics"]:
                if topic not in subscribers and topic in types:
                    subscriber = subscribe(topic, types[topic])
                    if subscriber is not None:
                        subscribers[topic] = subscriber
            for topic in list(latest):
                type_name, sample = latest.pop(topic)
                sample["t"] = time.time()
                send({"topic": topic, "type": type_name, "sample": sample})
            stop.wait(period)
    except (BrokenPipeError, ConnectionError):
        pass
    finally:
        rospy.signal_shutdown("the console stopped watching")
        try:
            sock.close()
        except OSError:
            pass
    return 0


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] != ["watch"]:
        sys.stderr.write("usage: python3 -m rcm_platform.rcmp_console watch --socket PATH --name SS_NAME\n")
        return 2
    return watch_main(argv[1:])


if __name__ == "__main__":
    sys.exit(main())
