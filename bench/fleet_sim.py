"""A simulated fleet: robot agents and server VMs speaking the real agent protocol to one real master, without ROS.

Owns the simulated agents and the handle that drives them (benchmarks and tests only; nothing of the product).

- ``python3 -m bench.fleet_sim worker --master HOST:PORT`` is one *worker*: a Twisted reactor holding any number
  of simulated agents, driven by JSON lines on its standard input (one answer line on standard output each).
  Each agent behaves on the wire as ``rcmp_event.RobotAgent`` does (docs/PROTOCOL.md): one connection from its
  own loopback address (``bind``), ``hello`` (``robot`` true, or false with ``max_service_spaces`` for a server
  VM), a watchdog from the connection on (``rcmp_wd.Watchdog``, 5 times the usual silence until the hello is
  answered), heartbeats both ways, ``start_items`` / ``stop_items`` / ``item_tails`` / ``disconnect`` served,
  reconnection with the product's backoff and jitter after a loss. Nothing is started: ``start_items`` answers
  every item ``running`` after an optional delay (``--server-start`` on a server VM, for its ROS master and S
  items; ``--robot-start`` on a robot, for its R items), and a server VM hands out ROS master ports of its own.
  The framing, request ids and timeouts are ``rcmp_inter_communication``'s.
- Agents can be started, made to leave (``bye``), crash (the connection dropped at once, no reconnection) and
  started again. Each worker records what a benchmark needs: hello answer times, heartbeat round trips (the
  agents' own beats), its own event loop's lateness (so a figure bound by the simulator shows as such), every
  session lost that the simulator did not end, and per agent when it was accepted and when its items were last
  started.
- ``Fleet`` (the driver's side) starts ``workers`` such processes (one per core is the most that helps) as
  children of a ``tests.support.processes.ProcessGroup``, spreads the agents over them and merges their answers.

File descriptors: each agent holds one socket, so a worker raises its soft ``RLIMIT_NOFILE`` to the hard limit
at start, and ``raise_nofile()`` does the same for the driver (the master it starts inherits it).
"""

import argparse
import json
import logging
import os
import random
import resource
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PYTHON = "/usr/bin/python3"
AFTER_DISCONNECT = 2.0           # a robot told to go waits this long (plus jitter) before its next hello (as rcmp_event)
HELLO_PATIENCE = 5               # until hello is answered, a robot bears this many times the usual silence
HELLO_TIMEOUT = 300.0
LAG_EVERY = 0.1                  # seconds between two looks at the worker's own event loop
MAX_SAMPLES = 200000             # samples of one kind a worker keeps between two resets
MAX_COMMAND = 64 * 1024 * 1024   # bytes of one command line


