"""A small real platform on loopback for the robot-lifecycle tests and benchmark (owned by the agents engineer).

``Platform(procs, root)`` prepares a master (``RcmpAgent`` on 127.0.0.1, free RDAPI/agent ports, a free
``ros_port_base``, short heartbeats) and makes robot agents on 127.0.0.2, .3, ... that point at it. It wraps
the RDAPI calls the tests need, and ``leftovers()`` lists every live process that belongs to this platform:
any process whose command line or environment mentions the platform's folder (agents get ``--home`` there;
everything an agent starts gets ``ROS_LOG_DIR`` under its home). ``kill_leftovers()`` is the safety net a
test's finalizer uses, so a failing test never leaves processes behind.
"""

import os
import re
import signal
import time

import rosgraph

from .polling import WaitTimeout, wait_until
from .ports import ros_port_base, stable_free_ports
from .rcmp_agent import RcmpAgent

HEARTBEAT = 0.5


def _read(path):
    try:
        with open(path, "rb") as f:
            return f.read()
    except OSError:
        return b""


def processes_mentioning(text):
    """[(pid, command line)] of live (non-zombie) processes whose argv or environment contains ``text``."""
    needle = text.encode()
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit() or int(entry) == os.getpid():
            continue
        stat = _read(f"/proc/{entry}/stat")
        try:
            state = stat.rsplit(b")", 1)[1].split()[0]
        except IndexError:
            continue
        if state in (b"Z", b"X"):
            continue
        cmdline = _read(f"/proc/{entry}/cmdline")
        if needle in cmdline or needle in _read(f"/proc/{entry}/environ"):
            found.append((int(entry), cmdline.replace(b"\0", b" ").decode("utf-8", "replace").strip()))
    return found


MASTER_HELLO = re.compile(r"robot (\w+) connected from \S+ \(hello answered in ([0-9.]+) s\)")
ROBOT_HELLO = re.compile(r"connected to master \S+ as (\w+) .*hello answered in ([0-9.]+) s")
SESSION_ENDED = re.compile(r"ending robot (\w+)'s session: (.*)")


class SessionLog:
    """What the agents' logs say about sessions (from each log's text after a given offset).

    ``opened``: sessions per robot name, from each robot's own "connected to master" lines (the master logs the
    first hellos of each 10 s only: a herd's are counted, not written); ``ended``: [(name, reason)] sessions the
    master ended; ``master_hello`` / ``robot_hello``: seconds accepted hellos took, as the master measured them
    (from reading the hello to answering: those it logged) and as the robots did (from sending it to reading the
    answer: every one); ``robot_lost``: robots' "lost the master" lines."""

    def __init__(self, master_text, robot_texts):
        self.opened = {}
        self.ended = []
        self.master_hello = [float(match.group(2)) for match in MASTER_HELLO.finditer(master_text)]
        for match in SESSION_ENDED.finditer(master_text):
            self.ended.append((match.group(1), match.group(2).strip()))
        self.robot_hello = []
        self.robot_lost = []
        for text in robot_texts:
            for match in ROBOT_HELLO.finditer(text):
                self.opened[match.group(1)] = self.opened.get(match.group(1), 0) + 1
                self.robot_hello.append(float(match.group(2)))
            self.robot_lost += [line for line in text.splitlines() if "lost the master" in line]

    def reopened(self):
        """Names whose session was opened more than once."""
        return sorted(name for name, count in self.opened.items() if count > 1)


