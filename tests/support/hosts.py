"""Test hosts as Linux namespaces: a LAN of hosts, each with its own ``eth0``, and a teardown that always runs.

What a ``Lan`` builds (root only; CAP_NET_ADMIN and CAP_SYS_ADMIN):

- **The LAN**: a network namespace ``rcmt-<pid>-<start>-<seq>-lan`` (the creating process's pid and start time, a
  sequence number) holding a bridge ``br0``. The bridge is never in the
  root namespace, so no test packet can reach the machine's real network.
- **A host** (``lan.add_host("master")``): a network namespace ``rcmt-<pid>-<start>-<seq>-<name>`` with loopback up and a
  veth pair created straight into the namespaces (the host's end is named ``eth0``, the LAN's end is a port of
  ``br0``), addressed in ``203.0.113.0/24`` (``.10`` upwards unless an address is given).
- **A mount namespace per host**, held by a *holder* process: ``setpriv --pdeathsig KILL ip netns exec NS sleep
  infinity``. ``ip netns exec`` unshares the mount namespace and mounts a ``/sys`` that shows the host's own
  interfaces; every command of the host then runs through ``nsenter --target HOLDER --net --mount`` (no fork, so
  the command's pid is the one a ``ProcessGroup`` signals). Nothing is mounted in the root namespace, ever.
- **Private installed files** (``lan.add_host("robot", private=INSTALL_PATHS)``): each listed directory is covered,
  inside that host's mount namespace only, by an overlayfs whose lower layer is the real directory and whose
  upper layer is a per-host directory under the run's state folder. An installer run in the host therefore sees
  the machine's files (Python, ROS, ``/usr/bin``) and writes only to its own copy: two hosts can install
  different zips into ``/opt/rcm-platform`` at once, and this machine's real installation paths (``/opt``,
  ``/usr/local``, ``/etc``) are never touched. Overlays are used rather than bind mounts of empty folders
  because an installer needs the real content beside its own (``/etc/init.d/*``, ``/usr/lib/python3``);
  ``Host.private_path(path)`` names the host's upper copy of a path, to inspect what the host wrote. Below the
  private folders the host does not see this machine's own rcm-platform installation (``RCM_INSTALLATION``,
  whited out in the upper layer, so also what ``tests/system/test_install.py`` installs there later) and sees the
  ``/etc/rc?.d`` folders empty (opaque): its installer starts from a clean machine. Folders whose machine content
  a host does not need and that another test may change while the host lives (``/opt``, where
  ``tests/system/test_install.py`` installs and removes ``/opt/rcm-platform``, and the package's dist-packages) are
  ``fresh=`` instead: covered by an empty folder of the host's own (a bind mount), because overlayfs does not
  allow its lower layer to change under it. Hosts for an installation: ``private=INSTALL_PATHS,
  fresh=INSTALL_FRESH``.

Commands: ``host.run(argv)`` (a list, never a shell; returns ``CompletedProcess``, raises ``HostCommandError``
with the output when ``check`` and it fails), ``host.start(argv)`` (a long-running child owned by the LAN's
``ProcessGroup``, or by the one passed as ``procs=``), ``host.argv(argv)`` (the wrapped argv, to start it
yourself), ``host.link_down()`` / ``host.link_up()`` (``ip link set eth0 down|up`` in the host, as an
administrator would; ``side="lan"`` cuts the bridge's end instead, so the host sees no carrier change).

Teardown (``Lan.close``; the ``with`` block, the ``lan`` fixture and an ``atexit`` hook all call it) always
runs every step, even when one fails: it stops the owned children, SIGKILLs any other process still in a host
(reported as a failure after the cleanup: a test must stop what it started), kills the holders (their mount
namespaces and overlays vanish with them), deletes every network namespace (veths and the bridge go with them)
and removes the state folder. SIGTERM and SIGHUP are turned into ``SystemExit`` while a LAN is open so that
``finally`` blocks and ``atexit`` run; Ctrl-C already does. If the test process is SIGKILLed, the holders die
with it (``pdeathsig``) and the next ``Lan`` created on the machine sweeps namespaces and state folders whose
owner (pid and start time, so a reused pid does not count) is gone. Names carry the creating pid, its start time
and a sequence number, so parallel runs never collide.

Create LANs from the main thread (``pdeathsig`` fires when the creating *thread* exits).
"""

import atexit
import ipaddress
import itertools
import os
import re
import shutil
import signal
import site
import stat
import subprocess
import tempfile
import threading

from .processes import ProcessGroup, group_alive
from .polling import wait_until

