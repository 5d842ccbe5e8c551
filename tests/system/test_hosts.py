"""The test-host library (tests/support/hosts.py): hosts reach each other over eth0, links cut, installed files
stay private to a host, and teardown leaves nothing behind after an exception, a signal or a killed run."""

import os
import signal
import subprocess
import sys

import pytest

from tests.support import hosts as hostlib
from tests.support.hosts import Lan, netns_names
from tests.support.paths import REPO
from tests.support.polling import wait_until

pytestmark = [pytest.mark.netns,
              pytest.mark.skipif(os.geteuid() != 0, reason="test hosts need root (network namespaces)")]

PY = "/usr/bin/python3"
# a one-connection-at-a-time echo server on ADDRESS:PORT that answers "<host name>:<what it got>"
ECHO_SERVER = """
import socket, sys
s = socket.socket()
s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
s.bind((sys.argv[1], int(sys.argv[2])))
s.listen(8)
while True:
    c, _ = s.accept()
    c.sendall(sys.argv[3].encode() + b":" + c.recv(100))
    c.close()
"""
CLIENT = """
import socket, sys
c = socket.create_connection((sys.argv[1], int(sys.argv[2])), timeout=float(sys.argv[3]))
c.sendall(b"hi")
print(c.recv(100).decode())
"""


def ask(host, address, port=7000, timeout=2):
    """Connect from ``host`` to address:port; the answer, or None when the connection fails."""
    result = host.run([PY, "-c", CLIENT, address, port, timeout], check=False, timeout=30)
    return result.stdout.strip() if result.returncode == 0 else None


def serve(host, port=7000):
    host.start([PY, "-c", ECHO_SERVER, host.address, port, host.name])
    wait_until(lambda: ask(host, host.address, port) == f"{host.name}:hi", timeout=10,
               message=f"the echo server on {host.name}")


def test_two_hosts_reach_each_other_over_eth0_and_nothing_is_in_the_root_namespace(lan):
    a, b = lan.add_host("alpha"), lan.add_host("beta")
    assert a.address == "203.0.113.10" and b.address == "203.0.113.11"
    links = a.run(["ip", "-o", "-4", "addr", "show"]).stdout
    assert "eth0" in links and "inet 203.0.113.10/24" in links and "inet 127.0.0.1/8" in links
    assert a.run(["cat", "/sys/class/net/eth0/address"]).stdout.strip()  # /sys shows the host's own links
    serve(a)
    serve(b)
    assert ask(b, a.address) == "alpha:hi"
    assert ask(a, b.address) == "beta:hi"
    # the root namespace has no test address, no bridge, no host end of a veth
    root = subprocess.run(["ip", "-o", "addr"], stdout=subprocess.PIPE, text=True).stdout
    assert "203.0.113." not in root
    bridges = subprocess.run(["ip", "-o", "link", "show", "type", "bridge"], stdout=subprocess.PIPE,
                             text=True).stdout
    assert "br0" not in bridges
    # nor can the root namespace reach a host
    probe = subprocess.run([PY, "-c", CLIENT, a.address, "7000", "1"], stdout=subprocess.PIPE,
                           stderr=subprocess.STDOUT, text=True)
    assert probe.returncode != 0


def test_link_down_cuts_and_link_up_restores(lan):
    a, b = lan.add_host("alpha"), lan.add_host("beta")
    serve(a)
    assert ask(b, a.address) == "alpha:hi"
    b.link_down()
    assert ask(b, a.address, timeout=1) is None
    b.link_up()
    assert wait_until(lambda: ask(b, a.address) == "alpha:hi", timeout=10)
    # cut at the bridge: the host keeps its carrier-less link configured, but nothing gets through
    b.link_down(side="lan")
    assert "203.0.113.11" in b.run(["ip", "-o", "-4", "addr", "show", "eth0"]).stdout
    assert ask(b, a.address, timeout=1) is None
    b.link_up(side="lan")
    assert wait_until(lambda: ask(b, a.address) == "alpha:hi", timeout=10)


