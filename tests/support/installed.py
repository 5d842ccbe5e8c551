"""An installed platform in a test host (tests/support/hosts.py), driven as its administrator would drive it.

``curl(host, url, body)`` calls an HTTP API from inside the host; ``service(host, action)`` runs ``service rcmpd
ACTION`` there; ``stop_daemons(*hosts)`` stops every installed daemon (for ``finally`` blocks: a LAN's teardown
reports a process left running as a failure); ``log_tail(host)`` gives the daemon's output and the agent's log for
a failure message; ``agent_pid(host)`` reads the daemon's pid file; ``process_env(pid)`` and ``process_argv(pid)``
read a process of any host from /proc (hosts share this machine's pid namespace).
"""

import json

USER_PATH = "/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"
# a root login's environment, as the administrator who runs the installer has it
ROOT_ENV = {"PATH": USER_PATH, "HOME": "/root", "LANG": "C", "USER": "root", "LOGNAME": "root"}


def curl(host, url, body=None, timeout=5):
    """(status, parsed JSON or text) of an HTTP request made from inside ``host``; (None, output) when curl
    fails."""
    argv = ["curl", "-s", "-S", "--max-time", timeout, "-w", "\n%{http_code}"]
    if body is not None:
        argv += ["-H", "Content-Type: application/json", "--data-binary", json.dumps(body)]
    result = host.run(argv + [url], check=False, timeout=timeout + 10)
    if result.returncode != 0:
        return None, result.stdout
    text, _, code = result.stdout.rpartition("\n")
    try:
        return int(code), json.loads(text)
    except ValueError:
        return int(code), text


def service(host, action, check=False):
    return host.run(["service", "rcmpd", action], env={"PATH": USER_PATH, "LANG": "C"}, check=check, timeout=120)


def agent_pid(host):
    result = host.run(["cat", "/run/rcmpd.pid"], check=False)
    return int(result.stdout) if result.returncode == 0 and result.stdout.strip().isdigit() else None


def stop_daemons(*hosts):
    """Stop the daemon of every host (finally blocks): the LAN's teardown would otherwise report it as left."""
    for host in hosts:
        if host.run(["test", "-x", "/etc/init.d/rcmpd"], check=False).returncode == 0:
            service(host, "stop")


def log_tail(host, lines=40):
    text = ""
    for name in ("rcmpd.out", "rcmp.log"):
        result = host.run(["tail", "-n", lines, f"/opt/rcm-platform/log/{name}"], check=False)
        text += f"--- {host.name} {name}\n{result.stdout}"
    return text


def process_env(pid):
    with open(f"/proc/{pid}/environ", "rb") as f:
        return dict(item.decode().split("=", 1) for item in f.read().split(b"\0") if b"=" in item)


def process_argv(pid):
    """The argv of ``pid``, or None when it is gone."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return [a.decode("utf-8", "replace") for a in f.read().split(b"\0") if a]
    except OSError:
        return None
