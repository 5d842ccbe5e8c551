"""A real RCM agent (``/usr/bin/python3 -m rcm_platform --home DIR``) started by a test, for any role and any keys.

``RcmpAgent(procs, home, role="master", **keys)`` writes the configuration file of its role (``.init.cfg`` for
the master, ``init.cfg`` for a robot or a server VM, ``[main]`` with the keys given), starts the agent as a child
of the test's ``ProcessGroup`` (its own session, stopped as a group, checked gone) and waits until it is ready:
the master when its RDAPI answers ``GET /``, a robot or server when its log says it started.

Loopback defaults: the master gets ``vpn_address`` and ``ext_address`` 127.0.0.1 and free ``ext_port`` and
``ic_port``; a robot gets ``vpn_address`` 127.0.0.1 (give ``ip_master`` and ``ic_port`` of its master). Any key
can be overridden, or removed by passing ``None``. ``base_url`` is the RDAPI's URL; ``get``/``post`` call it
and return ``(status, decoded JSON or text)``.
"""

import http.client
import json
import os
import signal

from .polling import wait_until
from .ports import stable_free_ports
from .processes import ros_env

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
PYTHON = "/usr/bin/python3"


class AgentLog:
    """The agent's own log, ``HOME/log/rcmp.log``, for any helper with a ``home``."""

    @property
    def log_path(self):
        return os.path.join(self.home, "log", "rcmp.log")

    def log_text(self):
        try:
            with open(self.log_path, encoding="utf-8", errors="replace") as f:
                return f.read()
        except OSError:
            return ""


class RcmpAgent(AgentLog):
    """One agent owned by a test. ``start()`` returns self; ``stop()``, ``kill()``, ``restart()``."""

    def __init__(self, procs, home, role="master", env=None, args=(), **keys):
        assert role in ("master", "robot", "server"), role
        self.procs = procs
        self.home = str(home)
        self.role = role
        self.extra_env = dict(env or {})
        self.args = list(args)
        self.process = None
        os.makedirs(self.home, exist_ok=True)
        if role == "master":
            ext_port, ic_port = stable_free_ports(2)
            defaults = {"vpn_address": "127.0.0.1", "ext_address": "127.0.0.1", "ext_port": ext_port,
                        "ic_port": ic_port}
        else:
            defaults = {"robot": "yes" if role == "robot" else "no", "vpn_address": "127.0.0.1"}
        defaults.update(keys)
        self.keys = {k: v for k, v in defaults.items() if v is not None}
        self.write_config()

    # -- configuration ------------------------------------------------------------------------------------
    @property
    def config_path(self):
        return os.path.join(self.home, ".init.cfg" if self.role == "master" else "init.cfg")

    def write_config(self):
        lines = ["[main]"] + [f"{key}={value}" for key, value in self.keys.items()]
        with open(self.config_path, "w") as f:
            f.write("\n".join(lines) + "\n")

    @property
    def ext_port(self):
        return int(self.keys["ext_port"]) if "ext_port" in self.keys else 80

    @property
    def ic_port(self):
        return int(self.keys["ic_port"]) if "ic_port" in self.keys else 9999

    @property
    def host(self):
        return str(self.keys.get("ext_address", "127.0.0.1"))

    @property
    def base_url(self):
        return f"http://{self.host}:{self.ext_port}"

    @property
    def db_path(self):
        return os.path.join(self.home, "robotics_data.db")


    def wait_log(self, text, timeout=20.0):
        """Wait until ``text`` appears in rcmp.log (anywhere, this run or a previous one) and return the log."""
        return wait_until(lambda: text in self.log_text() and self.log_text(), timeout=timeout,
                          message=f"{text!r} in {self.log_path}")

    # -- life ---------------------------------------------------------------------------------------------
    def argv(self):
        return [PYTHON, "-m", "rcm_platform", "--home", self.home] + self.args

    def env(self):
        env = ros_env(self.extra_env)
        env["PYTHONPATH"] = REPO + (":" + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        env.setdefault("ROS_LOG_DIR", os.path.join(self.home, "roslog"))
        return env

    def start(self, wait=True, timeout=20.0):
        self._log_size = os.path.getsize(self.log_path) if os.path.exists(self.log_path) else 0
        self.process = self.procs.start(self.argv(), env=self.env(), name=f"rcmp-{self.role}", cwd=REPO)
        if wait:
            self.wait_ready(timeout)
        return self

    def output(self):
        """What the agent wrote on stdout/stderr so far."""
        return self.procs.output(self.process) if self.process else ""

    def wait_ready(self, timeout=20.0):
        def ready():
            if self.process.poll() is not None:
                raise AssertionError(f"the agent exited with {self.process.returncode}: {self.output()[-2000:]}")
            if self.role == "master":
                return self.get("/")[0] == 200
            return "rcmp_n started as" in self.log_text()[self._log_size:]
        try:
            wait_until(ready, timeout=timeout, message=f"the {self.role} agent in {self.home} to be ready")
        except AssertionError:
            raise AssertionError(f"agent not ready; its output:\n{self.output()[-3000:]}") from None
        return self

    def stop(self, timeout=20.0):
        """SIGTERM, then wait for exit (``timeout`` s); returns the exit status. The group is checked gone."""
        if self.process is None:
            return None
        self.process.send_signal(signal.SIGTERM)
        wait_until(lambda: self.process.poll() is not None, timeout=timeout, message="the agent to exit on SIGTERM")
        status = self.process.returncode
        self.procs.stop(self.process)
        self.procs.children.remove(self.process)
        return status

    def kill(self):
        """SIGKILL the agent (its whole process group) and reap it."""
        os.killpg(self.process.pid, signal.SIGKILL)
        wait_until(lambda: self.process.poll() is not None, timeout=10.0, message="the agent to die")
        self.procs.stop(self.process)
        self.procs.children.remove(self.process)

    def restart(self, wait=True):
        self.stop()
        return self.start(wait=wait)

    # -- RDAPI --------------------------------------------------------------------------------------------
    def request(self, method, path, body=None, headers=None, timeout=10.0):
        """One request on a fresh connection; returns ``(status, JSON value or text, headers dict)``."""
        conn = http.client.HTTPConnection(self.host, self.ext_port, timeout=timeout)
        try:
            if body is not None and not isinstance(body, (bytes, str)):
                body = json.dumps(body)
            conn.request(method, path, body=body, headers=headers or {})
            resp = conn.getresponse()
            raw = resp.read()
            hdrs = {k.lower(): v for k, v in resp.getheaders()}
        finally:
            conn.close()
        text = raw.decode("utf-8", "replace")
        if text and hdrs.get("content-type", "").startswith("application/json"):
            return resp.status, json.loads(text), hdrs
        return resp.status, text, hdrs

    def get(self, path):
        status, value, _ = self.request("GET", path)
        return status, value

    def post(self, path, body):
        status, value, _ = self.request("POST", path, body, {"Content-Type": "application/json"})
        return status, value
