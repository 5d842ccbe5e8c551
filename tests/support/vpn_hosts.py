"""A platform spread over test hosts and joined by its own VPN (issue 9): master, robots and an office machine.

``VpnPlatform(lan, root)`` adds to a ``tests.support.hosts.Lan`` a ``master`` host and an ``office`` host (the
administrator's machine on the same LAN: it runs curl against the master's RDAPI on ``eth0``, as a person would),
creates the master's platform folder with the agent's *default* configuration (``tun0``, ``eth0``, ports 80 and
9999, no address keys; only short heartbeats) and runs ``rcmp_n vpn init --subnet 198.51.100.0/24`` in the master
host, so the client files name the master's ``eth0`` address. ``add_robot(name)`` adds a host, issues
``rcmp_n vpn client NAME -o HOME/vpn/client.conf`` on the master and writes the robot's ``init.cfg`` (name and
heartbeats only); ``add_server(name)`` the same for a server VM (``robot=no``) with a server certificate
(``--server``), or with the certificate of another role to play an attacker. ``HELLO`` is a hello over the agent
protocol as a one-file script, for a host to send as anyone it likes. Agents are started with ``python3 -m rcm_platform --home HOME`` inside their hosts, as children
of the LAN's ``ProcessGroup``; each agent starts its own OpenVPN (the managed VPN). ``rdapi(method, path, body)``
calls the master from the office host.

Everything is removed by the LAN's teardown (processes stopped, namespaces deleted) and the platform folders live
under ``root`` (a test's temporary folder).
"""

import contextlib
import json
import os
import signal
import subprocess

from .hosts import VPN_SUBNET, Lan
from .polling import wait_until
from .rcmp_agent import AgentLog
from .processes import ros_env

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
PYTHON = "/usr/bin/python3"
HEARTBEAT = 0.5
MISSES = 3
# a hello over the agent protocol (docs/PROTOCOL.md), from whichever host runs it; prints the answer frame.
# argv: name, address, master, port, and "robot" or "server" (default robot)
HELLO = r"""
import json, socket, struct, sys
name, address, master, port = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
robot = (sys.argv[5] if len(sys.argv) > 5 else "robot") == "robot"
s = socket.create_connection((master, port), timeout=10)
body = {"name": name, "address": address, "robot": robot, "version": 1}
frame = json.dumps({"v": 1, "id": 1, "kind": "req", "op": "hello", "body": body}).encode()
s.sendall(struct.pack(">I", len(frame)) + frame)
def read(n):
    data = b""
    while len(data) < n:
        chunk = s.recv(n - len(data))
        if not chunk:
            raise SystemExit("connection closed")
        data += chunk
    return data
size = struct.unpack(">I", read(4))[0]
print(read(size).decode())
"""


@contextlib.contextmanager
def vpn_platform(tmp_path_factory, name, **keys):
    """A ``VpnPlatform`` (``keys`` for its constructor) on a LAN of its own, under a temporary folder named after
    ``name``; the test is skipped without root. Everything is removed when the block ends."""
    import pytest
    if os.geteuid() != 0:
        pytest.skip("test hosts need root (network namespaces)")
    root = tmp_path_factory.mktemp(name)
    with Lan() as lan:
        yield VpnPlatform(lan, root, **keys)


