"""Clear failures of every ``rcmp_n`` command (the agent, ``vpn init|client|revoke|list``, ``token
add|list|revoke``): one exit status convention (0 done, 1 could not be done, 2 bad usage or configuration, 3 a
missing package), one line on stderr, no traceback, each wrong kind of platform folder named, and a missing
module named with the package that installs it.

Missing modules are real import failures of a real child: ``python3 -S`` (a Python that does not see the
system's packages, as a pyenv or venv Python first on PATH), the pyenv Python of this machine when there is one,
and a ``sitecustomize`` that makes chosen modules unimportable for one child (a package cannot be uninstalled
for a test).
"""

import os
import shutil
import subprocess
import tempfile

import pytest

from tests.support.paths import REPO

PYTHON = "/usr/bin/python3"
TOKEN = ["token", "add", "ops", "--role", "admin"]
COMMANDS = {   # every rcmp_n command, as a user types it (after --home DIR)
    "agent": [],
    "vpn init": ["vpn", "init", "--remote", "203.0.113.1"],
    "vpn client": ["vpn", "client", "robot1"],
    "vpn revoke": ["vpn", "revoke", "robot1"],
    "vpn list": ["vpn", "list"],
    "token add": TOKEN,
    "token list": ["token", "list"],
    "token revoke": ["token", "revoke", "ops"],
}

BLOCKER = '''
import sys
BLOCKED = {blocked!r}


class _Blocked:
    """Makes the modules of BLOCKED unimportable, as if their packages were not installed."""

    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
        return None


sys.meta_path.insert(0, _Blocked())
'''


def rcmp_n(home, *args, python=(PYTHON,), env=None, user=None):
    """``python -m rcm_platform --home HOME ARGS`` as a child (as ``user`` with setpriv when given)."""
    environ = dict(os.environ, PYTHONPATH=os.pathsep.join([REPO, os.environ.get("PYTHONPATH", "")]).rstrip(":"),
                   PATH="/usr/bin:/bin:/usr/sbin:/sbin")
    environ.update(env or {})
    argv = [*python, "-m", "rcm_platform", "--home", str(home), *args]
    if user is not None:
        argv = ["setpriv", f"--reuid={user}", "--regid=nogroup", "--clear-groups", *argv]
    return subprocess.run(argv, capture_output=True, text=True, timeout=60, env=environ, cwd="/")


def one_line(result):
    assert result.stdout == "", result.stdout
    assert result.stderr.count("\n") == 1 and result.stderr.endswith("\n"), result.stderr
    assert "Traceback" not in result.stderr
    return result.stderr.rstrip("\n")


def snapshot(home):
    """Every file below ``home`` but the agent's log, with its content."""
    found = {}
    for folder, dirs, files in os.walk(home):
        dirs[:] = [d for d in dirs if os.path.join(folder, d) != os.path.join(str(home), "log")]
        for name in files:
            with open(os.path.join(folder, name), "rb") as f:
                found[os.path.relpath(os.path.join(folder, name), home)] = f.read()
    return found


def blocking(tmp_path, *modules):
    """The environment of a child in which ``modules`` cannot be imported."""
    folder = tmp_path / "blocked"
    folder.mkdir(exist_ok=True)
    (folder / "sitecustomize.py").write_text(BLOCKER.format(blocked=set(modules)))
    return {"PYTHONPATH": os.pathsep.join([str(folder), REPO, os.environ.get("PYTHONPATH", "")]).rstrip(":")}


@pytest.fixture
def master_home(tmp_path):
    """A master's platform folder with a VPN (robot1 issued) and an RDAPI token."""
    home = tmp_path / "master"
    home.mkdir()
    (home / ".init.cfg").write_text("[main]\nvpn_address=127.0.0.1\next_address=127.0.0.1\n")
    for args in (COMMANDS["vpn init"], COMMANDS["vpn client"], TOKEN):
        assert rcmp_n(home, *args).returncode == 0
    return home


@pytest.fixture
def shared_folder():
    """A folder that user nobody may enter (pytest's own temporary folders are root's, mode 0700)."""
    folder = tempfile.mkdtemp(prefix="rcmp-exit-")
    os.chmod(folder, 0o755)
    yield folder
    shutil.rmtree(folder)


# -- 2: the platform folder, each wrong kind named ------------------------------------------------------------

@pytest.mark.parametrize("command", sorted(COMMANDS))
@pytest.mark.parametrize("home,problem", [
    ("/etc/passwd", "the platform folder is a file, not a folder"),
    ("/dev/null", "the platform folder is a character device, not a folder"),
    ("/etc/passwd/rcm", "the platform folder cannot exist: /etc/passwd is a file, not a folder"),
    ("/nonexistent/rcm-platform", "the platform folder does not exist"),
])
def test_every_command_names_the_wrong_kind_of_platform_folder_and_exits_2(command, home, problem):
    result = rcmp_n(home, *COMMANDS[command])
    assert result.returncode == 2, result.stderr
    assert one_line(result).endswith(f"{home}: {problem}")