PREFIX = "rcmt"
LAN_SUBNET = "203.0.113.0/24"
VPN_SUBNET = "198.51.100.0/24"
# what an rcm-platform installer writes to (section 5 of CONTRACTS.md), for hosts whose installed files differ
INSTALL_PATHS = ("/usr/local", "/etc", "/root", "/var/log", "/run")
# folders an rcm-platform installer writes whose machine content a host does not need: replaced by empty ones
INSTALL_FRESH = ("/opt", site.getsitepackages()[0])
# what an rcm-platform installation of this machine (tests/system/test_install.py may be running) places below those: a
# host never sees it, so its own installation starts from nothing (whiteouts in the overlay; the rc?.d folders
# start empty, as update-rc.d's link names vary)
RCM_INSTALLATION = ("/opt/rcm-platform", "/usr/local/bin/rcmp_n",
                    os.path.join(site.getsitepackages()[0], "rcm_platform"),
                    "/etc/init.d/rcmpd", "/etc/default/rcmpd", "/run/rcmpd.pid", "/root/rcmp_ws")
EMPTY_DIRS = tuple(f"/etc/rc{level}.d" for level in "0123456S")
HOST_NAME = re.compile(r"^[a-z][a-z0-9]{0,11}$")
STATE_ROOT = tempfile.gettempdir()

_seq = itertools.count(1)
_open_lans = set()
_lock = threading.Lock()
_previous_handlers = {}


class HostCommandError(AssertionError):
    """A command run in a host failed; the message holds its argv, exit status and output."""


