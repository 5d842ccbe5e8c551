"""Shared pools benchmark: a legitimate client from another address is served while other addresses hold their
whole share of each shared pool, on a real master and on a real FIROS. Writes the section "pools" of
docs/PERFORMANCE.md (``bench.report``); ``main`` returns 1 when the target is missed.

The master (``/usr/bin/python3 -m rcm_platform --home TMP`` on loopback): from 127.0.0.9, ``SAMPLES`` times
each, a console event stream's first ``snapshot`` (a new stream each time), a ``GET /platform_instance/read`` on
a new connection, and a hello's answer on the agent port (a name that is not provisioned: the refusal is the
answer). Once quiet, once with every pool held at once: 64 console streams opened from 127.0.0.2 and 127.0.0.3
and never read (the attack the console once lost every operator to), the RDAPI's 32 connections of 127.0.0.4
opened and never used, and the agent port's 8 connections of 127.0.0.5 that never say hello (opened again as the
master closes them).

FIROS (``rosrun firos core.py`` with a ROS master of its own, the stand-in broker ``tests/ngsi_broker`` and a
robot, ``tests/support/firos_talker.py``, all children on loopback; the master above is stopped by then): a
``GET /robots`` from 127.0.0.9, and a broker notification ``POST /firos`` commanding the robot's topic from
127.0.0.1 (the broker's address, to which FIROS gives the broker's share), each on a new connection, ``SAMPLES``
times each at one pair every ``SAMPLE_EVERY`` s, so that the held samples span more than a connection's lifetime
(30 s). Quiet, then while the attack FIROS once lost the broker's commands to goes on: 16 keep-alive connections
from 127.0.0.2 and 127.0.0.3, each sending a small ``GET /robots`` every ``TRICKLE_EVERY`` s (a connection FIROS
closes at its lifetime is opened again at once, a refused one tried again at its next tick), which leaves each
address its share of 4. Then the notification alone again while three addresses hold every worker not kept for
the broker (24 such connections, 12 held): a read from a fourth address is refused then (a share per address
does not stop an attacker with many addresses), the broker's notification must not be.

Target: every sample served (a 200; every notification's command received by the robot) and p99 under 250 ms
while the pools are held. The console's watchers' socket is not measured (the section says why).

Run: ``make bench-pools`` (FIROS is started with ``rosrun``, so the catkin overlay is needed).
"""

import collections
import http.client
import json
import os
import pathlib
import socket
import struct
import sys
import tempfile
import threading
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

from bench.report import load_average, percentile, write_section  # noqa: E402
from tests.ngsi_broker.testing import start_broker  # noqa: E402
from tests.support.firos import Firos, received, talker, write_config  # noqa: E402
from tests.support.polling import WaitTimeout, wait_until  # noqa: E402
from tests.support.processes import ProcessGroup  # noqa: E402
from tests.support.rcmp_agent import RcmpAgent  # noqa: E402
from tests.support.rosmaster import RosMaster  # noqa: E402

SAMPLES = 50
TARGET_P99_MS = 250.0
CLIENT = "127.0.0.9"
BROKER_SOURCE = "127.0.0.1"     # the stand-in broker's address: FIROS gives it the broker's share
ROBOT = "end_end_test"          # the robot of FIROS's test whitelist; p1 is its commanded topic
TRICKLE_EVERY = 8.0             # the attacker's pace: one request on each connection every 8 s
RETRY_AFTER = 1.0               # FIROS's Retry-After on a 503
SAMPLE_EVERY = 0.8              # the client's pace at FIROS: SAMPLES pairs span 40 s, past a connection's lifetime


def _connect(port, source, timeout=10):
    return socket.create_connection(("127.0.0.1", port), timeout=timeout, source_address=(source, 0))


