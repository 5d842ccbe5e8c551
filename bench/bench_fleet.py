"""Fleet scale: one real master coordinating N simulated robots on S simulated server VMs.

The master runs as users run it: ``python3 -m rcm_platform --home DIR`` on loopback with ``max_service_spaces 0``
(a pure coordinator), its real SQLite, RDAPI and console, heartbeats every 2 s (3 misses), and the open-file limit
``rcmpd`` gives it (its hard limit here). The fleet is ``bench/fleet_sim.py``: robots and server VMs speaking the
real agent protocol from their own loopback addresses, starting no ROS process (a server VM answers
``start_items`` after ``--server-start`` seconds, a robot after ``--robot-start``, standing for their ROS masters
and nodes). Every robot has one S-side and one R-side node.

For each N (default 500, 1,000, 2,000; ``--robots`` for others) over S servers (default 20), with one console
event stream open throughout (an operator watching):

- time from starting all robots at once to all paired (the last robot shown paired on the console's stream,
  confirmed by ``platform_instance/read``), hello answer p50/p99 and heartbeat round trip p99 as the robots see
  them;
- steady state (all paired, nothing changing, ``--steady`` seconds): the master agent's CPU (% of one core) and
  resident memory, heartbeat round trip p99;
- ``GET /platform_instance/read`` p50/p99 and size (each on a fresh connection, as ``curl`` does);
- the console: from a change to the patch that shows it on a raw event-stream client, p50/p99: a robot
  provisioned or removed through the RDAPI, a simulated robot leaving, and its space paired again when it
  returns (from the moment it answered ``start_items``, the last step of pairing);
- failover: the server hosting the most spaces (N/S) crashes (its connection dropped); the time until all of its
  robots are shown paired on other servers;
- sessions lost that nobody ended (the simulator's robots that lost a session it did not end, and the master's
  "ending robot" lines for robots the simulator did not make leave);
- a growth table: each figure divided by N.

The master runs under ``bench/agent_probe.py``, which measures its event loop's lateness and its full garbage
collections in each phase; ``--profile DIR`` also profiles it with ``cProfile`` (one file per N and phase, read
with ``pstats``) to find what costs.
Results go to docs/PERFORMANCE.md (section ``fleet``); ``main`` returns 1 when a target for N = 2,000 is missed.
Run it alone with ``./run bench-fleet`` (or ``python3 -m bench.bench_fleet --robots 500``).
"""

import argparse
import contextlib
import http.client
import json
import os
import re
import resource
import signal
import sys
import tempfile
import threading
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

from bench.fleet_sim import Fleet, raise_nofile  # noqa: E402
from bench.report import load_average, percentile, write_section  # noqa: E402
from tests.support.polling import WaitTimeout, wait_until  # noqa: E402
from tests.support.processes import ProcessGroup  # noqa: E402
from tests.support.rcmp_agent import RcmpAgent  # noqa: E402

OPTIONS = ("--quick",)
TARGET_N = 2000
TARGETS = {   # figure -> (limit, unit) for N = 2,000 over 20 servers (the fleet's targets)
    "pair_all": (60.0, "s"), "hello_p99": (0.200, "s"), "heartbeat_p99": (0.100, "s"), "cpu": (25.0, "%"),
    "rss": (400.0, "MB"), "read_p99": (0.100, "s"), "console_p99": (1.0, "s"), "failover": (15.0, "s"),
    "lost": (0, ""),
}
LOGIC = [{"sn_package": "robotics_test", "sn_type": "talker.py", "sn_name": "brain", "sn_params": "_topic:=brain",
          "sn_side": "S"},
         {"sn_package": "robotics_test", "sn_type": "talker.py", "sn_name": "body", "sn_params": "_topic:=body",
          "sn_side": "R"}]
SESSION_ENDED = re.compile(r"ending robot (\w+)'s session: (.*)")


# -- the master ---------------------------------------------------------------------------------------------

class Master(RcmpAgent):
    """The master agent under ``bench.agent_probe``: ``phase(name)`` measures its event loop's lateness and its
    garbage collections during one phase (and profiles it when ``profile`` is set)."""

    def __init__(self, procs, home, probe_prefix, profile=False, env=None, **keys):
        self.probe_prefix = probe_prefix
        self.profile = profile
        super().__init__(procs, home, role="master", args=["--no-stderr"], env=env, **keys)

    def argv(self):
        python = super().argv()[0]
        return [python, "-m", "bench.agent_probe", *(["--profile"] if self.profile else []), self.probe_prefix,
                "--home", self.home, *self.args]

    @contextlib.contextmanager
    def phase(self, name, into):
        """Probe the master during the block; ``into[name]`` gets ``{"lag": [...], "gc": [...]}``."""
        with open(self.probe_prefix + ".phase", "w") as f:
            f.write(name)
        self.process.send_signal(signal.SIGUSR1)
        try:
            yield
        finally:
            self.process.send_signal(signal.SIGUSR2)
            path = f"{self.probe_prefix}-{name}.json"
            try:
                into[name] = wait_until(lambda: _load_json(path), timeout=30, message=f"the probe's {path}")
            except WaitTimeout:
                into[name] = {"lag": [], "gc": []}