def raise_nofile():
    """Raise this process's soft open-file limit to its hard limit; returns the new soft limit."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard == resource.RLIM_INFINITY or soft < hard:
        target = hard if hard != resource.RLIM_INFINITY else max(soft, 1 << 20)
        resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
        soft = target
    return soft


def robot_address(index):
    """The loopback address of the ``index``-th simulated robot (0-based): 127.11.0.1 ... 127.11.0.250, 127.11.1.1 ..."""
    return f"127.11.{index // 250}.{index % 250 + 1}"


def server_address(index):
    """The loopback address of the ``index``-th simulated server VM: 127.12.0.1 ..."""
    return f"127.12.{index // 250}.{index % 250 + 1}"


# -- the worker: simulated agents in one reactor ---------------------------------------------------------------

def _item_report(entry, i_name):
    """The report of a service logic entry (``sn_*`` node or ``sl_*`` launcher) as a started item."""
    node = "sn_name" in entry
    name = str(entry.get("sn_name" if node else "sl_name", "?"))
    return {"kind": "node" if node else "launcher", "name": name,
            "package": entry.get("sn_package" if node else "sl_package"),
            "type_or_file": entry.get("sn_type" if node else "sl_file_launcher"),
            "side": entry.get("sn_side" if node else "sl_side"), "i_name": i_name, "state": "running",
            "error": None, "nodes": [f"/{name}"] if node else [], "node_types": {}}


class SimAgent:
    """One simulated robot agent or server VM (``robot`` False), a handler of ``rcmp_inter_communication.Peer``."""

    def __init__(self, worker, name, address, robot=True, capacity=None):
        from rcm_platform import rcmp_inter_communication as ic
        self.ic = ic
        self.worker = worker
        self.name = name
        self.address = address
        self.robot = robot
        self.capacity = capacity
        self.wanted = False          # the simulator wants it connected (start) or not (leave, crash)
        self.peer = None
        self.accepted = False
        self.watchdog = None
        self.call = None
        self.backoff = ic.Backoff(initial=0.25, factor=2.0, cap=5.0, jitter=1.0)
        self.told_to_go = False
        self.ending = None           # why the simulator is ending this connection (not a loss)
        self.sessions = 0            # hellos accepted
        self.accepted_at = None      # time.time() of the last accepted hello
        self.items_at = None         # time.time() of the last start_items answered (robot: its R items)
        self.ros_master_uri = None   # robot: the space's ROS master its items were last started against
        self.spaces = {}             # server: ss_name -> ROS master port
        self.next_port = 11311

    # -- life ---------------------------------------------------------------------------------------------
    def start(self):
        self.wanted = True
        self.backoff.reset()
        if self.peer is None and self.call is None:
            self._schedule(0)

    def leave(self):
        """Say bye and close, as a robot agent stopping does; stays away until started again."""
        self.wanted = False
        self._cancel_call()
        peer = self.peer
        if peer is None or peer.closed:
            return
        self.ending = "left"
        if self.accepted:
            d = peer.request("bye", {"reason": "the simulated agent leaves"}, timeout=2.0)
            d.addBoth(lambda _: peer.close("left"))
        else:
            peer.close("left")

    def crash(self):
        """Drop the connection at once (a crashed machine whose kernel resets it); stays away until started."""
        self.wanted = False
        self._cancel_call()
        if self.peer is not None and not self.peer.closed:
            self.ending = "crashed"
            self.peer.abort("crashed")

    def _cancel_call(self):
        if self.call is not None and self.call.active():
            self.call.cancel()
        self.call = None

    def _schedule(self, delay):
        self._cancel_call()
        self.call = self.worker.reactor.callLater(delay, self._attempt)

    def _attempt(self):
        self.call = None
        if not self.wanted:
            return
        self.worker.count("connects")
        d = self.ic.connect(self.worker.reactor, self.worker.master_host, self.worker.master_port, self,
                            timeout=5.0, bind_address=self.address)
        d.addCallbacks(self._connected, self._connect_failed)

    def _connect_failed(self, failure):
        self.worker.count("connect_failures")
        if self.wanted:
            self._schedule(self.backoff.next_delay())

    def _connected(self, peer):
        if not self.wanted:
            peer.close("not wanted any more")
            return
        self.peer = peer
        self.accepted = False
        self.ending = None
        self._watch(peer, self.worker.misses * HELLO_PATIENCE)
        hello = {"name": self.name, "address": self.address, "robot": self.robot, "version": 1}
        if not self.robot:
            hello["max_service_spaces"] = self.capacity if self.capacity is not None else 100
        asked = time.monotonic()
        d = peer.request("hello", hello, timeout=HELLO_TIMEOUT)
        d.addCallbacks(self._hello_answered, self._hello_failed, callbackArgs=(peer, asked), errbackArgs=(peer,))

    def _hello_answered(self, answer, peer, asked):
        if peer.closed:
            return
        self.worker.sample("hello", time.monotonic() - asked)
        self.accepted = True
        self.sessions += 1
        self.accepted_at = time.time()
        self.told_to_go = False
        self.backoff.reset()
        self._watch(peer, self.worker.misses)

    def _hello_failed(self, failure, peer):
        if isinstance(failure.value, self.ic.RemoteError):
            self.worker.count(f"refused_{failure.value.code}")
            peer.close("hello refused")
        else:
            self.worker.count("hello_failures")
            peer.abort("hello failed")

    def _watch(self, peer, misses):
        from rcm_platform import rcmp_wd
        self._stop_watchdog()
        self.watchdog = rcmp_wd.Watchdog(
            self.worker.reactor, self.worker.heartbeat, misses, send_beat=lambda: self._beat(peer),
            last_heard=lambda: peer.last_heard,
            on_gone=lambda silent: peer.abort(f"no heartbeat from the master for {silent:.1f} s"),
            name=f"the master of {self.name}")
        self.watchdog.start()

    def _beat(self, peer):
        sent = time.monotonic()
        d = peer.request("heartbeat", {}, timeout=self.worker.heartbeat * self.worker.misses)
        d.addCallback(lambda _: self.worker.sample("heartbeat", time.monotonic() - sent))
        return d

    def _stop_watchdog(self):
        if self.watchdog is not None:
            self.watchdog.stop()
            self.watchdog = None

    # -- the Peer's handler --------------------------------------------------------------------------------
    def peer_lost(self, peer, why):
        if peer is not self.peer:
            return
        self.peer = None
        self._stop_watchdog()
        was_accepted, self.accepted = self.accepted, False
        self.spaces.clear()
        if was_accepted:
            self.items_at = None
            self.ros_master_uri = None
            if self.ending is None:
                what = "told to go" if self.told_to_go else why
                self.worker.lost(self.name, what)
        self.ending = None
        if self.wanted:
            delay = self.backoff.next_delay()
            if self.told_to_go:
                delay = max(delay, AFTER_DISCONNECT + random.random())
            self._schedule(delay)

    def request_received(self, peer, op, body):
        if op == "heartbeat":
            return {}
        if op == "disconnect":
            self.told_to_go = True
            self.worker.count("disconnects")
            return {}
        if not self.accepted:
            raise self.ic.Refused(f"{op} before the master accepted hello", code="no_session")
        if op == "start_items":
            return self._start_items(body)
        if op == "stop_items":
            self.worker.count("stop_items")
            self.spaces.pop(body.get("ss_name"), None)
            if self.robot:
                self.items_at = None
            return {}
        if op == "item_tails":
            return {"tails": {}}
        raise self.ic.Refused(f"the simulated agent does not serve op {op!r}", code="unknown_op")

    def _start_items(self, body):
        from twisted.internet import task
        ss_name, items = body.get("ss_name"), body.get("items")
        if not isinstance(ss_name, str) or not isinstance(items, list):
            raise self.ic.Refused("start_items: 'ss_name' and 'items' are required", code="bad_request")
        self.worker.count("start_items_robot" if self.robot else "start_items_server")
        uri = body.get("ros_master_uri")
        if not self.robot:
            if ss_name not in self.spaces:
                taken = set(self.spaces.values())
                while self.next_port in taken:
                    self.next_port += 1
                self.spaces[ss_name] = self.next_port
                self.next_port += 1
            uri = f"http://{self.address}:{self.spaces[ss_name]}/"
        answer = {"ros_master_uri": uri, "items": [_item_report(e, self.name) for e in items if isinstance(e, dict)],
                  "reason": None, "inbound_port": None}
        delay = self.worker.robot_start if self.robot else self.worker.server_start

        def done():
            if self.robot and self.peer is peer:
                self.items_at = time.time()
                self.ros_master_uri = uri
            return answer
        peer = self.peer
        return task.deferLater(self.worker.reactor, delay, done) if delay > 0 else done()

    def state(self):
        return {"robot": self.robot, "address": self.address, "wanted": self.wanted, "connected": self.peer is not None,
                "accepted": self.accepted, "sessions": self.sessions, "accepted_at": self.accepted_at,
                "items_at": self.items_at, "ros_master_uri": self.ros_master_uri,
                "spaces": sorted(self.spaces)}


class Worker:
    """The simulated agents of one process and what they measured; serves the driver's commands."""

    def __init__(self, reactor, master, heartbeat, misses, server_start=0.0, robot_start=0.0):
        host, port = master.rsplit(":", 1)
        self.reactor = reactor
        self.master_host, self.master_port = host, int(port)
        self.heartbeat = heartbeat
        self.misses = misses
        self.server_start = server_start
        self.robot_start = robot_start
        self.agents = {}
        self.counters = {}
        self.samples = {"hello": [], "heartbeat": [], "lag": []}
        self.losses = []             # [time.time(), name, why] of sessions the simulator did not end
        self._lag_at = None

    def count(self, what, n=1):
        self.counters[what] = self.counters.get(what, 0) + n

    def sample(self, kind, value):
        values = self.samples[kind]
        if len(values) < MAX_SAMPLES:
            values.append(value)

    def lost(self, name, why):
        self.count("sessions_lost")
        if len(self.losses) < MAX_SAMPLES:
            self.losses.append([time.time(), name, str(why)[:200]])

    def start_lag_probe(self):
        from twisted.internet import task
        self._lag_at = time.monotonic()

        def look():
            now = time.monotonic()
            self.sample("lag", max(0.0, now - self._lag_at - LAG_EVERY))
            self._lag_at = now
        loop = task.LoopingCall(look)
        loop.clock = self.reactor
        loop.start(LAG_EVERY, now=False)

    # -- commands -----------------------------------------------------------------------------------------
    def command(self, message):
        cmd = message.get("cmd")
        names = message.get("names")
        chosen = list(self.agents.values()) if names is None else [self.agents[n] for n in names if n in self.agents]
        if cmd == "add":
            for spec in message["agents"]:
                self.agents[spec["name"]] = SimAgent(self, spec["name"], spec["address"], spec.get("robot", True),
                                                     spec.get("capacity"))
            return len(self.agents)
        if cmd in ("start", "leave", "crash"):
            for agent in chosen:
                getattr(agent, cmd)()
            return len(chosen)
        if cmd == "agents":
            return {agent.name: agent.state() for agent in chosen}
        if cmd == "stats":
            answer = {"counters": dict(self.counters), "samples": self.samples, "losses": list(self.losses),
                      "cpu": sum(os.times()[:2])}
            if message.get("reset"):
                self.samples = {kind: [] for kind in self.samples}
            return answer
        raise ValueError(f"unknown command {cmd!r}")


