"""A real installation, as root, of our zips into this machine, and the seed guide's checks against it.

The master goes to the real places issue 6 names (/usr/local/bin/rcmp_n, the rcm_platform package in
/usr/bin/python3's dist-packages, /opt/rcm-platform, /etc/init.d/rcmpd + /etc/default/rcmpd and the update-rc.d
links), non-interactively, on loopback (ext_address and vpn_address 127.0.0.1, free ext_port and ic_port), with the
installing user's HOME (and so ~/rcmp_ws) in a temporary folder. Anything of a real installation found there is
moved aside first (a running daemon stopped) and put back afterwards; everything the test placed is removed even
when it fails. The robot zip is installed next to the master with the (ext) options for another platform folder,
program folder, package folder, workspace and init script name, and must pair with that master.
"""

import glob
import json
import os
import shutil
import signal
import subprocess
import urllib.request
import zipfile

import pytest

from tests.support.paths import REPO
from tests.support.polling import wait_until
from tests.support.ports import stable_free_ports

ROOT = REPO
PYTHON = "/usr/bin/python3"
USER_PATH = "/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"

pytestmark = [
    pytest.mark.skipif(os.geteuid() != 0, reason="installs into the system: needs root"),
    pytest.mark.skipif(not (shutil.which("service") or os.path.exists("/usr/sbin/service"))
                       or not os.path.exists("/usr/sbin/update-rc.d"), reason="needs service and update-rc.d"),
]


def system_site():
    out = subprocess.run([PYTHON, "-c", "import site; print(site.getsitepackages()[0])"],
                         capture_output=True, text=True, check=True)
    return out.stdout.strip()


BIN = "/usr/local/bin/rcmp_n"
LIB = os.path.join(system_site(), "rcm_platform")
HOME = "/opt/rcm-platform"


def service_paths(name):
    """The system files an installation with init script NAME places (update-rc.d links included)."""
    return ([f"/etc/init.d/{name}", f"/etc/default/{name}", f"/run/{name}.pid"]
            + sorted(glob.glob(f"/etc/rc[0-6S].d/[SK][0-9][0-9]{name}")))


def rc_links(name):
    return sorted(glob.glob(f"/etc/rc[0-6S].d/[SK][0-9][0-9]{name}"))


def run(argv, env=None, timeout=300, check=True, **kwargs):
    result = subprocess.run([str(a) for a in argv], capture_output=True, text=True, env=env, timeout=timeout,
                            **kwargs)
    if check:
        assert result.returncode == 0, (f"{' '.join(map(str, argv))} exited {result.returncode}\n"
                                        f"stdout:\n{result.stdout}\nstderr:\n{result.stderr}")
    return result


def service(name, action, check=False):
    return run(["/usr/sbin/service", name, action], env={"PATH": USER_PATH, "LANG": "C"}, timeout=120,
               check=check)


def agent_processes(programs=(BIN,)):
    """pid -> argv of every living process running one of the installed rcmp_n ``programs`` on this machine
    (processes of test hosts, which have mount namespaces of their own, are other machines' agents)."""
    found = {}
    own_mnt = os.readlink("/proc/self/ns/mnt")
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            if os.readlink(f"/proc/{entry}/ns/mnt") != own_mnt:
                continue
            with open(f"/proc/{entry}/cmdline", "rb") as f:
                argv = [a.decode("utf-8", "replace") for a in f.read().split(b"\0") if a]
        except OSError:
            continue
        if argv and any(a in programs for a in argv[:2]):
            found[int(entry)] = argv
    return found


def process_env(pid):
    with open(f"/proc/{pid}/environ", "rb") as f:
        return dict(item.decode().split("=", 1) for item in f.read().split(b"\0") if b"=" in item)


def listening(address, port):
    out = run(["ss", "-ltnH"], timeout=30).stdout
    return any(line.split()[3] == f"{address}:{port}" for line in out.splitlines() if len(line.split()) > 3)


def curl(url):
    return run(["curl", "-s", "-S", "--max-time", "5", url], timeout=30, check=False)