def _http_request(port, path, complete, close=False, source=CLIENT, body=None):
    """Seconds from sending ``GET path`` (``POST`` of the JSON ``body`` when given) from ``source`` on a new
    connection until ``complete(data so far)`` (or, without it, the server closing the connection);
    ConnectionError unless the answer is a 200."""
    started = time.monotonic()
    with _connect(port, source) as sock:
        extra, data, method = "Connection: close\r\n" if close else "", b"", "GET"
        if body is not None:
            data, method = json.dumps(body).encode(), "POST"
            extra += f"Content-Type: application/json\r\nContent-Length: {len(data)}\r\n"
        sock.sendall(f"{method} {path} HTTP/1.1\r\nHost: 127.0.0.1\r\n{extra}\r\n".encode() + data)
        data = b""
        while not (complete and complete(data)):
            chunk = sock.recv(65536)
            if not chunk:
                if complete:
                    raise ConnectionError(f"closed early: {data[:200]!r}")
                break
            data += chunk
        if not data.startswith(b"HTTP/1.1 200"):
            raise ConnectionError(data.split(b"\r\n", 1)[0].decode())
    return time.monotonic() - started


def first_snapshot(master):
    """Seconds from a new stream's request to its whole snapshot event."""
    return _http_request(master.ext_port, "/console/api/events",
                         lambda data: b"\n\n" in data.split(b"event: snapshot", 1)[-1] and b"event: snapshot" in data)


def rdapi_read(master):
    return _http_request(master.ext_port, "/platform_instance/read", None, close=True)


def hello_answer(master):
    started = time.monotonic()
    with _connect(master.ic_port, CLIENT) as sock:
        body = json.dumps({"v": 1, "id": 1, "kind": "req", "op": "hello", "body": {
            "name": "stranger", "address": CLIENT, "robot": True, "version": 1}}).encode()
        sock.sendall(struct.pack("!I", len(body)) + body)
        header = sock.recv(4)
        if len(header) < 4:
            raise ConnectionError("closed before the answer")
        length = struct.unpack("!I", header)[0]
        data = b""
        while len(data) < length:
            chunk = sock.recv(length - len(data))
            if not chunk:
                raise ConnectionError("closed in the answer")
            data += chunk
        if json.loads(data)["body"].get("code") != "not_provisioned":
            raise ConnectionError(data[:200].decode())
    return time.monotonic() - started