def worker_main(argv):
    parser = argparse.ArgumentParser(prog="fleet_sim worker")
    parser.add_argument("--master", required=True, help="HOST:PORT of the master's agent port")
    parser.add_argument("--heartbeat", type=float, default=2.0)
    parser.add_argument("--misses", type=int, default=3)
    parser.add_argument("--server-start", type=float, default=0.0)
    parser.add_argument("--robot-start", type=float, default=0.0)
    args = parser.parse_args(argv)
    raise_nofile()
    try:   # the master agent runs 5 nice levels up when it can (rcmp_ms.raise_agent_priority): so do we, so that
        os.nice(-5)   # other work on the machine does not pass for the master's latency
    except OSError:
        pass
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    # the watchdogs' "gone" lines are counted as losses; the protocol's own warnings stay in the log
    logging.getLogger("rcmp.wd").setLevel(logging.ERROR)
    from twisted.internet import reactor, stdio
    from twisted.protocols.basic import LineReceiver

    worker = Worker(reactor, args.master, args.heartbeat, args.misses, args.server_start, args.robot_start)

    class Commands(LineReceiver):
        delimiter = b"\n"
        MAX_LENGTH = MAX_COMMAND

        def lineReceived(self, line):
            message = json.loads(line)
            if message.get("cmd") == "quit":
                for agent in worker.agents.values():
                    agent.wanted = False
                    if agent.peer is not None:
                        agent.ending = "quit"
                        agent.peer.abort("the simulator stops")
                self.sendLine(json.dumps({"id": message.get("id"), "result": True}).encode())
                reactor.callLater(0.1, reactor.stop)
                return
            try:
                answer = {"id": message.get("id"), "result": worker.command(message)}
            except Exception as exc:  # a driver's mistake: said, never fatal
                answer = {"id": message.get("id"), "error": f"{type(exc).__name__}: {exc}"}
            self.sendLine(json.dumps(answer, separators=(",", ":")).encode())

        def connectionLost(self, reason=None):
            if reactor.running:       # the driver went away: so do we
                reactor.stop()

    stdio.StandardIO(Commands())
    worker.start_lag_probe()
    reactor.run()
    return 0