def _ip_unchecked(*args):
    return subprocess.run(["ip", *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                          stdin=subprocess.DEVNULL)


def _checked(argv, timeout=30):
    result = subprocess.run(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            stdin=subprocess.DEVNULL, timeout=timeout)
    if result.returncode != 0:
        raise HostCommandError(f"{argv} exited {result.returncode}: {result.stdout.strip()}")
    return result


def netns_names():
    """The names ``ip netns list`` shows (first word of each line)."""
    out = subprocess.run(["ip", "netns", "list"], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                         stdin=subprocess.DEVNULL).stdout
    return [line.split()[0] for line in out.splitlines() if line.strip()]


def netns_pids(netns):
    """Pids of the processes in network namespace ``netns`` (empty if it is gone)."""
    result = subprocess.run(["ip", "netns", "pids", netns], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                            text=True, stdin=subprocess.DEVNULL)
    return [int(p) for p in result.stdout.split() if p.isdigit()]


def _start_time(pid):
    """The start time of process ``pid`` (clock ticks since boot), or None when it is gone."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return int(f.read().rsplit(")", 1)[1].split()[19])
    except (OSError, IndexError, ValueError):
        return None


def _owner_alive(pid, start):
    """True while the process that made a run (``pid`` started at ``start``) lives; a reused pid does not count."""
    return _start_time(pid) == start


def _kill_netns_processes(netns):
    """SIGKILL every process in ``netns``; returns the pids that were there (with their command names)."""
    found = []
    for pid in netns_pids(netns):
        try:
            with open(f"/proc/{pid}/comm") as f:
                comm = f.read().strip()
        except OSError:
            comm = "?"
        found.append((pid, comm))
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    if found:
        wait_until(lambda: not netns_pids(netns), timeout=10, message=f"processes in {netns} to die")
    return found


def sweep_stale():
    """Remove namespaces and state folders of runs whose creating process is gone (a SIGKILLed test run)."""
    pattern = re.compile(rf"^{PREFIX}-(\d+)-(\d+)-\d+-")   # PREFIX-PID-STARTTIME-SEQ-...
    for netns in netns_names():
        m = pattern.match(netns)
        if m and not _owner_alive(int(m.group(1)), int(m.group(2))):
            _kill_netns_processes(netns)
            _ip_unchecked("netns", "del", netns)
    for entry in os.listdir(STATE_ROOT):
        m = pattern.match(entry + "-") if entry.startswith(PREFIX + "-") else None
        if m and not _owner_alive(int(m.group(1)), int(m.group(2))):
            shutil.rmtree(os.path.join(STATE_ROOT, entry), ignore_errors=True)


def _close_all_open():
    for lan in list(_open_lans):
        try:
            lan.close(check=False)
        except Exception:  # atexit: clean what can be cleaned, never hide the rest
            pass


def _exit_on_signal(signum, frame):
    raise SystemExit(128 + signum)


def _install_signal_handlers():
    if threading.current_thread() is not threading.main_thread():
        return
    for sig in (signal.SIGTERM, signal.SIGHUP):
        if sig in _previous_handlers:
            continue
        current = signal.getsignal(sig)
        if current in (signal.SIG_DFL, None):
            _previous_handlers[sig] = current
            signal.signal(sig, _exit_on_signal)


def _restore_signal_handlers():
    if threading.current_thread() is not threading.main_thread():
        return
    for sig, handler in list(_previous_handlers.items()):
        if signal.getsignal(sig) is _exit_on_signal:
            signal.signal(sig, handler)
        del _previous_handlers[sig]


atexit.register(_close_all_open)


class Host:
    """One host of a ``Lan``: a network namespace with ``eth0`` and a mount namespace held by a holder process."""

    def __init__(self, lan, name, index, address, private, hide=RCM_INSTALLATION, empty=EMPTY_DIRS, fresh=()):
        self.lan = lan
        self.name = name
        self.netns = f"{lan.run_id}-{name}"
        self.address = address
        self.port = f"p{index}"  # the LAN end of the veth, in the LAN namespace
        self.private = tuple(os.path.normpath(p) for p in private)
        self.hide = tuple(os.path.normpath(p) for p in hide)
        self.empty = tuple(os.path.normpath(p) for p in empty)
        self.fresh = tuple(os.path.normpath(p) for p in fresh)
        self.state_dir = os.path.join(lan.state_dir, name)
        self.holder = None

    # ---- building
    def _create(self):
        os.makedirs(self.state_dir)
        _checked(["ip", "netns", "add", self.netns])
        self.lan._netns.append(self.netns)
        _checked(["ip", "link", "add", "eth0", "netns", self.netns, "type", "veth",
                  "peer", "name", self.port, "netns", self.lan.netns])
        _checked(["ip", "-n", self.lan.netns, "link", "set", self.port, "master", "br0", "up"])
        _checked(["ip", "-n", self.netns, "link", "set", "lo", "up"])
        _checked(["ip", "-n", self.netns, "addr", "add", f"{self.address}/{self.lan.prefixlen}", "dev", "eth0"])
        _checked(["ip", "-n", self.netns, "link", "set", "eth0", "up"])
        self.holder = subprocess.Popen(
            ["setpriv", "--pdeathsig", "KILL", "--", "ip", "netns", "exec", self.netns, "sleep", "infinity"],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            start_new_session=True)
        own_mnt = os.readlink("/proc/self/ns/mnt")
        wait_until(lambda: self._holder_ready(own_mnt), timeout=10, message=f"the holder of host {self.name}")
        for path in sorted(self.private, key=len):
            self._overlay(path)
        for path in sorted(self.fresh, key=len):
            self._fresh(path)

    def _holder_ready(self, own_mnt):
        if self.holder.poll() is not None:
            raise HostCommandError(f"the holder of host {self.name} exited {self.holder.returncode}")
        pid = self.holder.pid
        with open(f"/proc/{pid}/comm") as f:
            if f.read().strip() != "sleep":
                return False
        return os.readlink(f"/proc/{pid}/ns/mnt") != own_mnt

    def _overlay(self, path):
        path = os.path.normpath(path)
        if not os.path.isabs(path) or not os.path.isdir(path):
            raise ValueError(f"private path {path!r} must be an existing absolute directory")
        key = path.strip("/").replace("/", "_") or "root"
        upper = os.path.join(self.state_dir, "upper", key)
        work = os.path.join(self.state_dir, "work", key)
        os.makedirs(upper)
        os.makedirs(work)
        self._mirror_dir(path, upper)
        # before mounting (changing the upper layer of a mounted overlay is undefined): the machine's own
        # installation is whited out, the rc?.d folders made opaque (empty); both hold even for files the
        # machine creates later
        for hidden in self.hide + self.empty:
            rel = self._below(hidden, path)
            if rel is None:
                continue
            parent = upper
            for part in rel.split("/")[:-1]:
                lower = os.path.join(path, os.path.relpath(parent, upper), part)
                parent = os.path.join(parent, part)
                if not os.path.isdir(parent):
                    os.mkdir(parent)
                    if os.path.isdir(lower):
                        self._mirror_dir(lower, parent)
            target = os.path.join(upper, rel)
            if hidden in self.empty:
                os.mkdir(target)
                if os.path.isdir(os.path.join(path, rel)):
                    self._mirror_dir(os.path.join(path, rel), target)
                os.setxattr(target, "trusted.overlay.opaque", b"y")
            else:
                os.mknod(target, stat.S_IFCHR | 0o600, os.makedev(0, 0))  # an overlayfs whiteout
        self.run(["mount", "-t", "overlay", "overlay", "-o",
                  f"lowerdir={path},upperdir={upper},workdir={work}", path])

    def _fresh(self, path):
        """Cover ``path`` (inside the host only) with an empty folder of the host's own, owner and mode as the real
        one: nothing of the machine shows there, and the machine changing its folder cannot confuse an overlay."""
        if not os.path.isabs(path) or not os.path.isdir(path):
            raise ValueError(f"fresh path {path!r} must be an existing absolute directory")
        own = os.path.join(self.state_dir, "fresh", path.strip("/").replace("/", "_"))
        os.makedirs(own)
        self._mirror_dir(path, own)
        self.run(["mount", "--bind", own, path])

    @staticmethod
    def _below(path, base):
        """``path`` relative to ``base`` when strictly below it, else None."""
        if path.startswith(base.rstrip("/") + "/"):
            return os.path.relpath(path, base)
        return None

    @staticmethod
    def _mirror_dir(real, copy):
        """Give a folder of the upper layer the real folder's owner and mode (the upper one's win in the view)."""
        st = os.stat(real)
        os.chown(copy, st.st_uid, st.st_gid)
        os.chmod(copy, stat.S_IMODE(st.st_mode))

    def private_path(self, path):
        """Where this host's own changes below ``path`` are stored (the overlay's upper layer), seen from outside."""
        path = os.path.normpath(path)
        bases = [(b, "fresh") for b in self.fresh] + [(b, "upper") for b in self.private]
        for base, layer in sorted(bases, key=lambda item: len(item[0]), reverse=True):
            if path == base or path.startswith(base.rstrip("/") + "/"):
                key = base.strip("/").replace("/", "_") or "root"
                return os.path.join(self.state_dir, layer, key, os.path.relpath(path, base))
        raise ValueError(f"{path} is not below a private path of host {self.name}")

    # ---- commands
    def argv(self, argv):
        """``argv`` (a list) wrapped to run in this host's network and mount namespaces."""
        if not isinstance(argv, (list, tuple)) or not argv:
            raise TypeError("argv must be a non-empty list: no shell")
        return ["nsenter", f"--target={self.holder.pid}", "--net", "--mount", "--", *map(str, argv)]

    def run(self, argv, check=True, timeout=60, **kwargs):
        """Run ``argv`` in the host and wait; output captured as text (stdout, stderr merged unless given)."""
        kwargs.setdefault("stdout", subprocess.PIPE)
        kwargs.setdefault("stderr", subprocess.STDOUT)
        kwargs.setdefault("stdin", subprocess.DEVNULL)
        result = subprocess.run(self.argv(argv), text=True, timeout=timeout, **kwargs)
        if check and result.returncode != 0:
            raise HostCommandError(f"{self.name}: {list(argv)} exited {result.returncode}: {result.stdout}"
                                   + (f" {result.stderr}" if result.stderr else ""))
        return result

    def start(self, argv, procs=None, name=None, **kwargs):
        """Start ``argv`` in the host as a long-running child of ``procs`` (default: the LAN's ProcessGroup)."""
        group = procs if procs is not None else self.lan.procs
        name = name or f"{self.name}-{os.path.basename(str(argv[0]))}"
        return group.start(self.argv(argv), name=name, **kwargs)

    def link_down(self, side="host"):
        """Cut this host's LAN link: ``ip link set eth0 down`` in the host, or its port on the bridge (``lan``)."""
        self._set_link("down", side)

    def link_up(self, side="host"):
        self._set_link("up", side)

    def _set_link(self, state, side):
        if side == "host":
            _checked(["ip", "-n", self.netns, "link", "set", "eth0", state])
        elif side == "lan":
            _checked(["ip", "-n", self.lan.netns, "link", "set", self.port, state])
        else:
            raise ValueError("side is 'host' or 'lan'")

    def pids(self):
        """Pids of the processes in this host's network namespace (the holder included)."""
        return netns_pids(self.netns)

    def __repr__(self):
        return f"<Host {self.name} {self.address} netns={self.netns}>"