class Agent(AgentLog):
    """One agent in its host: ``start()``, ``stop()`` (SIGTERM, checked gone), its log."""

    def __init__(self, platform, host, home, role):
        self.platform = platform
        self.host = host
        self.home = home
        self.role = role
        self.process = None

    def start(self):
        env = ros_env({"ROS_LOG_DIR": os.path.join(self.home, "roslog")})
        env["PYTHONPATH"] = REPO + (":" + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        self.process = self.host.start([PYTHON, "-m", "rcm_platform", "--home", self.home], env=env, cwd=REPO,
                                       name=f"rcmp-{self.host.name}")
        return self

    def output(self):
        return self.platform.lan.procs.output(self.process) if self.process else ""

    def stop(self):
        """SIGTERM as the init script does; waits for exit 0 and checks its process group is gone."""
        self.process.send_signal(signal.SIGTERM)
        wait_until(lambda: self.process.poll() is not None, timeout=30.0,
                   message=f"the agent of {self.host.name} to exit on SIGTERM")
        status = self.process.returncode
        procs = self.platform.lan.procs
        procs.stop(self.process)
        procs.children.remove(self.process)
        self.process = None
        return status

    def vpn_address(self):
        result = self.host.run(["ip", "-4", "-o", "addr", "show", "dev", "tun0"], check=False)
        parts = result.stdout.split()
        if result.returncode != 0 or "inet" not in parts:
            return None
        return parts[parts.index("inet") + 1].split("/")[0]


class VpnPlatform:
    """A master, its robots and an office machine as hosts of ``lan``, over the platform's own VPN."""

    def __init__(self, lan, root, heartbeat=HEARTBEAT, master_keys=None):
        """``heartbeat``: seconds between heartbeats written into every agent's configuration (None: defaults)."""
        self.lan = lan
        self.root = str(root)
        self.heartbeat = heartbeat
        self.master_host = lan.add_host("master")
        self.office = lan.add_host("office")
        home = os.path.join(self.root, "master")
        os.makedirs(home)
        keys = {"heartbeat_interval": heartbeat, "heartbeat_misses": MISSES} if heartbeat else {}
        keys.update(master_keys or {})
        self._write_cfg(os.path.join(home, ".init.cfg"), keys)
        self.master = Agent(self, self.master_host, home, "master")
        result = self.vpn("init", "--subnet", VPN_SUBNET)
        assert result.returncode == 0, result.stdout
        self.robots = {}

    @staticmethod
    def _write_cfg(path, keys):
        with open(path, "w", encoding="utf-8") as f:
            f.write("[main]\n" + "".join(f"{k}={v}\n" for k, v in keys.items()))

    @property
    def master_address(self):
        """The master's eth0 address (its RDAPI)."""
        return self.master_host.address

    def vpn(self, *args):
        """``rcmp_n vpn ARGS`` on the master host; the CompletedProcess (stdout and stderr merged)."""
        return self.master_host.run([PYTHON, "-m", "rcm_platform", "--home", self.master.home, "vpn", *args],
                                    check=False, cwd=REPO)

    def add_robot(self, name, **keys):
        return self._add_agent(name, "robot", "robot", keys)

    def add_server(self, name, certificate="server", **keys):
        """A server VM (``robot=no``) whose client file holds a ``certificate`` of that role (``server``, as
        'rcmp_n vpn client NAME --server' issues it, or ``robot``: a robot's client file on a server VM)."""
        return self._add_agent(name, "server", certificate, keys)

    def _add_agent(self, name, role, certificate, keys):
        host = self.lan.add_host(name)
        home = os.path.join(self.root, name)
        os.makedirs(os.path.join(home, "vpn"), mode=0o700)
        issue = ["--server"] if certificate == "server" else []
        result = self.vpn("client", name, *issue, "-o", os.path.join(home, "vpn", "client.conf"))
        assert result.returncode == 0, result.stdout
        settings = {"name": name, "robot": "yes" if role == "robot" else "no"}
        if self.heartbeat:
            settings.update(heartbeat_interval=self.heartbeat, heartbeat_misses=MISSES)
        settings.update(keys)
        self._write_cfg(os.path.join(home, "init.cfg"), settings)
        agent = Agent(self, host, home, role)
        self.robots[name] = agent
        return agent

    # -- the RDAPI, from the office ---------------------------------------------------------------------
    def rdapi(self, method, path, body=None, timeout=10):
        """(status, decoded JSON or text) of one RDAPI call made with curl from the office host."""
        argv = ["curl", "-s", "-S", "--max-time", str(timeout), "-o", "-", "-w", "\n%{http_code}", "-X", method]
        if body is not None:
            argv += ["-H", "Content-Type: application/json", "--data-binary", json.dumps(body)]
        argv.append(f"http://{self.master_address}{path}")
        result = self.office.run(argv, check=False, stderr=subprocess.DEVNULL, timeout=timeout + 5)
        text, _, status = result.stdout.rpartition("\n")
        if result.returncode != 0 or not status.isdigit():
            return None, text
        try:
            return int(status), json.loads(text)
        except ValueError:
            return int(status), text

    def rdapi_ok(self, method, path, body=None):
        status, answer = self.rdapi(method, path, body)
        assert status == 200 and answer["result"] == "OK", (method, path, status, answer)
        return answer["reason"]

    def wait_rdapi(self, timeout=40.0):
        wait_until(lambda: self._master_alive() and self.rdapi("GET", "/", timeout=2)[0] == 200, timeout=timeout,
                   interval=0.3, message="the master's RDAPI on eth0")

    def _master_alive(self):
        if self.master.process is not None and self.master.process.poll() is not None:
            raise AssertionError(f"the master exited {self.master.process.returncode}: "
                                 f"{self.master.output()[-3000:]}")
        return True

    def state(self, name):
        """(connected, paired) of robot ``name`` as the RDAPI shows it, or None."""
        status, answer = self.rdapi("GET", "/platform_instance/read", timeout=3)
        if status != 200:
            return None
        rows = {row["pi_name"]: row for row in answer["reason"]}
        row = rows.get(name)
        return None if row is None else (row["connected"], row["paired"])

    def wait_state(self, name, connected, paired, timeout=40.0):
        wait_until(lambda: self.state(name) == (connected, paired), timeout=timeout, interval=0.2,
                   message=f"{name} connected={connected} paired={paired} (now {self.state(name)})")