class Holders:
    """The pools held: streams never read, RDAPI connections never used, agent connections that never say hello
    (opened again, in a thread, as soon as the master closes them)."""

    def __init__(self, master):
        self.master = master
        self.socks = []
        self.stop = threading.Event()
        self.streams_accepted = 0
        for n in range(64):
            sock = _connect(master.ext_port, "127.0.0.2" if n % 2 else "127.0.0.3")
            sock.sendall(b"GET /console/api/events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
            self.streams_accepted += sock.recv(12).startswith(b"HTTP/1.1 200")
            self.socks.append(sock)
        self.socks += [_connect(master.ext_port, "127.0.0.4") for _ in range(32)]
        self.thread = threading.Thread(target=self._hold_agent_port, daemon=True)
        self.thread.start()

    def _hold_agent_port(self):
        held = []
        while not self.stop.is_set():
            held = [s for s in held if not _closed(s)]
            while len(held) < 8:
                held.append(_connect(self.master.ic_port, "127.0.0.5"))
            self.stop.wait(0.2)
        for sock in held:
            sock.close()

    def close(self):
        self.stop.set()
        self.thread.join()
        for sock in self.socks:
            sock.close()


def _closed(sock):
    sock.setblocking(False)
    try:
        return sock.recv(1, socket.MSG_PEEK) == b""
    except BlockingIOError:
        return False
    except OSError:
        return True
    finally:
        sock.setblocking(True)


def measure(master):
    rows = {}
    for name, probe in (("console event stream: first snapshot", first_snapshot),
                        ("RDAPI: GET /platform_instance/read, new connection", rdapi_read),
                        ("agent port: a hello answered", hello_answer)):
        times, failed = [], 0
        for _ in range(SAMPLES):
            try:
                times.append(probe(master))
            except OSError:
                failed += 1
        rows[name] = (times, failed)
    return rows


MASTER_HOLDING = {"RDAPI: GET /platform_instance/read, new connection": "32 connections, never used",
                  "agent port: a hello answered": "8 connections that never say hello"}


def measure_master(procs, home):
    """The master's rows ``(pool, what is held, quiet, held)``, each of quiet and held ``(times, failed)``; the
    master is stopped (and checked gone) before this returns."""
    master = RcmpAgent(procs, home).start()
    try:
        quiet = measure(master)
        holders = Holders(master)
        try:
            held = measure(master)
        finally:
            holders.close()
    finally:
        procs.stop(master.process)
    holding = dict(MASTER_HOLDING)
    holding["console event stream: first snapshot"] = ("64 streams from two addresses, never read "
                                                       f"({holders.streams_accepted} accepted)")
    return [(name, holding[name], quiet[name], held[name]) for name in quiet]


# --- FIROS's worker pool ------------------------------------------------------------------------------------------

FIROS_READ = "FIROS: GET /robots, new connection"
FIROS_NOTE = "FIROS: the broker's notification POST /firos from its address, new connection"
FIROS_RESERVE = "FIROS: the broker's notification, while the workers not kept for the broker are held"


def firos_read(firos, _token):
    return _http_request(firos.port, "/robots", None, close=True)


def firos_notification(firos, token):
    """A v2 notification as the broker sends it, from the broker's address, commanding the robot's p1 with
    ``token``."""
    return _http_request(firos.port, "/firos", None, close=True, source=BROKER_SOURCE, body={
        "subscriptionId": "0" * 24, "data": [{
            "id": ROBOT, "type": "ROBOT", "p1": {"type": "std_msgs.msg.String", "value": {"data": token},
                                                "metadata": {}},
            "COMMAND": {"type": "COMMAND", "value": ["p1"], "metadata": {}}}]})


class Trickle:
    """The attack on FIROS's pool: ``count`` keep-alive connections from ``sources`` (in turn), each sending one
    small ``GET /robots`` every TRICKLE_EVERY s. A connection FIROS closes at its lifetime is opened again at
    once (and, when that is refused because FIROS has not yet counted the old one out, once more after FIROS's
    ``Retry-After``); one refused (503) or cut is tried again at its next tick. ``held``: the connections FIROS
    keeps open now; ``counts()``: how many FIROS closed at their lifetime, refused, or cut so far."""

    def __init__(self, port, sources, count):
        self.port = port
        self.held = 0
        self._counts = {"lifetime": 0, "refused": 0, "cut": 0}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._connection, args=(sources[n % len(sources)],), daemon=True)
                         for n in range(count)]
        for thread in self._threads:
            thread.start()

    def _connection(self, source):
        conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=15, source_address=(source, 0))
        held = reopening = False
        try:
            while not self._stop.is_set():
                try:
                    conn.request("GET", "/robots")
                    answer = conn.getresponse()
                    answer.read()
                    status, closing = answer.status, answer.will_close
                except (OSError, http.client.HTTPException):
                    status, closing = None, True
                    conn.close()
                lifetime = status == 200 and closing
                with self._lock:
                    self.held += (status == 200 and not closing) - held
                    outcome = "lifetime" if lifetime else "refused" if status == 503 else "cut" if closing else None
                    if outcome:
                        self._counts[outcome] += 1
                held = status == 200 and not closing
                if status == 503 and reopening:
                    self._stop.wait(RETRY_AFTER)    # its place may not be free yet: once more, as FIROS's 503 says
                elif not lifetime:
                    self._stop.wait(TRICKLE_EVERY)         # the attacker's pace
                reopening = lifetime
        finally:
            with self._lock:
                self.held -= held
            conn.close()

    def counts(self):
        with self._lock:
            return dict(self._counts)

    def stop(self):
        self._stop.set()
        for thread in self._threads:
            thread.join(30)


def start_firos(procs, tmp):
    """A ROS master, the stand-in broker, the robot (publishing s1, printing what it gets on p1) and FIROS, all
    children of ``procs``; (FIROS, the robot's process) once FIROS has the robot with p1."""
    master = RosMaster(procs).start()
    broker = start_broker(procs, extra_args=["--quiet"])
    config = write_config(os.path.join(tmp, "firos-config"), broker.port, log_level="INFO")
    robot = talker(procs, master, pathlib.Path(tmp), "--rate", "5", "--pub", f"/{ROBOT}/s1", "std_msgs/String",
                   json.dumps({"data": "hello"}), "--sub", f"/{ROBOT}/p1", "std_msgs/String")
    firos = Firos(procs, master, config).start()
    wait_until(lambda: "p1" in {t["name"] for t in firos.robots().get(ROBOT, {}).get("topics", [])}, timeout=20,
               message=f"FIROS to connect {ROBOT} with p1")
    return firos, robot