class Lan:
    """A LAN of test hosts in its own namespaces; use as a context manager (or the ``lan`` fixture)."""

    def __init__(self, subnet=LAN_SUBNET, log_dir=None, procs=None):
        if os.geteuid() != 0:
            raise PermissionError("test hosts need root (network and mount namespaces)")
        self.network = ipaddress.ip_network(subnet)
        self.prefixlen = self.network.prefixlen
        with _lock:
            self.run_id = f"{PREFIX}-{os.getpid()}-{_start_time(os.getpid())}-{next(_seq)}"
        self.netns = f"{self.run_id}-lan"
        self.hosts = {}
        self._netns = []
        self._addresses = iter(list(self.network.hosts())[9:])
        self.state_dir = None
        self.procs = procs if procs is not None else ProcessGroup(log_dir=log_dir)
        self.closed = False
        self.strays = []
        self._open()

    def _open(self):
        sweep_stale()
        _open_lans.add(self)
        _install_signal_handlers()
        try:
            self.state_dir = os.path.join(STATE_ROOT, self.run_id)
            os.makedirs(self.state_dir, mode=0o700)
            _checked(["ip", "netns", "add", self.netns])
            self._netns.append(self.netns)
            _checked(["ip", "-n", self.netns, "link", "set", "lo", "up"])
            _checked(["ip", "-n", self.netns, "link", "add", "br0", "type", "bridge"])
            _checked(["ip", "-n", self.netns, "link", "set", "br0", "up"])
            if self.procs.log_dir is None:
                logs = os.path.join(self.state_dir, "logs")
                os.makedirs(logs)
                self.procs.log_dir = logs
        except BaseException:
            self.close(check=False)
            raise

    def add_host(self, name, address=None, private=(), hide=RCM_INSTALLATION, empty=EMPTY_DIRS, fresh=()):
        """A new host ``name`` (lowercase letters and digits, at most 12) on this LAN; ``private`` lists
        directories whose content the host keeps to itself (``INSTALL_PATHS`` for an rcm-platform install).
        Below them, the host does not see the paths in ``hide`` (default: this machine's own rcm-platform
        installation) and sees the folders in ``empty`` empty (default: /etc/rc?.d). The folders in ``fresh``
        are replaced by empty ones of the host's own (``INSTALL_FRESH`` for an install: /opt and the
        rcm_platform package's dist-packages)."""
        if self.closed:
            raise RuntimeError("this LAN is closed")
        if not HOST_NAME.match(name) or name == "lan" or name in self.hosts:
            raise ValueError(f"bad or duplicate host name {name!r}")
        address = str(ipaddress.ip_address(address)) if address else str(next(self._addresses))
        if ipaddress.ip_address(address) not in self.network:
            raise ValueError(f"{address} is not in {self.network}")
        host = Host(self, name, len(self.hosts) + 1, address, private, hide, empty, fresh)
        self.hosts[name] = host
        try:
            host._create()
        except BaseException:
            self.close(check=False)
            raise
        return host

    def __getitem__(self, name):
        return self.hosts[name]

    def close(self, check=True):
        """Remove everything this LAN made. Every step runs even if an earlier one fails; with ``check``, raise
        afterwards if a child could not be stopped or a process the test left behind had to be killed."""
        if self.closed:
            return
        self.closed = True
        errors = []
        try:
            self.procs.stop_all()
        except BaseException as exc:  # noqa: keep cleaning
            errors.append(f"stopping children: {exc}")
        holders = [h.holder for h in self.hosts.values() if h.holder is not None]
        for proc in holders:
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        for proc in holders:
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                errors.append(f"holder {proc.pid} did not die")
        for netns in reversed(self._netns):
            try:
                strays = [(pid, comm) for pid, comm in _kill_netns_processes(netns)]
                if strays:
                    self.strays.extend(strays)
                    errors.append(f"processes left in {netns} (killed): {strays}")
            except BaseException as exc:  # noqa
                errors.append(f"killing processes in {netns}: {exc}")
            result = _ip_unchecked("netns", "del", netns)
            if result.returncode != 0 and netns in netns_names():
                errors.append(f"ip netns del {netns}: {result.stdout.strip()}")
        for proc in holders:
            if group_alive(proc.pid):
                errors.append(f"holder group {proc.pid} still alive")
        if self.state_dir:
            shutil.rmtree(self.state_dir, ignore_errors=True)
            if os.path.exists(self.state_dir):
                errors.append(f"could not remove {self.state_dir}")
        _open_lans.discard(self)
        if not _open_lans:
            _restore_signal_handlers()
        if check and errors:
            raise AssertionError("LAN teardown: " + "; ".join(errors))

    def leftovers(self):
        """What of this LAN still exists on the machine (empty after ``close``)."""
        left = [n for n in netns_names() if n.startswith(self.run_id + "-")]
        if self.state_dir and os.path.exists(self.state_dir):
            left.append(self.state_dir)
        left += [f"holder {h.holder.pid}" for h in self.hosts.values()
                 if h.holder is not None and h.holder.poll() is None]
        return left

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        # on an exception, clean without masking it; otherwise report a dirty teardown
        self.close(check=exc_type is None)