def _load_json(path):
    try:
        with open(path) as f:
            return json.load(f)
    except (OSError, ValueError):
        return None


class Http:
    """Keep-alive RDAPI calls for provisioning many robots quickly."""

    def __init__(self, master):
        self.conn = http.client.HTTPConnection(master.host, master.ext_port, timeout=60)

    def post(self, path, body):
        self.conn.request("POST", path, body=json.dumps(body), headers={"Content-Type": "application/json"})
        resp = self.conn.getresponse()
        answer = json.loads(resp.read())
        if resp.status != 200:
            raise RuntimeError(f"POST {path} {body}: {resp.status} {answer}")
        return answer

    def close(self):
        self.conn.close()


def read_rows(master, timeout=30):
    """``GET /platform_instance/read`` on a fresh connection: (seconds, bytes, rows by name)."""
    started = time.monotonic()
    conn = http.client.HTTPConnection(master.host, master.ext_port, timeout=timeout)
    try:
        conn.request("GET", "/platform_instance/read")
        resp = conn.getresponse()
        raw = resp.read()
    finally:
        conn.close()
    elapsed = time.monotonic() - started
    if resp.status != 200:
        raise RuntimeError(f"platform_instance/read answered {resp.status}")
    return elapsed, len(raw), {row["pi_name"]: row for row in json.loads(raw)["reason"]}


def master_port_cap():
    """The master's default agent-port cap: a quarter of the open-file limit it raises itself to at start (the hard
    limit it inherits from us, at most ``NOFILE_CEILING``)."""
    from rcm_platform.rcmp_resources import NOFILE_CEILING
    hard = resource.getrlimit(resource.RLIMIT_NOFILE)[1]
    return (NOFILE_CEILING if hard == resource.RLIM_INFINITY else min(hard, NOFILE_CEILING)) // 4


def hello_buckets(master):
    """The master's own hello answer times (``rcm_hello_duration_seconds`` of ``/metrics``: the log writes only
    the first hellos of each 10 s) as ``[(upper bound, cumulative count)]``."""
    conn = http.client.HTTPConnection(master.host, master.ext_port, timeout=30)
    try:
        conn.request("GET", "/metrics")
        text = conn.getresponse().read().decode()
    finally:
        conn.close()
    found = re.findall(r'^rcm_hello_duration_seconds_bucket\{le="([^"]+)"\} ([0-9.e+]+)$', text, re.M)
    return [(float(bound), float(count)) for bound, count in found]


def bucket_p(buckets, q):
    """The upper bound of the histogram bucket holding quantile ``q`` of ``[(bound, cumulative count)]``."""
    total = buckets[-1][1]
    for bound, count in buckets:
        if count >= q * total:
            return bound
    return float("inf")