def _as_nobody(shared_folder, mode, command):
    """``command`` run by user nobody in a master's platform folder of root's with ``mode``."""
    home = os.path.join(shared_folder, "home")
    os.mkdir(home, mode)
    with open(os.path.join(home, ".init.cfg"), "w") as f:
        f.write("[main]\nvpn_address=127.0.0.1\next_address=127.0.0.1\n")
    result = rcmp_n(home, *COMMANDS[command], user="nobody")
    assert result.returncode == 2, result.stderr
    return home, one_line(result)


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_a_folder_that_user_nobody_may_not_read_is_named_with_its_owner_and_mode(shared_folder, command):
    home, line = _as_nobody(shared_folder, 0o700, command)
    assert line.endswith(f"{home}: the platform folder cannot be read by user nobody (owner root, mode 0700)")


@pytest.mark.parametrize("command", ["agent", "vpn init", "token add", "token revoke"])
def test_a_folder_these_commands_must_write_and_cannot_is_named_and_nothing_is_written(shared_folder, command):
    home, line = _as_nobody(shared_folder, 0o755, command)
    assert line.endswith(f"{home}: the platform folder cannot be written by user nobody (owner root, mode 0755)")
    assert os.listdir(home) == [".init.cfg"]


def test_a_robots_log_folder_that_is_a_file_is_named(tmp_path):
    home = tmp_path / "robot"
    home.mkdir()
    (home / "init.cfg").write_text("[main]\nname=robot1\nvpn_address=127.0.0.1\nip_master=127.0.0.1\n")
    (home / "log").write_text("not a folder")
    result = rcmp_n(home)
    assert result.returncode == 2
    assert one_line(result) == f"rcmp_n: {home}/log: the agent's log folder is a file, not a folder"


@pytest.mark.parametrize("command", ["vpn init", "vpn client", "vpn revoke", "vpn list", "token add",
                                     "token list", "token revoke"])
def test_master_commands_in_a_robots_folder_exit_2(tmp_path, command):
    home = tmp_path / "robot"
    home.mkdir()
    (home / "init.cfg").write_text("[main]\nname=robot1\nvpn_address=127.0.0.1\n")
    result = rcmp_n(home, *COMMANDS[command])
    assert result.returncode == 2, result.stderr
    line = one_line(result)
    assert "runs on the master" in line or "belong to the master" in line, line
    assert sorted(os.listdir(home)) == ["init.cfg"]


def test_usage_errors_exit_2_for_every_command(master_home):
    for args in (["--frobnicate"], ["vpn", "init", "--port", "0"], ["vpn", "client", "bad-name"],
                 ["vpn", "revoke"], ["token", "add", "x", "--role", "root"], ["token", "add", "../x", "--role",
                                                                              "read"]):
        result = rcmp_n(master_home, *args)
        assert result.returncode == 2, (args, result.stderr)
        assert "Traceback" not in result.stderr


def test_every_commands_help_lists_the_exit_statuses(tmp_path):
    for args in ([], ["vpn"], ["vpn", "init"], ["vpn", "client"], ["vpn", "revoke"], ["vpn", "list"], ["token"],
                 ["token", "add"], ["token", "list"], ["token", "revoke"]):
        result = rcmp_n(tmp_path, *args, "--help")
        assert result.returncode == 0, (args, result.stderr)
        text = " ".join(result.stdout.split())
        assert "Exit status: 0 done" in text and "2 bad usage or configuration" in text, args
        assert "3 a package the command needs is not installed" in text, args


# -- 1: asked rightly, but it cannot be done now --------------------------------------------------------------

@pytest.mark.parametrize("args,message", [
    (["vpn", "init", "--remote", "203.0.113.1"], "a VPN already exists"),
    (["vpn", "revoke", "robot9"], "no VPN certificate was issued to 'robot9'"),
    (TOKEN, "already exists"),
    (["token", "revoke", "nobody"], "no token named 'nobody'"),
])
def test_what_cannot_be_done_now_exits_1(master_home, args, message):
    result = rcmp_n(master_home, *args)
    assert result.returncode == 1, result.stderr
    assert message in one_line(result)


def test_every_command_exits_0_when_done(master_home):
    for args in (["vpn", "list"], ["vpn", "revoke", "robot1"], ["token", "list"], ["token", "revoke", "ops"]):
        result = rcmp_n(master_home, *args)
        assert result.returncode == 0, (args, result.stderr)


# -- 3: a missing package, named for this system --------------------------------------------------------------