# -- the driver's side --------------------------------------------------------------------------------------

class Fleet:
    """``workers`` simulator processes against the master at ``master_host:ic_port``; their agents by name.

    ``add(specs)`` spreads agents (``{"name", "address", "robot", "capacity"}``) over the workers;
    ``start(names)``, ``leave(names)``, ``crash(names)`` (None: every agent); ``agents(names)`` their states;
    ``stats(reset)`` the merged measurements; ``close()`` ends the workers (also on error: use ``with``).
    """

    def __init__(self, procs, master_host, ic_port, heartbeat=2.0, misses=3, workers=1, server_start=0.0,
                 robot_start=0.0):
        self.procs = procs
        self.workers = []
        self.where = {}              # agent name -> worker index
        self._next = 0
        env = dict(os.environ)
        env["PYTHONPATH"] = ROOT + (":" + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        argv = [PYTHON, "-m", "bench.fleet_sim", "worker", "--master", f"{master_host}:{ic_port}",
                "--heartbeat", str(heartbeat), "--misses", str(misses), "--server-start", str(server_start),
                "--robot-start", str(robot_start)]
        for index in range(workers):
            log_path = os.path.join(procs.log_dir or "/tmp", f"fleet-worker-{index}.log")
            with open(log_path, "ab") as log:
                proc = procs.start(argv, env=env, name=f"fleet-worker-{index}", cwd=ROOT, stdin=subprocess.PIPE,
                                   stdout=subprocess.PIPE, stderr=log)
            proc.log_path = log_path
            self.workers.append(proc)

    @property
    def pids(self):
        return [proc.pid for proc in self.workers]

    def _ask(self, index, message):
        proc = self.workers[index]
        proc.stdin.write(json.dumps(message).encode() + b"\n")
        proc.stdin.flush()
        line = proc.stdout.readline()
        if not line:
            raise RuntimeError(f"simulator worker {index} ended: {self._tail(proc)}")
        answer = json.loads(line)
        if "error" in answer:
            raise RuntimeError(f"simulator worker {index}: {answer['error']}")
        return answer["result"]

    @staticmethod
    def _tail(proc):
        try:
            with open(proc.log_path, "rb") as f:
                return f.read()[-2000:].decode("utf-8", "replace")
        except OSError:
            return "(no log)"

    def _each(self, cmd, names=None, **extra):
        """Send ``cmd`` to the workers holding ``names`` (all when None); [(index, result)]."""
        if names is None:
            targets = {index: None for index in range(len(self.workers))}
        else:
            targets = {}
            for name in names:
                targets.setdefault(self.where[name], []).append(name)
        return [(index, self._ask(index, dict(extra, cmd=cmd, names=chosen))) for index, chosen in targets.items()]

    def add(self, specs):
        per_worker = {}
        for spec in specs:
            index = self._next % len(self.workers)
            self._next += 1
            self.where[spec["name"]] = index
            per_worker.setdefault(index, []).append(spec)
        for index, chosen in per_worker.items():
            self._ask(index, {"cmd": "add", "agents": chosen})

    def add_robots(self, names, first=0):
        self.add([{"name": n, "address": robot_address(first + i), "robot": True} for i, n in enumerate(names)])

    def add_servers(self, names, capacity, first=0):
        self.add([{"name": n, "address": server_address(first + i), "robot": False, "capacity": capacity}
                  for i, n in enumerate(names)])

    def start(self, names=None):
        self._each("start", names)

    def leave(self, names=None):
        self._each("leave", names)

    def crash(self, names=None):
        self._each("crash", names)

    def agents(self, names=None):
        merged = {}
        for _, result in self._each("agents", names):
            merged.update(result)
        return merged

    def stats(self, reset=False):
        """Merged: counters summed, samples joined, losses sorted by time, ``cpu`` per worker."""
        merged = {"counters": {}, "samples": {}, "losses": [], "cpu": []}
        for _, result in self._each("stats", None, reset=reset):
            for key, value in result["counters"].items():
                merged["counters"][key] = merged["counters"].get(key, 0) + value
            for kind, values in result["samples"].items():
                merged["samples"].setdefault(kind, []).extend(values)
            merged["losses"].extend(result["losses"])
            merged["cpu"].append(result["cpu"])
        merged["losses"].sort()
        return merged

    def close(self):
        """End every worker (their connections are dropped at once) and reap it."""
        for index, proc in enumerate(self.workers):
            if proc.poll() is None:
                try:
                    self._ask(index, {"cmd": "quit"})
                except (OSError, RuntimeError, ValueError):
                    pass
        for proc in self.workers:
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                pass
            for stream in (proc.stdin, proc.stdout):
                try:
                    stream.close()
                except OSError:
                    pass
            if proc in self.procs.children:
                self.procs.stop(proc)
                self.procs.children.remove(proc)
        self.workers = []

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] != ["worker"]:
        sys.stderr.write("usage: python3 -m bench.fleet_sim worker --master HOST:PORT [options]\n")
        return 2
    if ROOT not in sys.path:
        sys.path.insert(0, ROOT)
    return worker_main(argv[1:])


if __name__ == "__main__":
    sys.exit(main())