def proc_cpu(pid):
    """User + system CPU seconds of process ``pid`` (all its threads) so far."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def main_thread_cpu(pid):
    """CPU seconds of the main thread (the reactor) of process ``pid`` so far."""
    return proc_cpu(f"{pid}/task/{pid}")


def proc_rss_mb(pid):
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def listen_overflows():
    """This machine's count of connections its listening sockets' accept queues had no room for (all sockets:
    other work on the machine counts too), from /proc/net/netstat ``TcpExt ListenOverflows``."""
    try:
        with open("/proc/net/netstat") as f:
            rows = [line.split() for line in f if line.startswith("TcpExt:")]
        return int(dict(zip(rows[0], rows[1]))["ListenOverflows"])
    except (OSError, IndexError, KeyError, ValueError):
        return -1


def proc_fds(pid):
    try:
        return len(os.listdir(f"/proc/{pid}/fd"))
    except OSError:
        return -1


# -- the console, as a raw event-stream client ----------------------------------------------------------------

class ConsoleClock:
    """Reads ``/console/api/events`` in a thread; keeps every robot's (connected, paired, server) as pushed and
    when each changed (``time.time()``), so that a change made at time T can be timed to the push showing it."""

    def __init__(self, master):
        self.master = master
        self.lock = threading.Lock()
        self.rows = {}               # name -> (connected, paired, server)
        self.changes = []            # (time, name, state or None when gone)
        self.pushes = 0
        self.bytes = 0
        self.drops = 0               # times the stream ended under us (the console drops a client that lags)
        self.closing = False
        self.conn = None
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        while not self.closing:
            try:
                self.conn = http.client.HTTPConnection(self.master.host, self.master.ext_port, timeout=600)
                self.conn.request("GET", "/console/api/events")
                resp = self.conn.getresponse()
                event = None
                while not self.closing:
                    line = resp.readline()
                    if not line:
                        break
                    self.bytes += len(line)
                    line = line.decode("utf-8").rstrip("\n")
                    if line.startswith("event: "):
                        event = line[7:]
                    elif line.startswith("data: ") and event in ("snapshot", "patch"):
                        self._take(json.loads(line[6:]))
            except (OSError, ValueError, http.client.HTTPException):
                pass
            if not self.closing:
                self.drops += 1
                time.sleep(0.2)   # reconnect pace, as the page's own retry

    def _take(self, payload):
        """A snapshot (its ``robots`` a whole list) or a patch (its ``robots`` the changed rows and the names
        gone, docs/CONSOLE.md)."""
        robots = payload.get("robots")
        now = time.time()
        with self.lock:
            self.pushes += 1
            if robots is None:
                return
            whole = isinstance(robots, list)
            rows = robots if whole else list(robots.get("changed", {}).values())
            seen = set()
            for row in rows:
                name = row["pi_name"]
                seen.add(name)
                state = (row.get("connected"), row.get("paired"), row.get("server"))
                if self.rows.get(name) != state:
                    self.rows[name] = state
                    self.changes.append((now, name, state))
            gone = [n for n in self.rows if n not in seen] if whole else robots.get("gone", [])
            for name in gone:
                if self.rows.pop(name, None) is not None:
                    self.changes.append((now, name, None))

    def first(self, name, predicate, after):
        """The time of the first change of ``name`` at or after ``after`` whose state satisfies ``predicate``."""
        with self.lock:
            for at, who, state in self.changes:
                if at >= after and who == name and predicate(state):
                    return at
        return None

    def wait(self, name, predicate, after, timeout):
        return wait_until(lambda: self.first(name, predicate, after), timeout=timeout, interval=0.005,
                          message=f"the console to push {name}'s change")

    def all_paired_at(self, names, after, exclude=None):
        """When the last of ``names`` was last pushed as paired (on a server other than ``exclude``, when given), or
        None while one is not."""
        names = set(names)
        with self.lock:
            for name in names:
                state = self.rows.get(name)
                if not state or not (state[0] and state[1]) or (exclude and state[2] in (None, exclude)):
                    return None
            last = {}
            for at, who, state in self.changes:
                if who in names and at >= after:
                    last[who] = at
        return max(last.values()) if len(last) == len(names) else None

    def close(self):
        self.closing = True
        try:
            if self.conn is not None and self.conn.sock is not None:
                self.conn.sock.shutdown(2)
        except OSError:
            pass
        self.thread.join(timeout=5)


# -- one fleet size --------------------------------------------------------------------------------------------

class Run:
    """One master, one fleet of ``n`` robots over ``s`` servers, and the figures measured on them."""

    def __init__(self, procs, tmp, n, args):
        self.procs = procs
        self.n = n
        self.args = args
        self.s = args.servers
        self.robots = [f"fleetbot{i}" for i in range(n)]
        self.servers = [f"fleetvm{i}" for i in range(self.s)]
        self.figures = {"n": n, "s": self.s}
        self.left = set()            # robots the benchmark made leave (their session ends are expected)
        keys = {"max_service_spaces": 0, "heartbeat_interval": args.heartbeat, "heartbeat_misses": 3,
                "log_max_bytes": 200 * 1024 * 1024}
        if n + self.s + 64 > master_port_cap():
            keys["ic_max_connections"] = n + self.s + 256
            self.figures["ic_max_connections"] = keys["ic_max_connections"]
        keys.update(args.master_key)
        prefix = os.path.join(args.profile or tmp, f"master-{n}")
        self.master = Master(procs, os.path.join(tmp, f"master-{n}"), prefix, profile=bool(args.profile),
                             env=args.master_env, **keys)
        self.fleet = None
        self.console = None

    # -- phases -------------------------------------------------------------------------------------------
    def setup(self):
        if self.args.master_nofile:   # the master inherits our soft limit: lower it for the start only
            soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
            resource.setrlimit(resource.RLIMIT_NOFILE, (min(self.args.master_nofile, hard), hard))
            try:
                self.master.start(timeout=60)
            finally:
                resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))
        else:
            self.master.start(timeout=60)
        self.pid = self.master.process.pid
        self.figures["nofile"] = open(f"/proc/{self.pid}/limits").read().split("Max open files")[1].split()[0]
        started = time.monotonic()
        rdapi = Http(self.master)
        try:
            rdapi.post("/service_logic/provisioning", {"slg_name": "fleet_logic", "sn_list": LOGIC})
            for name in self.robots:
                rdapi.post("/platform_instance/provisioning", {"pi_name": name, "pi_service_logic": "fleet_logic"})
        finally:
            rdapi.close()
        self.figures["provision_s"] = time.monotonic() - started
        self.console = ConsoleClock(self.master)
        self.fleet = Fleet(self.procs, self.master.host, self.master.ic_port, heartbeat=self.args.heartbeat,
                           workers=self.args.workers, server_start=self.args.server_start,
                           robot_start=self.args.robot_start)
        capacity = max(100, 2 * self.n // max(1, self.s - 1) + 10)    # room for a failover
        self.fleet.add_servers(self.servers, capacity)
        self.figures["capacity"] = capacity
        self.fleet.start(self.servers)
        wait_until(lambda: all(a["accepted"] for a in self.fleet.agents(self.servers).values()), timeout=60,
                   message="every simulated server to be accepted")
        self.fleet.add_robots(self.robots)
        self.fleet.stats(reset=True)

    def pair_all(self):
        """Start every robot at once; the time until all are paired, and what it cost."""
        cpu0, load0, overflows = proc_cpu(self.pid), load_average(), listen_overflows()
        read_times, read_failures = [], 0
        t0 = time.time()
        self._start_robots()
        deadline = time.monotonic() + self.args.timeout
        paired_at = None
        while time.monotonic() < deadline:
            time.sleep(0.5)   # the polling interval, not synchronisation
            try:
                elapsed, _, rows = read_rows(self.master)
                read_times.append(elapsed)
            except (OSError, RuntimeError, http.client.HTTPException):
                read_failures += 1
                continue
            if all(rows[n]["connected"] and rows[n]["paired"] for n in self.robots):
                paired_at = self.console.all_paired_at(self.robots, t0) or time.time()
                break
        f = self.figures
        f["pair_cpu"] = proc_cpu(self.pid) - cpu0
        f["listen_overflows"] = listen_overflows() - overflows
        f["pair_load"] = (load0, load_average())
        f["pair_reads"] = (percentile(read_times, 0.5) if read_times else None,
                           percentile(read_times, 0.99) if read_times else None, len(read_times), read_failures)
        agents = self.fleet.agents(self.robots)
        accepted = [a["accepted_at"] for a in agents.values() if a["accepted_at"]]
        items = [a["items_at"] for a in agents.values() if a["items_at"]]
        f["accepted_all"] = (max(accepted) - t0) if len(accepted) == self.n else None
        f["items_all"] = (max(items) - t0) if len(items) == self.n else None
        stats = self.fleet.stats(reset=True)
        f["hello"] = stats["samples"]["hello"]
        f["pair_heartbeat"] = stats["samples"]["heartbeat"]
        f["pair_lag"] = stats["samples"]["lag"]
        f["pair_counters"] = stats["counters"]
        f["pair_sim_cpu"] = stats["cpu"]
        if paired_at is None:
            done = sum(1 for a in agents.values() if a["items_at"])
            raise WaitTimeout(f"not all {self.n} robots paired within {self.args.timeout:.0f} s "
                              f"({len(accepted)} accepted, {done} with their items started)")
        f["pair_all"] = paired_at - t0
        f["rss_paired"] = proc_rss_mb(self.pid)

    def _start_robots(self):
        """All robots at once, or (``--ramp``) in even steps over that many seconds, as a fleet switched on over
        a while would arrive."""
        if not self.args.ramp:
            self.fleet.start(self.robots)
            return
        steps = max(1, int(self.args.ramp * 20))
        began = time.monotonic()
        for step in range(steps):
            chunk = self.robots[step * len(self.robots) // steps:(step + 1) * len(self.robots) // steps]
            if chunk:
                self.fleet.start(chunk)
            pause = began + (step + 1) * self.args.ramp / steps - time.monotonic()
            if pause > 0:
                time.sleep(pause)   # the ramp's pace, not synchronisation

    def steady(self):
        """All paired, nothing changing: the master's CPU and memory, heartbeat round trips."""
        time.sleep(self.args.settle)     # let the write queue and the console's last rebuilds finish
        self.fleet.stats(reset=True)
        cpu0, t0 = proc_cpu(self.pid), time.monotonic()
        time.sleep(self.args.steady)     # the measuring window
        cpu1, t1 = proc_cpu(self.pid), time.monotonic()
        stats = self.fleet.stats(reset=True)
        f = self.figures
        f["cpu"] = 100.0 * (cpu1 - cpu0) / (t1 - t0)
        f["rss"] = proc_rss_mb(self.pid)
        f["fds"] = proc_fds(self.pid)
        f["heartbeat"] = stats["samples"]["heartbeat"]
        f["lag"] = stats["samples"]["lag"]
        f["steady_load"] = load_average()

    def reads(self):
        times, sizes = [], []
        for _ in range(self.args.reads):
            elapsed, size, _ = read_rows(self.master)
            times.append(elapsed)
            sizes.append(size)
        self.figures["read"] = times
        self.figures["read_size"] = max(sizes)

    def console_changes(self):
        """Changes timed to the console's push: RDAPI writes, a robot leaving, its space paired again."""
        write, leave, pair = [], [], []
        rdapi = Http(self.master)
        try:
            for k in range(self.args.console_changes):
                name = f"latbot{k}"
                t = time.time()
                rdapi.post("/platform_instance/provisioning", {"pi_name": name, "pi_service_logic": "fleet_logic"})
                write.append(self.console.wait(name, lambda s: s is not None, t, 30) - t)
                t = time.time()
                rdapi.post("/platform_instance/r_provisioning", {"pi_name": name})
                write.append(self.console.wait(name, lambda s: s is None, t, 30) - t)
        finally:
            rdapi.close()
        step = max(1, self.n // max(1, self.args.console_changes))
        for robot in self.robots[::step][:self.args.console_changes]:
            self.left.add(robot)
            t = time.time()
            self.fleet.leave([robot])
            leave.append(self.console.wait(robot, lambda s: s is not None and not s[0], t, 30) - t)
            t = time.time()
            self.fleet.start([robot])
            at = self.console.wait(robot, lambda s: s is not None and s[0] and s[1], t, 60)
            items_at = self.fleet.agents([robot])[robot]["items_at"]
            pair.append(at - (items_at or t))
        self.figures["console"] = {"write": write, "leave": leave, "pair": pair}
        self.figures["console_pushes"] = (self.console.pushes, self.console.bytes, self.console.drops)

    def failover(self):
        """The server hosting the most spaces crashes: time until its robots are paired elsewhere."""
        agents = self.fleet.agents(self.servers)
        victim = max(self.servers, key=lambda s: len(agents[s]["spaces"]))
        moved = list(agents[victim]["spaces"])
        time.sleep(self.args.heartbeat)   # a quiet moment after the console's changes
        lost_before = self.fleet.stats()["counters"].get("sessions_lost", 0)
        cpu0 = proc_cpu(self.pid)
        t0 = time.time()
        self.fleet.crash([victim])
        at = wait_until(lambda: self.console.all_paired_at(moved, t0, exclude=victim), timeout=self.args.timeout,
                        interval=0.05, message=f"the {len(moved)} robots of {victim} to pair again elsewhere")
        _, _, rows = read_rows(self.master)
        wrong = [n for n in moved if not (rows[n]["paired"] and rows[n].get("server") not in (None, victim))]
        if wrong:
            raise RuntimeError(f"the console showed them paired but the RDAPI does not: {wrong[:5]}")
        f = self.figures
        f["failover"] = at - t0
        f["failover_spaces"] = len(moved)
        f["failover_cpu"] = proc_cpu(self.pid) - cpu0
        f["failover_lost"] = self.fleet.stats()["counters"].get("sessions_lost", 0) - lost_before

    def finish(self):
        """Sessions lost, then the master stopped under its fleet (timed) and the simulator closed."""
        stats = self.fleet.stats()
        f = self.figures
        f["sim_losses"] = [x for x in stats["losses"] if x[1] in set(self.robots)]
        text = self.master.log_text()
        f["master_hello"] = hello_buckets(self.master)
        ended = SESSION_ENDED.findall(text)
        f["master_ended"] = [(n, why) for n, why in ended if n not in self.left and not n.startswith("latbot")]
        f["counters"] = stats["counters"]
        f["sim_cpu"] = stats["cpu"]
        started = time.monotonic()
        f["stop_status"] = self.master.stop(timeout=300)
        f["stop_s"] = time.monotonic() - started

    def close(self):
        if self.console is not None:
            self.console.close()
        if self.fleet is not None:
            self.fleet.close()


def run_size(n, args):
    """Every phase for ``n`` robots; the figures (``error`` says what could not be measured)."""
    with tempfile.TemporaryDirectory(prefix=f"bench-fleet-{n}-") as tmp:
        procs = ProcessGroup(log_dir=tmp)
        run = Run(procs, tmp, n, args)
        try:
            phases = [run.setup, run.pair_all, run.steady, run.reads, run.console_changes, run.failover,
                      run.finish]
            for phase in phases:
                print(f"[fleet {n} {time.strftime('%H:%M:%S')}] {phase.__name__} (load {load_average()})", flush=True)
                if phase in (run.setup, run.finish):
                    phase()
                    continue
                cpu, main_cpu = proc_cpu(run.pid), main_thread_cpu(run.pid)
                probes = run.figures.setdefault("probe", {})
                try:
                    with run.master.phase(phase.__name__, probes):
                        phase()
                finally:
                    for stack, count in (probes.get(phase.__name__) or {}).get("stalls", [])[:3]:
                        print(f"[fleet {n}] {phase.__name__}: the master's loop stalled here in {count} "
                              f"samples:\n{stack}", flush=True)
                run.figures.setdefault("threads", {})[phase.__name__] = (
                    proc_cpu(run.pid) - cpu, main_thread_cpu(run.pid) - main_cpu)
        except Exception as exc:   # a phase that cannot finish: say so in the report, measure the next N
            run.figures["error"] = f"{phase.__name__}: {type(exc).__name__}: {exc}"
            print(f"[fleet {n}] {run.figures['error']}", flush=True)
            if args.keep_failed:
                import shutil
                shutil.copytree(tmp, os.path.join(args.keep_failed, f"fleet-{n}"), dirs_exist_ok=True,
                                ignore=shutil.ignore_patterns("*.db-journal"))
        finally:
            try:
                run.close()
            finally:
                procs.stop_all()
        return run.figures


# -- the report ------------------------------------------------------------------------------------------------

def _ms(value):
    return "–" if value is None else f"{value * 1000:.0f} ms"


def _s(value):
    return "–" if value is None else f"{value:.1f} s"


def _p(values, fraction):
    return percentile(values, fraction) if values else None


def summary(f):
    """The headline figures of one run (seconds, %, MB), None where not measured."""
    console = f.get("console") or {}
    every = console.get("write", []) + console.get("leave", []) + console.get("pair", [])
    lost = None
    if "sim_losses" in f:
        lost = len(f["sim_losses"]) + len(f["master_ended"])
    return {"pair_all": f.get("pair_all"), "hello_p50": _p(f.get("hello"), 0.5), "hello_p99": _p(f.get("hello"), 0.99),
            "heartbeat_p99": _p(f.get("heartbeat"), 0.99), "cpu": f.get("cpu"), "rss": f.get("rss"),
            "read_p99": _p(f.get("read"), 0.99), "read_size": f.get("read_size"),
            "console_p99": _p(every, 0.99), "failover": f.get("failover"), "lost": lost}


def verdict(key, value):
    if value is None:
        return "not measured"
    limit, _ = TARGETS[key]
    ok = value <= limit if key in ("pair_all", "failover", "lost") else value < limit
    return "met" if ok else "**NOT met**"


def report(results, args):
    arrival = (f"the robots are started evenly over {args.ramp:g} s (times to pair count from the first)"
               if args.ramp else "all robots are started at once")
    lines = ([args.note, ""] if args.note else []) + [
        f"`bench/bench_fleet.py`: one master agent (`python3 -m rcm_platform`, `max_service_spaces 0`, real SQLite, "
        f"RDAPI and console, heartbeats every {args.heartbeat:g} s, 3 misses) on loopback; the fleet simulated by "
        f"`bench/fleet_sim.py` ({args.workers} process{'es' if args.workers > 1 else ''}): N robots and "
        f"{args.servers} server VMs, each on its own loopback address, speaking the agent protocol; no ROS process "
        f"runs. A server VM answers `start_items` after {args.server_start:g} s (its ROS master and S node), a "
        f"robot after {args.robot_start:g} s (its R node). Every robot: one S-side and one R-side node; {arrival}. A "
        f"console event stream is open throughout. The master and the simulator share this machine's "
        f"{os.cpu_count()} cores (and other work: load averages below).",
        "",
        "| figure | " + " | ".join(f"N = {r['n']:,}" for r in results) + " | target (N = 2,000) |",
        "| --- | " + " | ".join("---:" for _ in results) + " | --- |",
    ]
    sums = [summary(r) for r in results]

    def row(label, key, fmt, target=None):
        cells = [fmt(s[key]) if s[key] is not None else "–" for s in sums]
        big = next((s for r, s in zip(results, sums) if r["n"] == TARGET_N), None)
        tail = ""
        if target:
            tail = f"{target}: {verdict(key, big[key]) if big else 'not measured'}"
        lines.append(f"| {label} | " + " | ".join(cells) + f" | {tail} |")

    row("robots started → all paired", "pair_all", lambda v: f"**{v:.1f} s**", "≤ 60 s")
    row("hello answer p50", "hello_p50", lambda v: f"{v * 1000:.0f} ms")
    row("hello answer p99", "hello_p99", lambda v: f"**{v * 1000:.0f} ms**", "< 200 ms")
    row("heartbeat round trip p99 (steady)", "heartbeat_p99", lambda v: f"**{v * 1000:.0f} ms**", "< 100 ms")
    row("master CPU, steady (% of one core)", "cpu", lambda v: f"**{v:.1f} %**", "< 25 %")
    row("master RSS, steady", "rss", lambda v: f"**{v:.0f} MB**", "< 400 MB")
    row("`platform_instance/read` p99", "read_p99", lambda v: f"**{v * 1000:.0f} ms**", "< 100 ms")
    row("`platform_instance/read` size", "read_size", lambda v: f"{v / 1024:.0f} KiB")
    row("console change → push p99", "console_p99", lambda v: f"**{v * 1000:.0f} ms**", "< 1 s")
    row("failover: server crash → its robots paired elsewhere", "failover", lambda v: f"**{v:.1f} s**", "< 15 s")
    row("sessions lost that nobody ended", "lost", lambda v: f"**{v}**", "0")

    lines += ["", "Details:", "", "| detail | " + " | ".join(f"N = {r['n']:,}" for r in results) + " |",
              "| --- | " + " | ".join("---:" for _ in results) + " |"]

    def detail(label, fn):
        cells = []
        for r in results:
            try:
                cells.append(fn(r))
            except (KeyError, TypeError, ValueError, IndexError):
                cells.append("–")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")

    detail("all accepted (last hello answered)", lambda r: _s(r["accepted_all"]))
    detail("hello answer inside the master (reading it → answering), p50 / p99",
           lambda r: (f"≤ {_ms(bucket_p(r['master_hello'], 0.5))} / ≤ {_ms(bucket_p(r['master_hello'], 0.99))}"
                      if r["master_hello"] and isinstance(r["master_hello"][0], (list, tuple)) else
                      f"{_ms(_p(r['master_hello'], 0.5))} / {_ms(_p(r['master_hello'], 0.99))}"))
    detail("connections the accept queue dropped while pairing (machine-wide)", lambda r: f"{r['listen_overflows']}")
    detail("connection attempts by the simulated robots / hellos refused",
           lambda r: f"{r['pair_counters'].get('connects', 0)} / "
                     f"{sum(v for k, v in r['pair_counters'].items() if k.startswith('refused_'))}")
    detail("all robots' R items started (simulator's view)", lambda r: _s(r["items_all"]))
    detail("master CPU-s while pairing: all threads / main thread (the reactor)",
           lambda r: f"{r['threads']['pair_all'][0]:.1f} / {r['threads']['pair_all'][1]:.1f}")
    detail("master CPU-s, settle and steady window: all threads / main thread",
           lambda r: f"{r['threads']['steady'][0]:.1f} / {r['threads']['steady'][1]:.1f}")
    detail("master RSS when all paired", lambda r: f"{r['rss_paired']:.0f} MB")
    detail("heartbeat round trip p50 / p99 while pairing",
           lambda r: f"{_ms(_p(r['pair_heartbeat'], 0.5))} / {_ms(_p(r['pair_heartbeat'], 0.99))}")
    detail("heartbeat round trip p50 (steady)", lambda r: _ms(_p(r["heartbeat"], 0.5)))
    detail("`platform_instance/read` p50 (steady) / p50, p99 while pairing",
           lambda r: f"{_ms(_p(r['read'], 0.5))} / {_ms(r['pair_reads'][0])}, {_ms(r['pair_reads'][1])}")
    detail("console: RDAPI write → push p50 / p99",
           lambda r: f"{_ms(_p(r['console']['write'], 0.5))} / {_ms(_p(r['console']['write'], 0.99))}")
    detail("console: robot leaves → push p50 / p99",
           lambda r: f"{_ms(_p(r['console']['leave'], 0.5))} / {_ms(_p(r['console']['leave'], 0.99))}")
    detail("console: robot's items up → push paired p50 / p99",
           lambda r: f"{_ms(_p(r['console']['pair'], 0.5))} / {_ms(_p(r['console']['pair'], 0.99))}")
    detail("console pushes / MB received / streams dropped",
           lambda r: f"{r['console_pushes'][0]} / {r['console_pushes'][1] / 1e6:.0f} / {r['console_pushes'][2]}")
    detail("failover: spaces moved / master CPU-s", lambda r: f"{r['failover_spaces']} / {r['failover_cpu']:.1f}")
    detail("master stop (SIGTERM → exit) under the fleet", lambda r: _s(r["stop_s"]))
    detail("master open files, steady (its limit)", lambda r: f"{r['fds']} ({r['nofile']})")
    detail("master event-loop lateness p99 / longest, pairing",
           lambda r: f"{_ms(_p(r['probe']['pair_all']['lag'], 0.99))} / {_ms(max(r['probe']['pair_all']['lag']))}")
    detail("master event-loop lateness p99 / longest, steady",
           lambda r: f"{_ms(_p(r['probe']['steady']['lag'], 0.99))} / {_ms(max(r['probe']['steady']['lag']))}")
    detail("master event-loop lateness p99 / longest, failover",
           lambda r: f"{_ms(_p(r['probe']['failover']['lag'], 0.99))} / {_ms(max(r['probe']['failover']['lag']))}")
    detail("master full garbage collections while pairing: count / total / longest",
           lambda r: f"{len(r['probe']['pair_all']['gc'])} / {_s(sum(r['probe']['pair_all']['gc']))} / "
                     f"{_ms(max(r['probe']['pair_all']['gc'] or [0]))}")
    detail("master full garbage collections, steady: count / longest",
           lambda r: f"{len(r['probe']['steady']['gc'])} / {_ms(max(r['probe']['steady']['gc'] or [0]))}")
    detail("objects the master's garbage collector tracks, steady",
           lambda r: f"{r['probe']['steady']['objects']:,}")
    detail("simulator event-loop lateness p99, pairing / steady",
           lambda r: f"{_ms(_p(r['pair_lag'], 0.99))} / {_ms(_p(r['lag'], 0.99))}")
    detail("simulator CPU-s (per worker)", lambda r: ", ".join(f"{c:.0f}" for c in r["sim_cpu"]))
    detail("load average (1 / 5 min): start of pairing / steady",
           lambda r: f"{r['pair_load'][0]} / {r['steady_load']}")

    lines += ["", "Growth: each figure divided by N (a column growing from left to right grows faster than N).",
              "", "| figure ÷ N | " + " | ".join(f"N = {r['n']:,}" for r in results) + " |",
              "| --- | " + " | ".join("---:" for _ in results) + " |"]

    def growth(label, key, scale, unit):
        cells = []
        for r, s in zip(results, sums):
            value = s[key]
            cells.append("–" if value is None else f"{value * scale / r['n']:.3g} {unit}")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")

    growth("all paired", "pair_all", 1000, "ms")
    growth("hello p99", "hello_p99", 1e6, "µs")
    growth("heartbeat p99", "heartbeat_p99", 1e6, "µs")
    growth("master CPU, steady", "cpu", 1000, "m%")
    growth("master RSS", "rss", 1024, "KiB")
    growth("read p99", "read_p99", 1e6, "µs")
    growth("read size", "read_size", 1, "B")
    growth("console p99", "console_p99", 1e6, "µs")
    growth("failover", "failover", 1000, "ms")

    for r in results:
        notes = []
        if r.get("error"):
            notes.append(f"not finished: {r['error']}")
        if r.get("ic_max_connections"):
            notes.append(f"`ic_max_connections {r['ic_max_connections']}` was set: the agent port's default cap "
                         f"(a quarter of the open-file limit the master raises itself to) is below N")
        losses = (r.get("sim_losses") or [])[:5]
        if losses:
            notes.append("sessions lost (simulator): " + "; ".join(f"{n}: {why}" for _, n, why in losses))
        if r.get("master_ended"):
            notes.append("sessions the master ended: " + "; ".join(f"{n}: {why}" for n, why in r["master_ended"][:5]))
        if notes:
            lines += ["", f"N = {r['n']:,}: " + " ".join(notes)]
    return "\n".join(lines)


def _pair(text):
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, not {text!r}")
    return key, value


def main(argv=None):
    parser = argparse.ArgumentParser(prog="bench_fleet", description=__doc__.split("\n\n")[0])
    parser.add_argument("--robots", default="500,1000,2000", help="fleet sizes, comma separated (default 500,1000,2000)")
    parser.add_argument("--servers", type=int, default=20, help="simulated server VMs (default 20)")
    parser.add_argument("--heartbeat", type=float, default=2.0, help="heartbeat_interval of every agent (default 2)")
    parser.add_argument("--workers", type=int, default=2, help="simulator processes (default 2: one per core)")
    parser.add_argument("--server-start", type=float, default=0.3,
                        help="seconds a simulated server takes to answer start_items (default 0.3)")
    parser.add_argument("--robot-start", type=float, default=0.2,
                        help="seconds a simulated robot takes to answer start_items (default 0.2)")
    parser.add_argument("--ramp", type=float, default=0.0, metavar="SECONDS",
                        help="start the robots evenly over this many seconds instead of all at once (default 0)")
    parser.add_argument("--note", default="", help="a sentence put first in the report (what code was measured)")
    parser.add_argument("--timeout", type=float, default=900.0, help="seconds to wait for a fleet to pair")
    parser.add_argument("--settle", type=float, default=10.0, help="seconds between all paired and the steady window")
    parser.add_argument("--steady", type=float, default=30.0, help="seconds of the steady-state window (default 30)")
    parser.add_argument("--reads", type=int, default=100, help="platform_instance/read calls timed (default 100)")
    parser.add_argument("--console-changes", type=int, default=10, help="changes of each kind timed on the console")
    parser.add_argument("--master-key", metavar="KEY=VALUE", action="append", default=[], type=_pair,
                        help="a key of the master's .init.cfg (repeatable), e.g. max_starting_spaces=80")
    parser.add_argument("--master-env", metavar="NAME=VALUE", action="append", default=[], type=_pair,
                        help="an environment variable of the master (repeatable)")
    parser.add_argument("--master-nofile", type=int, metavar="N",
                        help="the master's soft open-file limit (default: this process's, raised to its hard limit, "
                             "as rcmpd raises it); e.g. 1024, a shell's usual limit")
    parser.add_argument("--profile", metavar="DIR", help="profile the master with cProfile: one file per N and phase in DIR")
    parser.add_argument("--keep-failed", metavar="DIR", help="copy a failed run's folder (logs, data) into DIR")
    parser.add_argument("--quick", action="store_true", help="N = 100 and 200 only, short windows (a smoke run)")
    parser.add_argument("--no-write", action="store_true", help="print, do not write docs/PERFORMANCE.md")
    args = parser.parse_args(argv)
    args.master_key, args.master_env = dict(args.master_key), dict(args.master_env)
    if args.quick:
        args.robots, args.steady, args.settle, args.reads, args.console_changes = "100,200", 6.0, 3.0, 20, 3
        args.no_write = True
    sizes = [int(x) for x in args.robots.split(",") if x.strip()]
    for folder in (args.profile, args.keep_failed):
        if folder:
            os.makedirs(folder, exist_ok=True)
    nofile = raise_nofile()
    print(f"open-file limit {nofile}; load {load_average()}", flush=True)
    results = [run_size(n, args) for n in sizes]
    body = report(results, args)
    print(body)
    if not args.no_write:
        if args.server_start or args.robot_start:
            write_section("fleet", f"Fleet scale: one master, up to {max(sizes):,} simulated robots on "
                                   f"{args.servers} server VMs", body)
        else:   # the control plane alone: a second section, so that both can stand side by side
            write_section("fleet_zero_start", f"Fleet scale, the control plane alone: simulated items start at once "
                                              f"(up to {max(sizes):,} robots on {args.servers} server VMs)", body)
    big = next((r for r in results if r["n"] == TARGET_N), None)
    if big is None:
        return 0 if all("error" not in r for r in results) else 1
    s = summary(big)
    return 0 if all(verdict(k, s[k]) == "met" for k in TARGETS) and "error" not in big else 1


if __name__ == "__main__":
    sys.exit(main())