def test_help_on_a_python_that_does_not_see_the_systems_packages_is_one_line_exit_3():
    result = rcmp_n("/nonexistent", "--help", python=(PYTHON, "-S"))
    assert result.returncode == 3
    line = one_line(result)
    assert line.startswith("rcmp_n: Twisted (Python module 'twisted') is not available to ")
    assert "run '/usr/bin/python3 -m rcm_platform' instead (python3-twisted is installed for it)" in line


def _pyenv_python():
    root = subprocess.run(["pyenv", "root"], capture_output=True, text=True).stdout.strip() \
        if shutil.which("pyenv") else ""
    versions = sorted(os.listdir(os.path.join(root, "versions"))) if root and os.path.isdir(
        os.path.join(root, "versions")) else []
    for version in reversed(versions):
        path = os.path.join(root, "versions", version, "bin", "python3")
        if version.startswith("3.1") and os.path.exists(path):
            return path
    return None


@pytest.mark.skipif(_pyenv_python() is None, reason="no pyenv Python 3.10+ on this machine")
def test_help_with_pyenvs_python_first_on_path_names_the_system_python():
    """The README's own form, ``python3 -m rcm_platform --help``, with the pyenv shim's Python first on PATH."""
    python = _pyenv_python()
    result = rcmp_n("/nonexistent", "--help", python=(python,))
    assert result.returncode == 3
    assert f"is not available to {python}" in one_line(result)
    assert "python3-twisted" in result.stderr


@pytest.mark.parametrize("command,module,package", [
    ("agent", "twisted", "python3-twisted"),
    ("agent", "roslaunch", "python3-roslaunch"),
    ("agent", "rospkg", "python3-rospkg"),
    ("vpn init", "cryptography", "python3-cryptography"),
    ("vpn client", "cryptography", "python3-cryptography"),
    ("vpn list", "twisted", "python3-twisted"),
    ("token add", "twisted", "python3-twisted"),
    ("token list", "zope", "python3-zope.interface"),
])
def test_a_missing_module_is_one_line_naming_its_debian_package_exit_3(tmp_path, master_home, command, module,
                                                                       package):
    before = snapshot(master_home)
    args = COMMANDS[command] + (["--force"] if command == "vpn init" else [])   # this folder has a VPN
    result = rcmp_n(master_home, *args, env=blocking(tmp_path, module))
    assert result.returncode == 3, result.stderr
    line = one_line(result)
    assert f"(Python module '{module}') is missing" in line
    assert f"install it with 'sudo apt-get install {package}' (Debian GNU/Linux 12 (bookworm))" in line
    assert snapshot(master_home) == before          # the agent may have begun its log: nothing else


def test_an_rdapi_over_https_needs_pyopenssl_and_says_so_at_start(tmp_path):
    home = tmp_path / "master"
    home.mkdir()
    (home / ".init.cfg").write_text("[main]\nvpn_address=127.0.0.1\next_address=127.0.0.1\n"
                                    "rdapi_tls_cert=/etc/rcm/rdapi.crt\nrdapi_tls_key=/etc/rcm/rdapi.key\n")
    result = rcmp_n(home, env=blocking(tmp_path, "OpenSSL"))
    assert result.returncode == 3
    assert "pyOpenSSL (Python module 'OpenSSL') is missing: install it with 'sudo apt-get install python3-openssl'" \
        in one_line(result)
    assert not (home / "robotics_data.db").exists()


def test_netifaces_is_needed_only_to_look_an_interface_up(tmp_path):
    home = tmp_path / "master"
    home.mkdir()
    (home / ".init.cfg").write_text("[main]\next_address=127.0.0.1\n")   # the VPN address from tun0's
    result = rcmp_n(home, env=blocking(tmp_path, "netifaces"))
    assert result.returncode == 3
    assert "'sudo apt-get install python3-netifaces'" in one_line(result)
    robot = tmp_path / "robot"
    robot.mkdir()
    (robot / "init.cfg").write_text("[main]\nname=robot1\n")   # ip_master from the VPN address: netifaces
    result = rcmp_n(robot, env=blocking(tmp_path, "netifaces"))
    assert result.returncode == 3
    assert "python3-netifaces" in one_line(result)
    # with both addresses given it is not needed: the agent goes on, to the next problem (a certificate)
    (home / ".init.cfg").write_text("[main]\nvpn_address=127.0.0.1\next_address=127.0.0.1\n"
                                    "rdapi_tls_cert=/nonexistent.crt\nrdapi_tls_key=/nonexistent.key\n")
    result = rcmp_n(home, env=blocking(tmp_path, "netifaces"))
    assert result.returncode == 2, result.stderr
    assert "rdapi_tls_cert" in one_line(result) and "python3-netifaces" not in result.stderr