def test_fresh_paths_start_empty_and_stay_the_hosts(lan):
    a = lan.add_host("alpha", private=hostlib.INSTALL_PATHS, fresh=hostlib.INSTALL_FRESH)
    assert a.run(["ls", "-A", "/opt"]).stdout.split() == []
    a.run(["mkdir", "/opt/rcm-platform"])
    a.run(["touch", "/opt/rcm-platform/x", os.path.join(hostlib.INSTALL_FRESH[1], "y.py")])
    assert os.path.isfile(a.private_path("/opt/rcm-platform/x"))
    assert os.path.isfile(a.private_path(os.path.join(hostlib.INSTALL_FRESH[1], "y.py")))
    assert not os.path.exists(os.path.join(hostlib.INSTALL_FRESH[1], "y.py"))
    assert a.run(["test", "-x", "/usr/bin/python3"]).returncode == 0


def test_private_paths_are_seen_only_by_their_host(lan):
    a = lan.add_host("alpha", private=("/opt", "/usr/local"))
    b = lan.add_host("beta", private=("/opt",))
    marker = f"/opt/rcmt-probe-{os.getpid()}"
    a.run(["mkdir", "-p", marker + "/sub"])
    a.run(["touch", marker + "/sub/file"])
    assert os.path.isfile(os.path.join(a.private_path(marker), "sub", "file"))
    assert not os.path.exists(marker)
    assert b.run(["test", "-e", marker], check=False).returncode == 1
    # the real content stays visible through the overlay
    assert a.run(["test", "-x", "/usr/bin/python3"]).returncode == 0
    real = sorted(os.listdir("/usr/local"))
    assert set(real) <= set(a.run(["ls", "-A", "/usr/local"]).stdout.split())
    with pytest.raises(ValueError):
        a.private_path("/etc/hosts")


def test_teardown_after_an_exception_leaves_nothing(tmp_path):
    with pytest.raises(RuntimeError, match="boom"):
        with Lan(log_dir=str(tmp_path)) as lan:
            a = lan.add_host("alpha", private=("/opt",))
            lan.add_host("beta")
            child = a.start(["sleep", "600"])
            holders = [h.holder.pid for h in lan.hosts.values()]
            raise RuntimeError("boom")
    assert lan.leftovers() == []
    assert not any(n.startswith(lan.run_id) for n in netns_names())
    assert child.poll() is not None
    assert not any(os.path.exists(f"/proc/{pid}") for pid in holders)
    assert not os.path.exists(lan.state_dir)


def test_a_process_left_in_a_host_is_killed_and_reported(tmp_path):
    lan = Lan(log_dir=str(tmp_path))
    a = lan.add_host("alpha")
    stray = subprocess.Popen(a.argv(["sleep", "600"]), start_new_session=True)
    wait_until(lambda: stray.pid in a.pids(), timeout=10, message="the stray to be in the host")
    with pytest.raises(AssertionError, match="processes left in"):
        lan.close()
    assert stray.wait(timeout=10) == -signal.SIGKILL
    assert lan.leftovers() == []


def test_bad_host_names_are_refused(lan):
    for bad in ("", "Alpha", "lan", "a-b", "x" * 13, "a/b"):
        with pytest.raises(ValueError):
            lan.add_host(bad)
    lan.add_host("alpha")
    with pytest.raises(ValueError):
        lan.add_host("alpha")
    with pytest.raises(ValueError):
        lan.add_host("beta", address="198.51.100.7")


OWNER = """
import sys, time
sys.path.insert(0, sys.argv[1])
from tests.support.hosts import Lan
lan = Lan()
lan.add_host("alpha", private=("/opt",))
lan.add_host("beta")
print(lan.run_id, flush=True)
while True:
    time.sleep(1)
"""