def commands_received(procs, robot, tokens):
    """The commands of ``tokens`` the robot printed having received."""
    return set(tokens) & {message.get("data") for message in received(procs, robot, f"/{ROBOT}/p1")}


def measure_firos(firos, phase, probes, attack=None):
    """``SAMPLES`` rounds, one every SAMPLE_EVERY s, each timing every probe of ``probes`` ({row: probe(firos,
    token)}) once. Returns ({row: (times, failed)}, {row: the tokens of the samples answered 200}, the attack's
    held connections at each round)."""
    times, failed, served, held = {row: [] for row in probes}, dict.fromkeys(probes, 0), {row: [] for row in probes}, []
    start = time.monotonic()
    for i in range(SAMPLES):
        pause = start + i * SAMPLE_EVERY - time.monotonic()
        if pause > 0:
            time.sleep(pause)       # the client's pace: the samples spread over 40 s (not synchronisation)
        if attack is not None:
            held.append(attack.held)
        for row, probe in probes.items():
            token = f"{phase}-{i}"
            try:
                times[row].append(probe(firos, token))
                served[row].append(token)
            except OSError:
                failed[row] += 1
    return {row: (times[row], failed[row]) for row in probes}, served, held


def measure_firos_pool(procs, tmp):
    """FIROS's rows (as ``measure_master``'s), the sentences saying what happened meanwhile, and (commands the
    robot received, commands answered 200)."""
    firos, robot = start_firos(procs, tmp)
    warm_up = []

    def first_command_arrived():    # FIROS makes p1's publisher at the first command: its connection takes a moment
        warm_up.append(f"warm-up-{len(warm_up)}")
        firos_notification(firos, warm_up[-1])
        return commands_received(procs, robot, warm_up)
    wait_until(first_command_arrived, timeout=20, interval=0.5, message="the robot to receive a first command")
    probes = {FIROS_READ: firos_read, FIROS_NOTE: firos_notification}
    quiet, served, _ = measure_firos(firos, "quiet", probes)
    tokens = served[FIROS_NOTE]
    attack = Trickle(firos.port, ("127.0.0.2", "127.0.0.3"), 16)
    try:
        wait_until(lambda: attack.held == 8, timeout=30, message="the attack to hold its two shares of 4")
        before = attack.counts()
        held, served, seen = measure_firos(firos, "held", probes, attack)
        during = {key: value - before[key] for key, value in attack.counts().items()}
    finally:
        attack.stop()
    tokens += served[FIROS_NOTE]
    wide = Trickle(firos.port, ("127.0.0.2", "127.0.0.3", "127.0.0.4"), 24)
    try:
        wait_until(lambda: wide.held == 12, timeout=30, message="the attack to hold the 12 workers not kept for "
                                                                "the broker")
        try:
            firos_read(firos, None)
            fourth = "200"
        except OSError as exc:       # the 503's status line, or why no answer came
            fourth = str(exc)
        reserve, served, wide_seen = measure_firos(firos, "reserve", {FIROS_NOTE: firos_notification}, wide)
    finally:
        wide.stop()
    tokens += served[FIROS_NOTE]
    try:
        wait_until(lambda: len(commands_received(procs, robot, tokens)) == len(tokens), timeout=15,
                   message="the robot to receive every command answered 200")
    except WaitTimeout:
        pass                        # reported below: the target needs every one
    got = len(commands_received(procs, robot, tokens))
    trickling = "16 keep-alive connections from two addresses, a small request every 8 s each"
    rows = [(FIROS_READ, f"{trickling} (held: {_held_at(seen)})", quiet[FIROS_READ], held[FIROS_READ]),
            (FIROS_NOTE, f"{trickling} (held: {_held_at(seen)})", quiet[FIROS_NOTE], held[FIROS_NOTE]),
            (FIROS_RESERVE, f"the same, 24 connections from three addresses (held: {_held_at(wide_seen)})",
             quiet[FIROS_NOTE], reserve[FIROS_NOTE])]
    notes = (f"While two addresses trickled, FIROS closed {during['lifetime']} of their connections at their "
             f"lifetime (each opened again at once), refused {during['refused']} (503) and cut "
             f"{during['cut']}. While three held every worker not kept for the broker, a read from {CLIENT} was "
             f"answered `{fourth}`: a share per address does not stop an attacker with many addresses. The robot "
             f"received {got} of the {len(tokens)} commands answered 200.")
    return rows, notes, (got, len(tokens))