def http_json(url, body=None):
    data = json.dumps(body).encode() if body is not None else None
    request = urllib.request.Request(url, data=data, headers={"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(request, timeout=10) as response:
            return response.status, json.loads(response.read())
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read() or b"null")


class SystemSlot:
    """Makes room for the test's installations and restores the machine afterwards, whatever happens."""

    def __init__(self, backup_dir):
        self.backup_dir = backup_dir
        self.moved = []
        self.restart_after = []
        self.services = []

    def claim(self, name, extra_paths=()):
        """Move aside what an installation with init script ``name`` (and extra_paths) would overwrite."""
        self.services.append(name)
        init = f"/etc/init.d/{name}"
        if os.path.exists(init) and run([init, "status"], check=False, timeout=60).returncode == 0:
            run([init, "stop"], timeout=120)
            self.restart_after.append(name)
        for path in service_paths(name) + list(extra_paths):
            if os.path.lexists(path):
                target = os.path.join(self.backup_dir, str(len(self.moved)))
                shutil.move(path, target)
                self.moved.append((path, target))

    def clean(self, name, paths):
        """Stop the daemon ``name`` this test may have started and remove everything at ``paths``."""
        errors = []
        init = f"/etc/init.d/{name}"
        if os.path.exists(init):
            result = run([init, "stop"], check=False, timeout=120)
            if result.returncode != 0:
                errors.append(f"{init} stop: {result.stderr.strip()}")
        pidfile = f"/run/{name}.pid"
        if os.path.exists(pidfile):
            try:
                pid = int(open(pidfile).read().strip())
                os.killpg(pid, signal.SIGKILL)  # the daemon is its own session leader
                errors.append(f"{name} had to be killed")
            except (ValueError, ProcessLookupError, PermissionError):
                pass
        run(["/usr/sbin/update-rc.d", "-f", name, "remove"], check=False, timeout=60)
        for path in service_paths(name) + list(paths):
            if os.path.isdir(path) and not os.path.islink(path):
                shutil.rmtree(path, ignore_errors=True)
            elif os.path.lexists(path):
                os.remove(path)
        return errors

    def restore(self):
        for path, target in reversed(self.moved):
            if os.path.lexists(path):
                if os.path.isdir(path) and not os.path.islink(path):
                    shutil.rmtree(path)
                else:
                    os.remove(path)
            os.makedirs(os.path.dirname(path), exist_ok=True)
            shutil.move(target, path)
        for name in self.restart_after:
            run([f"/etc/init.d/{name}", "start"], check=False, timeout=120)


@pytest.fixture
def slot(tmp_path):
    backup = tmp_path / "backup"
    backup.mkdir()
    s = SystemSlot(str(backup))
    s.claim("rcmpd", extra_paths=[BIN, LIB, HOME])
    cleanups = []
    s.add_cleanup = cleanups.append
    try:
        yield s
    finally:
        errors = []
        for name, paths in reversed(cleanups):
            errors += s.clean(name, paths)
        errors += s.clean("rcmpd", [BIN, LIB, HOME])
        s.restore()
        assert not agent_processes(), f"rcmp_n processes left: {agent_processes()}"
        assert not errors, "; ".join(errors)


def build_zip(tmp_path, package=None):
    out = tmp_path / "dist"
    result = run([PYTHON, os.path.join(ROOT, "create_robotics_pkg")] + ([package] if package else [])
                 + ["-o", out], timeout=120)
    path = out / ZIP_NAMES[package]
    assert path.exists(), result.stdout
    return unpack_zip(path, tmp_path / "unpacked")


ZIP_NAMES = {None: "robotics.zip", "master": "rcm_platform_master.zip", "robot": "rcm_platform_robot.zip"}


def unpack_zip(path, unpacked):
    """Unpack an agent zip into the folder ``unpacked`` as unzip would; returns its package folder."""
    with zipfile.ZipFile(path) as zf:
        zf.extractall(unpacked)
        for info in zf.infolist():  # zipfile does not restore permissions: as unzip would
            mode = (info.external_attr >> 16) & 0o777
            if mode:
                os.chmod(unpacked / info.filename, mode)
    return unpacked / ("rcm_platform_robot" if path.name == ZIP_NAMES["robot"] else "rcm_platform_master")


def user_env(home):
    """A fresh login's environment of the installing user (no pyenv, no sourced workspace)."""
    return {"PATH": USER_PATH, "HOME": str(home), "LANG": "C", "USER": "root", "LOGNAME": "root"}


def master_up(ext_port):
    def check():
        result = curl(f"http://127.0.0.1:{ext_port}/")
        return result.returncode == 0 and result.stdout
    return wait_until(check, timeout=30, message=f"the RDAPI on 127.0.0.1:{ext_port}")


def log_tail(home, lines=40):
    text = ""
    for name in ("rcmpd.out", "rcmp.log"):
        try:
            with open(os.path.join(str(home), "log", name), errors="replace") as f:
                text += f"--- {name}\n" + "".join(f.readlines()[-lines:])
        except OSError as exc:
            text += f"--- {name}: {exc.strerror}\n"
    return text


def assert_nothing_left(ws, service_name="rcmpd", paths=(BIN, LIB, HOME)):
    left = [p for p in list(paths) + service_paths(service_name) + [str(ws)] if os.path.lexists(p)]
    assert not left, f"uninstall.sh left {left}"
    assert not rc_links(service_name)


def test_master_installation_seed_checks_and_uninstallation(tmp_path, slot):
    pkg = build_zip(tmp_path)  # robotics.zip: the master with FIWARE support
    user = tmp_path / "user"
    user.mkdir()
    ws = user / "rcmp_ws"
    ext_port, ic_port = stable_free_ports(2)
    install = [pkg / "install.sh", "--non-interactive", "--ext-address", "127.0.0.1", "--ext-port", ext_port,
               "--vpn-address", "127.0.0.1", "--ic-port", ic_port, "--no-vpn"]

    result = run(install, env=user_env(user), cwd=pkg)
    assert "Dependencies:" in result.stdout  # the apt-get step ran (and found everything installed)

    # -- the seed's "Installation files" ------------------------------------------------------------------------
    assert os.access(BIN, os.X_OK)
    with open(BIN) as f:
        assert f.readline().strip() == "#!/usr/bin/python3"
    modules = sorted(n for n in os.listdir(LIB) if n.endswith(".py"))
    assert modules == sorted(n for n in os.listdir(pkg / "rcm_platform") if n.endswith(".py"))
    assert "rcmp_ext_connector.py" in modules and "rcmp_robotics_data.py" in modules
    assert sorted(os.listdir(os.path.join(LIB, "console"))) == sorted(os.listdir(pkg / "rcm_platform" / "console"))
    config = open(os.path.join(HOME, ".init.cfg")).read()
    assert "inbound_open_ports=10100, 10101, 10102, 10103" in config
    assert f"ext_port={ext_port}" in config and f"ic_port={ic_port}" in config
    assert not os.path.exists(os.path.join(HOME, "init.cfg"))
    assert open(os.path.join(HOME, "rosconsole.config")).read() == open(pkg / "ros" / "rosconsole.config").read()
    assert os.access("/etc/init.d/rcmpd", os.X_OK) and rc_links("rcmpd")
    for package in ("firos", "rcm", "robotics_msgs"):
        assert (ws / "src" / package / "package.xml").is_file()
    assert (ws / "devel" / "setup.bash").is_file()

    # -- "Sanity check procedures" and "End to End testing" ---------------------------------------------------
    status = service("rcmpd", "status")
    assert (status.returncode, status.stdout.strip()) == (0, "/usr/local/bin/rcmp_n is running")
    assert master_up(ext_port) == "<html><body>Welcome to the RCM platform node server!</body></html>"
    read = curl(f"http://127.0.0.1:{ext_port}/platform_instance/read")
    assert json.loads(read.stdout) == {"reason": [], "result": "OK"}
    assert "<title>RCM platform console</title>" in curl(f"http://127.0.0.1:{ext_port}/console/").stdout

    # -- "List of Running Processes": one rcmp_n (one reactor serves the RDAPI and the agent protocol) ---------
    agents = agent_processes()
    assert len(agents) == 1, agents
    (pid, argv), = agents.items()
    assert argv[:2] == ["/usr/bin/python3", BIN]
    assert open("/run/rcmpd.pid").read().strip() == str(pid)
    env = process_env(pid)
    # rcmpd sources nothing of the workspace (issue 12): the agent gets its path and makes the overlay itself
    assert env["RCMP_WS"] == str(ws) and "ROS_PACKAGE_PATH" not in env
    assert env["ROSCONSOLE_CONFIG_FILE"] == os.path.join(HOME, "rosconsole.config")
    assert f"workspace {ws} (owner uid 0): root's alone" in open(os.path.join(HOME, "log", "rcmp.log")).read()

    # -- "Network interfaces Up & Open" -------------------------------------------------------------------------
    assert listening("127.0.0.1", ext_port) and listening("127.0.0.1", ic_port)

    # -- "Databases": readable without writing -------------------------------------------------------------------
    db = os.path.join(HOME, "robotics_data.db")
    tables = run(["sqlite3", "-readonly", db, ".tables"], timeout=30).stdout.split()
    assert {"platform_instance", "service_logic"} <= set(tables)
    count = run(["sqlite3", "-readonly", db, "SELECT count(*) FROM platform_instance;"], timeout=30)
    assert count.stdout.strip().isdigit()
    write = run(["sqlite3", "-readonly", db, "DELETE FROM service_logic;"], timeout=30, check=False)
    assert write.returncode != 0 and "readonly" in write.stderr
    assert oct(os.stat(db).st_mode & 0o777) == "0o640" and os.stat(db).st_uid == 0  # not world-readable

    # -- running the wizard again changes the configuration, keeps an administrator's own keys, is safe ---------
    with open(os.path.join(HOME, ".init.cfg"), "a") as f:
        f.write("log_max_bytes=1024\n")
    again = run(install + ["--replace-ws", "no", "--inbound-ports", "10200, 10201"], env=user_env(user), cwd=pkg)
    assert "Building the workspace" not in again.stdout  # kept as it was
    config = open(os.path.join(HOME, ".init.cfg")).read()
    assert "inbound_open_ports=10200, 10201" in config and "log_max_bytes=1024" in config
    new_pid = wait_until(lambda: [p for p in agent_processes() if p != pid], timeout=30,
                         message="the restarted agent")
    assert len(agent_processes()) == 1 and new_pid[0] != pid
    master_up(ext_port)
    assert service("rcmpd", "status").returncode == 0

    # -- "Diagnosis procedures": /opt/rcm-platform/log/rcmp.log rolls over at its size, keeping 5 ---------------
    log_dir = os.path.join(HOME, "log")
    for i in range(150):  # each provisioning is logged (refused ones are rate-limited in the log: not those)
        assert http_json(f"http://127.0.0.1:{ext_port}/platform_instance/provisioning",
                         {"pi_name": f"r{i}", "pi_service_logic": "empty"})[0] == 200
    wait_until(lambda: os.path.exists(os.path.join(log_dir, "rcmp.log.5")), timeout=20, message="rcmp.log.5")
    rotated = sorted(n for n in os.listdir(log_dir) if n.startswith("rcmp.log"))
    assert rotated == ["rcmp.log"] + [f"rcmp.log.{i}" for i in range(1, 6)]

    # -- stop, status, uninstall -------------------------------------------------------------------------------
    stop = service("rcmpd", "stop")
    assert stop.returncode == 0, stop.stderr
    assert not agent_processes()
    status = service("rcmpd", "status")
    assert (status.returncode, status.stdout.strip()) == (3, "/usr/local/bin/rcmp_n is not running")
    assert not os.path.exists("/run/rcmpd.pid")
    assert not listening("127.0.0.1", ext_port)

    result = run([pkg / "uninstall.sh"], env=user_env(user), cwd=pkg)
    assert "package dependencies kept" in result.stdout
    assert_nothing_left(ws)
    assert shutil.which("catkin_make", path=USER_PATH) and shutil.which("sqlite3", path=USER_PATH)


def test_robot_installed_next_to_the_master_pairs_with_it(tmp_path, slot):
    robot_service = f"rcmpdtest{os.getpid()}"
    robot_dir = tmp_path / "robot"
    robot_paths = {"home": robot_dir / "opt", "bin": robot_dir / "bin", "lib": robot_dir / "lib",
                   "ws": robot_dir / "rcmp_ws"}
    slot.claim(robot_service)
    slot.add_cleanup((robot_service, [str(p) for p in robot_paths.values()]))

    master_pkg = build_zip(tmp_path / "m", "master")
    robot_pkg = build_zip(tmp_path / "r", "robot")
    user = tmp_path / "user"
    user.mkdir()
    ext_port, ic_port, ros_port = stable_free_ports(3)

    run([master_pkg / "install.sh", "-n", "--ext-address", "127.0.0.1", "--ext-port", ext_port,
         "--vpn-address", "127.0.0.1", "--ic-port", ic_port, "--ros-port-base", ros_port, "--no-vpn"],
        env=user_env(user), cwd=master_pkg)
    assert not (user / "rcmp_ws" / "src" / "firos").exists()  # the master zip carries no FIWARE packages
    base = f"http://127.0.0.1:{ext_port}"
    master_up(ext_port)
    assert http_json(f"{base}/service_logic/provisioning",
                     {"slg_name": "install_test", "sn_list": [], "sl_list": []})[1]["result"] == "OK"
    assert http_json(f"{base}/platform_instance/provisioning",
                     {"pi_name": "robot1", "pi_service_logic": "install_test"})[1]["result"] == "OK"

    run([robot_pkg / "install.sh", "-n", "--name", "robot1", "--ip-master", "127.0.0.1",
         "--vpn-address", "127.0.0.2", "--ic-port", ic_port, "--home", robot_paths["home"],
         "--bin-dir", robot_paths["bin"], "--lib-dir", robot_paths["lib"], "--workspace", robot_paths["ws"],
         "--service-name", robot_service], env=user_env(user), cwd=robot_pkg)
    robot_modules = sorted(n for n in os.listdir(robot_paths["lib"] / "rcm_platform") if n.endswith(".py"))
    assert robot_modules == sorted(os.listdir(robot_pkg / "rcm_platform"))
    assert not (robot_paths["lib"] / "rcm_platform" / "console").exists()
    assert "rcmp_ext_connector.py" not in robot_modules and "rcmp_robotics_data.py" not in robot_modules
    robot_bin = str(robot_paths["bin"] / "rcmp_n")
    status = service(robot_service, "status")
    assert (status.returncode, status.stdout.strip()) == (0, f"{robot_bin} is running")
    assert len(agent_processes((BIN, robot_bin))) == 2  # one process per agent
    (robot_pid,) = agent_processes((robot_bin,))
    # the robot imports its own rcm_platform (no RDAPI), not the master's in the system dist-packages
    assert process_env(robot_pid)["PYTHONPATH"].split(":")[0] == str(robot_paths["lib"])

    def robot_row():
        rows = http_json(f"{base}/platform_instance/read")[1]["reason"]
        return next((r for r in rows if r["pi_name"] == "robot1"), None)

    try:
        wait_until(lambda: (robot_row() or {}).get("paired"), timeout=60, message="robot1 to pair with the master")
    except AssertionError as exc:
        raise AssertionError(f"{exc}; robot1: {robot_row()}\nmaster log:\n{log_tail(HOME)}\n"
                             f"robot log:\n{log_tail(robot_paths['home'])}") from None
    assert robot_row()["connected"] is True
    space = http_json(f"{base}/service_space/read?ss_name=robot1")
    assert space[0] == 200, space

    # the robot leaves: its daemon stops, its uninstallation removes what it placed
    run([robot_pkg / "uninstall.sh", "--service-name", robot_service], env=user_env(user), cwd=robot_pkg)
    assert_nothing_left(robot_paths["ws"], robot_service,
                        paths=[robot_bin, str(robot_paths["lib"] / "rcm_platform"), str(robot_paths["home"])])
    wait_until(lambda: robot_row() and not robot_row()["connected"], timeout=60,
               message="the master to see robot1 gone")
    assert len(agent_processes((BIN, robot_bin))) == 1

    run([master_pkg / "uninstall.sh"], env=user_env(user), cwd=master_pkg)
    assert_nothing_left(user / "rcmp_ws")
    assert not agent_processes()


def test_rcmpd_reports_start_failures_stale_pid_files_and_double_starts(tmp_path, slot):
    """The init script's answers, on an (ext) installation in temporary places under its own name."""
    name = f"rcmpdtest{os.getpid()}"
    places = {"home": tmp_path / "opt", "bin": tmp_path / "bin", "lib": tmp_path / "lib", "ws": tmp_path / "ws"}
    slot.claim(name)
    slot.add_cleanup((name, [str(p) for p in places.values()]))
    pkg = build_zip(tmp_path / "m", "master")
    user = tmp_path / "user"
    user.mkdir()
    ext_port, ic_port = stable_free_ports(2)
    run([pkg / "install.sh", "-n", "--skip-deps", "--start", "no", "--no-vpn", "--ext-address", "127.0.0.1",
         "--ext-port", ext_port, "--vpn-address", "127.0.0.1", "--ic-port", ic_port, "--home", places["home"],
         "--bin-dir", places["bin"], "--lib-dir", places["lib"], "--workspace", places["ws"],
         "--service-name", name], env=user_env(user), cwd=pkg)
    program = str(places["bin"] / "rcmp_n")
    with open(f"/etc/init.d/{name}") as f:
        assert f"# Provides:          {name}\n" in f.read()
    status = service(name, "status")
    assert (status.returncode, status.stdout.strip()) == (3, f"{program} is not running")

    # a configuration the agent refuses: start fails and shows the agent's one line
    config = places["home"] / ".init.cfg"
    good = config.read_text()
    config.write_text(good + "ext_port=not-a-port\n")
    bad = service(name, "start")
    assert bad.returncode == 1
    assert "stopped right after starting" in bad.stderr and ".init.cfg" in bad.stderr
    assert service(name, "status").returncode == 3 and not agent_processes((program,))

    config.write_text(good)
    assert service(name, "start").returncode == 0
    master_up(ext_port)
    pids = list(agent_processes((program,)))
    again = service(name, "start")
    assert (again.returncode, again.stdout.strip()) == (0, f"{program} is already running")
    assert list(agent_processes((program,))) == pids

    # the agent dies behind the script's back: status says so, start recovers
    os.kill(pids[0], signal.SIGKILL)
    wait_until(lambda: not agent_processes((program,)), timeout=10, message="the killed agent to go")
    stale = service(name, "status")
    assert (stale.returncode, stale.stdout.strip()) == (1, f"{program} is not running (stale pid file /run/{name}.pid)")
    assert service(name, "start").returncode == 0
    master_up(ext_port)
    assert service(name, "restart").returncode == 0
    master_up(ext_port)
    assert service(name, "stop").returncode == 0
    assert not agent_processes((program,))
    stopped = service(name, "stop")
    assert (stopped.returncode, stopped.stdout.strip()) == (0, f"{program} is not running")
    usage = service(name, "reload-everything")
    assert usage.returncode == 2 and "Usage:" in usage.stderr

    run([pkg / "uninstall.sh", "--service-name", name], env=user_env(user), cwd=pkg)
    assert_nothing_left(places["ws"], name, paths=[program, str(places["lib"] / "rcm_platform"),
                                                   str(places["home"])])