def start_owner(procs):
    proc = procs.start([sys.executable, "-c", OWNER, REPO], stdout=subprocess.PIPE, text=True, name="lan-owner")
    run_id = proc.stdout.readline().strip()
    assert run_id.startswith(hostlib.PREFIX + "-"), run_id
    assert [n for n in netns_names() if n.startswith(run_id + "-")]
    return proc, run_id


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_an_interrupted_run_removes_its_hosts(procs, sig):
    proc, run_id = start_owner(procs)
    os.kill(proc.pid, sig)
    proc.wait(timeout=30)
    assert not [n for n in netns_names() if n.startswith(run_id + "-")]
    assert not os.path.exists(os.path.join(hostlib.STATE_ROOT, run_id))


def test_a_killed_run_is_swept_by_the_next_one(procs, tmp_path):
    proc, run_id = start_owner(procs)
    holders = [pid for n in netns_names() if n.startswith(run_id + "-") for pid in hostlib.netns_pids(n)]
    assert holders
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=10)
    # the holders die with their owner (pdeathsig): the mount namespaces and overlays go with them
    wait_until(lambda: not any(os.path.exists(f"/proc/{pid}") for pid in holders), timeout=10,
               message="the holders to die with their owner")
    # the names stay until the next Lan on this machine sweeps them (maybe another test run's, at any moment)
    with Lan(log_dir=str(tmp_path)):
        assert not [n for n in netns_names() if n.startswith(run_id + "-")]
    assert not os.path.exists(os.path.join(hostlib.STATE_ROOT, run_id))


def test_a_reused_pid_does_not_keep_a_dead_runs_namespaces(tmp_path):
    # a run that died long ago with the pid this process has now: same pid, another start time
    stale = f"{hostlib.PREFIX}-{os.getpid()}-1-1-lan"
    other = f"{hostlib.PREFIX}-{os.getpid()}-7-lan"  # not a name this library makes: never touched
    subprocess.run(["ip", "netns", "add", stale], check=True)
    subprocess.run(["ip", "netns", "add", other], check=True)
    try:
        with Lan(log_dir=str(tmp_path)) as lan:
            assert stale not in netns_names()
            assert other in netns_names()
            assert lan.run_id.startswith(f"{hostlib.PREFIX}-{os.getpid()}-")
    finally:
        for name in (stale, other):
            subprocess.run(["ip", "netns", "del", name], stderr=subprocess.DEVNULL)
    assert stale not in netns_names() and other not in netns_names()


def test_hidden_paths_and_empty_folders_below_private_ones(lan, tmp_path):
    base = tmp_path / "machine"
    (base / "rc2.d").mkdir(parents=True)
    (base / "rc2.d" / "S01other").write_text("")
    (base / "installed").mkdir()
    (base / "installed" / "cfg").write_text("the machine's own")
    (base / "kept").write_text("seen")
    host = lan.add_host("alpha", private=(str(base),), hide=(str(base / "installed"), str(base / "later")),
                        empty=(str(base / "rc2.d"),))
    listing = host.run(["ls", "-A", base]).stdout.split()
    assert "kept" in listing and "installed" not in listing and "rc2.d" in listing
    assert host.run(["ls", "-A", base / "rc2.d"]).stdout.split() == []
    # what the machine installs after the host was made stays hidden too
    (base / "later").mkdir()
    (base / "later" / "x").write_text("")
    assert host.run(["test", "-e", base / "later"], check=False).returncode == 1
    # the host's own installation there is its own
    host.run(["mkdir", base / "installed"])
    host.run(["touch", base / "installed" / "mine"])
    assert host.run(["ls", "-A", base / "installed"]).stdout.split() == ["mine"]
    assert sorted(os.listdir(base / "installed")) == ["cfg"]
    assert oct(os.stat(host.private_path(str(base))).st_mode & 0o777) == oct(os.stat(base).st_mode & 0o777)


def test_install_hosts_do_not_see_this_machines_rcm_installation():
    assert "/opt/rcm-platform" in hostlib.RCM_INSTALLATION and "/etc/init.d/rcmpd" in hostlib.RCM_INSTALLATION
    bases = hostlib.INSTALL_PATHS + hostlib.INSTALL_FRESH
    assert all(any(p.startswith(base + "/") for base in bases) for p in hostlib.RCM_INSTALLATION)