class Platform:
    """A master and its robots, all under ``root``."""

    def __init__(self, procs, root, heartbeat=HEARTBEAT, inbound_ports=1, **master_keys):
        self.procs = procs
        self.root = str(root)
        self.heartbeat = heartbeat
        self.inbound_ports = stable_free_ports(inbound_ports) if inbound_ports else []
        keys = {"heartbeat_interval": heartbeat, "heartbeat_misses": 3, "ros_port_base": ros_port_base(),
                "inbound_open_ports": ", ".join(str(p) for p in self.inbound_ports) or None}
        keys.update(master_keys)
        home = os.path.join(self.root, "master")
        self.master = RcmpAgent(procs, home, role="master", env=self._env(home), **keys)
        self.robots = {}

    @staticmethod
    def _env(home):
        return {"ROS_LOG_DIR": os.path.join(home, "roslog")}

    def robot(self, name, address, role="robot", **keys):
        """A robot (or, role "server", server VM) agent, not started, named ``name`` at ``address``."""
        home = os.path.join(self.root, name)
        settings = {"name": name, "vpn_address": address, "ip_master": "127.0.0.1",
                    "ic_port": self.master.ic_port, "heartbeat_interval": self.heartbeat, "heartbeat_misses": 3}
        settings.update(keys)
        agent = RcmpAgent(self.procs, home, role=role, env=self._env(home), **settings)
        self.robots[name] = agent
        return agent

    # -- RDAPI ------------------------------------------------------------------------------------------
    def provision_logic(self, slg_name, sn_list=(), sl_list=(), **extra):
        body = {"slg_name": slg_name, "sn_list": list(sn_list), "sl_list": list(sl_list)}
        body.update(extra)
        status, answer = self.master.post("/service_logic/provisioning", body)
        assert status == 200 and answer["result"] == "OK", (status, answer)

    def provision_robot(self, pi_name, slg_name):
        status, answer = self.master.post("/platform_instance/provisioning",
                                          {"pi_name": pi_name, "pi_service_logic": slg_name})
        assert status == 200 and answer["result"] == "OK", (status, answer)

    def remove_robot(self, pi_name):
        return self.master.post("/platform_instance/r_provisioning", {"pi_name": pi_name})

    def instances(self):
        status, answer = self.master.get("/platform_instance/read")
        assert status == 200, (status, answer)
        return {row["pi_name"]: row for row in answer["reason"]}

    def state(self, pi_name):
        """(connected, paired) of ``pi_name``, or None when it is not provisioned."""
        row = self.instances().get(pi_name)
        return None if row is None else (row["connected"], row["paired"])

    def space(self, ss_name):
        """``service_space/read`` of ``ss_name``: (status, reason)."""
        status, answer = self.master.get(f"/service_space/read?ss_name={ss_name}")
        return status, answer.get("reason") if isinstance(answer, dict) else answer

    def wait_state(self, pi_name, connected, paired, timeout=30.0):
        wait_until(lambda: self.state(pi_name) == (connected, paired), timeout=timeout,
                   message=f"{pi_name} to be connected={connected} paired={paired} "
                           f"(now {self._safe_state(pi_name)})")

    def _safe_state(self, pi_name):
        try:
            return self.state(pi_name)
        except Exception as exc:
            return repr(exc)

    def ros_master(self, ss_name):
        status, space = self.space(ss_name)
        assert status == 200, (status, space)
        return rosgraph.Master("/lifecycle_test", master_uri=space["ros_master_uri"])

    # -- a herd: many robots at once (issue 10) ----------------------------------------------------------
    @staticmethod
    def herd_address(index):
        """The loopback address of the ``index``-th robot of a herd (0-based): 127.0.0.2 ... 127.0.0.254, then
        127.0.1.2 ..."""
        return f"127.0.{index // 253}.{index % 253 + 2}"

    def start_herd(self, names, **keys):
        """Start a robot agent for every name at once (without waiting for any); ``{name: start time}``."""
        started = {}
        for index, name in enumerate(names):
            agent = self.robots.get(name) or self.robot(name, self.herd_address(index), **keys)
            started[name] = time.monotonic()
            agent.start(wait=False)
        return started

    def stop_robots(self, names):
        """SIGTERM every robot of ``names`` first, then wait for each (a herd stops together, not one by one)."""
        agents = [self.robots[n] for n in names if self.robots[n].process is not None]
        for agent in agents:
            if agent.process.poll() is None:
                agent.process.send_signal(signal.SIGTERM)
        for agent in agents:
            agent.stop()

    def paired_now(self, names):
        """The names of ``names`` that platform_instance/read shows connected and paired."""
        rows = self.instances()
        return {n for n in names if n in rows and rows[n]["connected"] and rows[n]["paired"]}

    def wait_all_paired(self, names, timeout, started=None, interval=0.1):
        """Wait until every robot of ``names`` is paired; ``{name: seconds from its start to paired}`` (from the
        first read that showed it). WaitTimeout names how many and which are missing."""
        started = started or {}
        paired_at = {}
        self.read_failures = []          # RDAPI reads that failed meanwhile (a saturated master), kept for reports
        deadline = time.monotonic() + timeout
        while True:
            try:
                paired = self.paired_now(names)
            except OSError as exc:       # timed out or refused: the master is busy, not the test's problem yet
                self.read_failures.append(repr(exc))
                paired = set()
            now = time.monotonic()
            for name in paired - set(paired_at):
                paired_at[name] = now - started.get(name, now)
            missing = sorted(set(names) - set(paired_at))
            if not missing:
                return paired_at
            if now >= deadline:
                raise WaitTimeout(f"{len(missing)} of {len(names)} robots not paired within {timeout:.0f} s: "
                                  f"{', '.join(missing[:10])}{' ...' if len(missing) > 10 else ''}")
            time.sleep(interval)  # the polling interval, not synchronisation

    def log_marks(self):
        """Where each agent's log ends now; give it to ``session_log`` to read only what comes after."""
        marks = {"master": len(self.master.log_text())}
        marks.update({name: len(agent.log_text()) for name, agent in self.robots.items()})
        return marks

    def session_log(self, names, marks=None):
        """A SessionLog of the master's log and the logs of robots ``names`` since ``marks``."""
        marks = marks or {}
        return SessionLog(self.master.log_text()[marks.get("master", 0):],
                          [self.robots[n].log_text()[marks.get(n, 0):] for n in names])

    # -- processes --------------------------------------------------------------------------------------
    def leftovers(self):
        return processes_mentioning(self.root)

    def stop_all_and_check_nothing_left(self):
        """End of a test: stop every child of the test (agents first stop what they started), then kill and
        report anything of the platform still running, so one test's leak never reaches the next."""
        try:
            self.procs.stop_all()
        finally:
            leftovers = self.leftovers()
            self.kill_leftovers()
        assert not leftovers, f"processes left behind: {leftovers}"

    def kill_leftovers(self):
        for pid, _ in self.leftovers():
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass

    def wait_no_leftovers(self, timeout=15.0):
        wait_until(lambda: not self.leftovers(), timeout=timeout,
                   message=f"every process of the platform to be gone (left: {self.leftovers()})")