def _held_at(values):
    """How many connections were held at the samples: "8 at every sample", or "8 at 44 samples, 7 at 6"."""
    counts = collections.Counter(values)
    if len(counts) == 1:
        return f"{values[0]} at every sample"
    return ", ".join(f"{held} at {n} samples" if i == 0 else f"{held} at {n}"
                     for i, (held, n) in enumerate(sorted(counts.items(), reverse=True)))


def _ms(values, fraction):
    return f"{percentile(values, fraction) * 1000:.1f}" if values else "-"


def main(argv=None):
    tmp = tempfile.mkdtemp(prefix="bench-pools-")
    for folder in ("logs", "master"):
        os.makedirs(os.path.join(tmp, folder))
    procs = ProcessGroup(log_dir=os.path.join(tmp, "logs"))
    load_before = load_average()
    try:
        rows = measure_master(procs, os.path.join(tmp, "master"))
        firos_rows, notes, (got, commands) = measure_firos_pool(procs, tmp)
    finally:
        procs.stop_all()
    lines = ["| pool | what other addresses hold | quiet p50 ms | quiet p99 ms | held p50 ms | held p99 ms | "
             "held: not served |", "| --- | --- | ---: | ---: | ---: | ---: | ---: |"]
    worst, unserved = 0.0, 0
    for name, holding, (quiet, _), (held, failed) in rows + firos_rows:
        worst = max(worst, percentile(held, 0.99) * 1000 if held else float("inf"))
        unserved += failed
        lines.append(f"| {name} | {holding} | {_ms(quiet, 0.5)} | {_ms(quiet, 0.99)} | {_ms(held, 0.5)} | "
                     f"{_ms(held, 0.99)} | {failed} of {SAMPLES} |")
    met = unserved == 0 and worst < TARGET_P99_MS and got == commands
    body = (f"`bench/bench_pools.py`: a client from {CLIENT} measured {SAMPLES} times per pool, each time on a new "
            "connection, quiet and while other addresses hold their whole share. The master's pools (a real master "
            "on loopback) are held all at once, the console's streams as in the attack the tests replay (64 from two "
            "addresses, never read). FIROS's worker pool (a real FIROS with its ROS master, the stand-in broker and a "
            "robot on loopback; the master stopped by then): a read from "
            f"{CLIENT} and the broker's notification commanding the robot, from the broker's address "
            f"{BROKER_SOURCE}, one pair every {SAMPLE_EVERY} s so that the held samples span more than a "
            "connection's 30 s lifetime; held as in the attack the tests replay (16 keep-alive connections from two "
            "addresses, a small request every 8 s each, which leaves each address its share of 4), then by 24 such "
            "connections from three addresses, which hold the 12 workers not kept for the broker.\n\n"
            + "\n".join(lines) + "\n\n" + notes + "\n\n"
            "The console's topic watchers' socket is not measured: it is a Unix socket that keeps only a watcher "
            "process the agent started, with its one-time key, and closes every other connection at once, so no "
            "other client has a share of it to hold.\n\n"
            f"Load average (1 / 5 min) {load_before} before, {load_average()} after.\n\n"
            f"Target: every request served (every command received) and p99 under {TARGET_P99_MS:.0f} ms while "
            f"the pools are held: {'met' if met else 'MISSED'} (worst p99 {worst:.1f} ms, {unserved} not served, "
            f"{commands - got} commands not received).")
    write_section("pools", "Shared pools: another address served while others hold their share", body)
    print(body)
    return 0 if met else 1


if __name__ == "__main__":
    sys.exit(main())
