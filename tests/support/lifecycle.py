"""A small real platform on loopback for the robot-lifecycle tests and benchmark (owned by the agents engineer).

``Platform(procs, root)`` prepares a master (``RcmpAgent`` on 127.0.0.1, free RDAPI/agent ports, a free
``ros_port_base``, short heartbeats) and makes robot agents on 127.0.0.2, .3, ... that point at it. It wraps
the RDAPI calls the tests need, and ``leftovers()`` lists every live process that belongs to this platform:
any process whose command line or environment mentions the platform's folder (agents get ``--home`` there;
everything an agent starts gets ``ROS_LOG_DIR`` under its home). ``kill_leftovers()`` is the safety net a
test's finalizer uses, so a failing test never leaves processes behind.
"""

import os
import signal

import rosgraph

from .polling import wait_until
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
