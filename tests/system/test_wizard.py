"""install.sh's wizard driven through its prompts, on a pseudo-terminal and with piped answers.

Every run uses --dry-run, which asks (or takes) every answer, prints the configuration file and the steps it
would take, and changes nothing; the real installation is tests/system/test_install.py. The package folder is made from
this tree's install.sh, with the marker that makes it a master (rcm_platform/rcmp_ext_connector.py) or not.
"""

import os
import pty
import select
import shutil
import subprocess
import time

import pytest

from tests.support.paths import REPO

ROOT = REPO
SEED_REPLACE_QUESTION = "The workspace rcmp_ws already exists: do you wanna replace it ([Y]es/no)?"
PORTS_QUESTION = "Inbound open ports, comma separated [10100, 10101, 10102, 10103]:"
FIWARE_QUESTION = "Do you want FIWARE support (firos, rcm_driver and robotics_msgs in the workspace)"
START_QUESTION = "Do you want to start the rcm daemon now ([Y]es/no)?"
ROBOT_QUESTION = "Is this machine a robot (no: a virtual machine on the server side)"
NAME_QUESTION = "Name of this platform instance (as provisioned on the master)"
MASTER_IP_QUESTION = "VPN address of the rcm master"
VPN_QUESTION = "Do you want the platform to create its own VPN (OpenVPN; no: you run the VPN yourself) ([Y]es/no)?"
VPN_CONFIG_QUESTION = ("OpenVPN client file of this machine, from 'rcmp_n vpn client NAME' on the master "
                       "(none: you run the VPN yourself)")


def make_package(base, role, component_zips=True):
    pkg = base / f"rcm_platform_{role}"
    (pkg / "rcm_platform").mkdir(parents=True)
    for script in ("install.sh", "sub_inst.sh"):  # sub_inst.sh finds the ROS installation and the dependencies
        shutil.copy(os.path.join(ROOT, script), pkg / script)
    (pkg / "rcm_platform" / "__init__.py").write_text("")
    if role == "master":
        (pkg / "rcm_platform" / "rcmp_ext_connector.py").write_text("")
        if component_zips:
            for z in ("firos.zip", "rcm_driver.zip", "robotics_msgs.zip"):
                (pkg / z).write_bytes(b"")
    return pkg


class Setup:
    """A user's home with an existing ~/rcmp_ws, a platform folder path, and an unpacked package."""

    def __init__(self, tmp_path, role, component_zips=True, existing_ws=True):
        self.home = tmp_path / "user"
        self.home.mkdir()
        if existing_ws:
            (self.home / "rcmp_ws" / "src").mkdir(parents=True)
        self.platform = tmp_path / "opt-rcm-platform"
        self.pkg = make_package(tmp_path, role, component_zips)
        self.env = {"PATH": "/usr/bin:/bin:/usr/sbin:/sbin", "HOME": str(self.home), "LC_ALL": "C"}

    def argv(self, *extra):
        return [str(self.pkg / "install.sh"), "--dry-run", "--home", str(self.platform),
                "--vpn-interface", "nosuch0", *extra]

    def run(self, answers="", *extra):
        return subprocess.run(self.argv(*extra), input=answers, capture_output=True, text=True, env=self.env,
                              timeout=60)

    def config_lines(self, stdout):
        """The configuration file the dry run would write (its key lines)."""
        lines = stdout.split("  - write ", 1)[1].splitlines()[1:]
        return [line.strip() for line in lines if line.startswith("    ") and not line.strip().startswith("#")]


class Terminal:
    """A child on a pseudo-terminal: read until a text shows, type lines."""

    def __init__(self, procs, argv, env):
        self.fd, slave = pty.openpty()
        try:
            self.proc = procs.start(argv, env=env, name="install.sh", stdin=slave, stdout=slave, stderr=slave)
        finally:
            os.close(slave)
        self.seen = ""
        self.pos = 0

    def expect(self, text, timeout=15.0):
        deadline = time.monotonic() + timeout
        while text not in self.seen[self.pos:]:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise AssertionError(f"{text!r} not shown; the terminal shows:\n{self.seen}")
            ready, _, _ = select.select([self.fd], [], [], remaining)
            if not ready:
                continue
            try:
                data = os.read(self.fd, 4096)
            except OSError:  # EIO: the child closed the terminal
                data = b""
            if not data:
                raise AssertionError(f"{text!r} not shown before the end; the terminal shows:\n{self.seen}")
            self.seen += data.decode("utf-8", "replace").replace("\r\n", "\n")
        self.pos = self.seen.index(text, self.pos) + len(text)

    def type(self, line):
        os.write(self.fd, line.encode() + b"\r")

    def finish(self, timeout=15.0):
        try:
            self.expect("\0never\0", timeout=timeout)
        except AssertionError:
            pass
        status = self.proc.wait(timeout=timeout)
        os.close(self.fd)
        return status


def test_master_wizard_on_a_terminal_takes_every_default_with_enter(tmp_path, procs):
    setup = Setup(tmp_path, "master")
    term = Terminal(procs, setup.argv(), setup.env)
    term.expect(SEED_REPLACE_QUESTION)
    term.type("")
    term.expect(FIWARE_QUESTION + " ([Y]es/no)?")
    term.type("")
    term.expect(PORTS_QUESTION)
    term.type("")
    term.expect(VPN_QUESTION)
    term.type("")
    term.expect(START_QUESTION)
    term.type("")
    term.expect("Dry run: nothing was changed.")
    assert term.finish() == 0
    out = term.seen
    assert (f"create the platform's VPN in {setup.platform}/vpn: subnet 10.11.12.0/24, UDP port 1194, "
            "remote the address of the external interface") in out
    assert f"replace the workspace {setup.home}/rcmp_ws" in out
    assert "unpack firos.zip rcm_driver.zip robotics_msgs.zip" in out
    assert "start the rcm daemon (rcmpd)" in out
    assert f"write {setup.platform}/.init.cfg" in out
    assert "inbound_open_ports=10100, 10101, 10102, 10103" in out
    assert not setup.platform.exists(), "a dry run must not create the platform folder"
    assert (setup.home / "rcmp_ws" / "src").is_dir(), "a dry run must not touch the workspace"


def test_robot_wizard_on_a_terminal_asks_again_after_wrong_answers(tmp_path, procs):
    setup = Setup(tmp_path, "robot")
    term = Terminal(procs, setup.argv(), setup.env)
    term.expect(SEED_REPLACE_QUESTION)
    term.type("perhaps")
    term.expect("Please answer yes or no.")
    term.expect(SEED_REPLACE_QUESTION)
    term.type("n")
    term.expect(ROBOT_QUESTION + " ([Y]es/no)?")
    term.type("")
    term.expect(NAME_QUESTION)
    term.type("robot-1")
    term.expect("'robot-1' is not a valid name")
    term.expect(NAME_QUESTION)
    term.type("robot1")
    term.expect(VPN_CONFIG_QUESTION + " [none]:")
    term.type("nosuch.conf")
    term.expect("'nosuch.conf' is not a readable file.")
    term.expect(VPN_CONFIG_QUESTION)
    term.type("")
    term.expect(MASTER_IP_QUESTION + ":")  # no VPN interface here, so no default to offer
    term.type("")
    term.expect("An answer is needed.")
    term.expect(MASTER_IP_QUESTION)
    term.type("10.11.12.256")
    term.expect("'10.11.12.256' is not an IPv4 address")
    term.expect(MASTER_IP_QUESTION)
    term.type("10.11.12.1")
    term.expect(START_QUESTION)
    term.type("no")
    term.expect("Dry run: nothing was changed.")
    assert term.finish() == 0
    out = term.seen
    assert f"keep the workspace {setup.home}/rcmp_ws" in out
    assert "not start the rcm daemon" in out
    assert "not install a VPN client file" in out
    assert f"write {setup.platform}/init.cfg" in out
    assert setup.config_lines(out) == ["[main]", "name=robot1", "robot=yes", "ip_master=10.11.12.1",
                                       "vpn_interface=nosuch0"]


def test_piped_answers_wrong_ones_asked_again(tmp_path):
    setup = Setup(tmp_path, "master")
    result = setup.run("maybe\nY\nnope\nyes\n80000\n10100,10100\nten\n 10200 , 10201\nno\nNO\n")
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert out.count(SEED_REPLACE_QUESTION) == 2
    assert out.count(FIWARE_QUESTION) == 2
    assert out.count(PORTS_QUESTION) == 4
    assert out.count("Please answer yes or no.") == 2
    assert "'80000' in '80000' is not a port number (1-65535)." in out
    assert "Port 10100 is listed twice in '10100,10100'." in out
    assert "'ten' in 'ten' is not a port number" in out
    assert setup.config_lines(out) == ["[main]", "inbound_open_ports=10200, 10201", "vpn_interface=nosuch0"]
    assert "not start the rcm daemon" in out
    assert "not create a VPN (the administrator runs it)" in out


def test_replace_question_only_when_the_workspace_exists(tmp_path):
    setup = Setup(tmp_path, "master", existing_ws=False)
    result = setup.run("\n\n\n\n")
    assert result.returncode == 0, result.stderr
    assert "already exists" not in result.stdout
    assert f"create the workspace {setup.home}/rcmp_ws" in result.stdout


def test_fiware_cannot_be_chosen_without_the_component_zips(tmp_path):
    setup = Setup(tmp_path, "master", component_zips=False)
    result = setup.run("\nyes\n\n\n\n\n")
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert FIWARE_QUESTION + " (yes/[N]o)?" in out  # the default follows what the package holds
    assert "are not in" in out and out.count(FIWARE_QUESTION) == 2
    assert "unpack" not in out


def test_robot_name_and_server_vm(tmp_path):
    setup = Setup(tmp_path, "robot")
    result = setup.run("\nno\nvm_one\n\n198.51.100.1\n\n", "--ros-port-base", "12000")
    assert result.returncode == 0, result.stderr
    assert setup.config_lines(result.stdout) == [
        "[main]", "name=vm_one", "robot=no", "ip_master=198.51.100.1", "vpn_interface=nosuch0", "ros_port_base=12000"]


def test_rerun_offers_the_current_configuration_as_defaults(tmp_path):
    setup = Setup(tmp_path, "robot")
    setup.platform.mkdir()
    (setup.platform / "init.cfg").write_text(
        "[main]\nname=robot7\nrobot=yes\nip_master=10.9.8.1\nvpn_address=10.9.8.7\nic_port=9000\n")
    result = setup.run("\n\n\n\n\n\n")
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert NAME_QUESTION + " [robot7]:" in out
    assert MASTER_IP_QUESTION + " [10.9.8.1]:" in out
    assert setup.config_lines(out) == ["[main]", "name=robot7", "robot=yes", "ip_master=10.9.8.1",
                                       "vpn_interface=nosuch0", "vpn_address=10.9.8.7", "ic_port=9000"]


def test_master_vpn_address_offers_a_default_master_address_to_robots(tmp_path):
    setup = Setup(tmp_path, "robot")
    result = setup.run("\n\nr2\n\n\n\n", "--vpn-address", "10.20.30.40")
    assert result.returncode == 0, result.stderr
    assert MASTER_IP_QUESTION + " [10.20.30.1]:" in result.stdout
    assert "ip_master=10.20.30.1" in setup.config_lines(result.stdout)


def test_options_answer_their_questions(tmp_path):
    setup = Setup(tmp_path, "master")
    result = setup.run("\n", "--replace-ws", "no", "--fiware", "no", "--inbound-ports", "10300",
                       "--ext-address", "127.0.0.1", "--ext-port", "8080", "--ic-port", "9990", "--no-vpn")
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert "already exists" not in out and FIWARE_QUESTION not in out and "Inbound open ports" not in out
    assert VPN_QUESTION not in out and "not create a VPN" in out
    assert START_QUESTION in out
    assert setup.config_lines(out) == ["[main]", "inbound_open_ports=10300", "ext_address=127.0.0.1",
                                       "ext_port=8080", "vpn_interface=nosuch0", "ic_port=9990"]


def test_non_interactive_asks_nothing(tmp_path):
    setup = Setup(tmp_path, "robot")
    result = setup.run("", "-n", "--name", "robot3", "--ip-master", "10.1.1.1", "--start", "no")
    assert result.returncode == 0, result.stderr
    assert "?" not in result.stdout.split("Dry run")[0]
    assert setup.config_lines(result.stdout)[:4] == ["[main]", "name=robot3", "robot=yes", "ip_master=10.1.1.1"]


def test_non_interactive_without_a_required_value_is_refused(tmp_path):
    setup = Setup(tmp_path, "robot")
    result = setup.run("", "-n", "--name", "robot3")
    assert result.returncode == 2
    assert "no value for 'ip_master'" in result.stderr
    assert not setup.platform.exists()


def test_end_of_input_stops_instead_of_looping(tmp_path):
    setup = Setup(tmp_path, "master")
    result = setup.run("\n")
    assert result.returncode == 1
    assert "(end of input)" in result.stderr
    assert not setup.platform.exists()


@pytest.mark.parametrize("role, args, message", [
    ("master", ["--ext-port", "70000"], "--ext-port: '70000' is not a port number (1-65535)."),
    ("master", ["--inbound-ports", "10100, x"], "--inbound-ports: 'x' in '10100, x' is not a port number"),
    ("master", ["--ext-address", "localhost"], "--ext-address: 'localhost' is not an IPv4 address"),
    ("master", ["--name", "robot1"], "unknown option '--name' for the rcm master installer"),
    ("robot", ["--fiware", "yes"], "unknown option '--fiware' for the rcm robot installer"),
    ("robot", ["--name", "1robot"], "--name: '1robot' is not a valid name"),
    ("robot", ["--home", "relative/dir"], "--home: 'relative/dir' is not an absolute path."),
    ("robot", ["--start", "maybe"], "--start: Please answer yes or no."),
    ("robot", ["--bogus"], "unknown option '--bogus'"),
    ("robot", ["--ip-master"], "--ip-master needs a value"),
    ("master", ["--vpn-subnet", "198.51.100.7/24"], "'198.51.100.7/24' has host bits set"),
    ("master", ["--vpn-subnet", "198.51.100.0/30"], "'198.51.100.0/30' is not an IPv4 subnet from /8 to /29"),
    ("master", ["--vpn-subnet", "198.51.100.0"], "is not an IPv4 subnet"),
    ("master", ["--vpn-port", "0"], "--vpn-port: '0' is not a port number"),
    ("master", ["--vpn-remote", "-oops"], "--vpn-remote: '-oops' is not a host name or IPv4 address."),
    ("master", ["--no-vpn", "--vpn-port", "1195"], "--no-vpn (--vpn no) cannot go with --vpn-subnet"),
    ("master", ["--vpn-config", "x.conf"], "unknown option '--vpn-config' for the rcm master installer"),
    ("robot", ["--no-vpn"], "unknown option '--no-vpn' for the rcm robot installer"),
    ("robot", ["--vpn-subnet", "198.51.100.0/24"], "unknown option '--vpn-subnet' for the rcm robot installer"),
    ("robot", ["--vpn-config", "/nonexistent/client.conf"], "'/nonexistent/client.conf' is not a readable file."),
    ("robot", ["--vpn-config", "/etc/hostname"], "is not an OpenVPN client file written by 'rcmp_n vpn client"),
    ("robot", ["-n", "--ip-master", "198.51.100.1", "--name", "r", "--ros-port-base", "12000"],
     "ros_port_base (--ros-port-base) is only for a server virtual machine"),
])
def test_bad_options_are_refused_and_change_nothing(tmp_path, role, args, message):
    setup = Setup(tmp_path, role)
    result = setup.run("", *args)
    assert result.returncode == 2, result.stdout + result.stderr
    assert message in result.stderr
    assert not setup.platform.exists()
    assert (setup.home / "rcmp_ws" / "src").is_dir()


def test_help_names_every_answer_option(tmp_path):
    for role, words in (("master", ["--fiware", "--inbound-ports", "--ext-address", "--ext-port", "--vpn-subnet",
                                    "--vpn-port", "--vpn-remote", "--no-vpn"]),
                        ("robot", ["--robot", "--name", "--ip-master", "--vpn-config"])):
        (tmp_path / role).mkdir()
        setup = Setup(tmp_path / role, role)
        result = subprocess.run([str(setup.pkg / "install.sh"), "--help"], capture_output=True, text=True,
                                env=setup.env, timeout=30)
        assert result.returncode == 0
        for word in words + ["--start", "--replace-ws", "--non-interactive", "--home", "--workspace",
                             "--service-name", "--vpn-address", "--ic-port", "--skip-deps", "--dry-run"]:
            assert word in result.stdout, f"{role} --help lacks {word}"


def test_rerun_keeps_keys_the_wizard_does_not_manage(tmp_path):
    setup = Setup(tmp_path, "master")
    setup.platform.mkdir()
    (setup.platform / ".init.cfg").write_text(
        "[main]\ninbound_open_ports=10100\nlog_max_bytes = 4096\nheartbeat_interval=1.5\next_port=8080\n")
    result = setup.run("", "-n", "--inbound-ports", "10300, 10301")
    assert result.returncode == 0, result.stderr
    assert setup.config_lines(result.stdout) == [
        "[main]", "inbound_open_ports=10300, 10301", "ext_port=8080", "vpn_interface=nosuch0",
        "log_max_bytes = 4096", "heartbeat_interval=1.5"]


def test_uninstall_refuses_an_unknown_option_before_doing_anything(tmp_path):
    result = subprocess.run([os.path.join(ROOT, "uninstall.sh"), "--bogus"], capture_output=True, text=True,
                            timeout=30)
    assert result.returncode == 2
    assert "unknown option '--bogus'" in result.stderr
    help_text = subprocess.run([os.path.join(ROOT, "uninstall.sh"), "--help"], capture_output=True, text=True,
                               timeout=30)
    assert help_text.returncode == 0 and "--service-name" in help_text.stdout


def test_server_vm_turned_robot_drops_its_ros_port_base(tmp_path):
    setup = Setup(tmp_path, "robot")
    setup.platform.mkdir()
    (setup.platform / "init.cfg").write_text("[main]\nname=vm1\nrobot=no\nip_master=198.51.100.1\nros_port_base=12000\n")
    result = setup.run("", "-n", "--robot", "yes")
    assert result.returncode == 0, result.stderr
    assert setup.config_lines(result.stdout) == ["[main]", "name=vm1", "robot=yes", "ip_master=198.51.100.1",
                                                 "vpn_interface=nosuch0"]


def test_master_rerun_keeps_its_own_name_key(tmp_path):
    setup = Setup(tmp_path, "master")
    setup.platform.mkdir()
    (setup.platform / ".init.cfg").write_text("[main]\nname=central\ninbound_open_ports=10100\n")
    result = setup.run("", "-n")
    assert result.returncode == 0, result.stderr
    assert setup.config_lines(result.stdout) == ["[main]", "inbound_open_ports=10100", "vpn_interface=nosuch0",
                                                 "name=central"]


CLIENT_FILE = "client\ndev tun\nproto udp\nremote 203.0.113.10 1194\n<ca>\nCA\n</ca>\n<cert>\nCERT\n</cert>\n<key>\nKEY\n</key>\n"


def test_master_vpn_flags_answer_the_vpn_question(tmp_path):
    setup = Setup(tmp_path, "master")
    result = setup.run("", "-n", "--vpn-subnet", "198.51.100.0/24", "--vpn-port", "1195",
                       "--vpn-remote", "203.0.113.10")
    assert result.returncode == 0, result.stderr
    assert VPN_QUESTION not in result.stdout
    assert (f"create the platform's VPN in {setup.platform}/vpn: subnet 198.51.100.0/24, UDP port 1195, "
            "remote 203.0.113.10") in result.stdout
    no_vpn = setup.run("", "-n", "--no-vpn")
    assert no_vpn.returncode == 0 and "not create a VPN (the administrator runs it)" in no_vpn.stdout


def test_master_rerun_keeps_an_existing_vpn_and_refuses_new_settings(tmp_path):
    setup = Setup(tmp_path, "master")
    (setup.platform / "vpn").mkdir(parents=True)
    (setup.platform / "vpn" / "server.conf").write_text("dev tun0\n")
    result = setup.run("\n\n\n\n")  # replace, FIWARE, ports, start: no VPN question
    assert result.returncode == 0, result.stderr
    assert VPN_QUESTION not in result.stdout and f"keep the platform's VPN in {setup.platform}/vpn" in result.stdout
    refused = setup.run("", "-n", "--vpn-port", "1195")
    assert refused.returncode == 2
    assert "already exists" in refused.stderr and "rcmp_n vpn init --force" in refused.stderr
    assert (setup.platform / "vpn" / "server.conf").read_text() == "dev tun0\n"


def test_robot_vpn_config_is_installed_and_ip_master_comes_from_the_vpn(tmp_path):
    setup = Setup(tmp_path, "robot")
    client = tmp_path / "robot1.conf"
    client.write_text(CLIENT_FILE)
    result = setup.run("", "-n", "--name", "robot1", "--vpn-config", str(client))
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert f"install {client} as {setup.platform}/vpn/client.conf (mode 0600)" in out
    assert "last octet 1, once the VPN is up" in out
    assert setup.config_lines(out) == ["[main]", "name=robot1", "robot=yes", "vpn_interface=nosuch0"]
    # a relative path is taken from where the installer runs
    relative = subprocess.run(setup.argv("-n", "--name", "robot1", "--vpn-config", "robot1.conf"), cwd=tmp_path,
                              capture_output=True, text=True, env=setup.env, timeout=60)
    assert relative.returncode == 0, relative.stderr
    assert f"install {client} as" in relative.stdout
    # an explicit master address is still taken
    explicit = setup.run("", "-n", "--name", "robot1", "--vpn-config", str(client), "--ip-master", "198.51.100.1")
    assert "ip_master=198.51.100.1" in setup.config_lines(explicit.stdout)
    # once installed, a re-run keeps it
    (setup.platform / "vpn").mkdir(parents=True)
    (setup.platform / "vpn" / "client.conf").write_text(CLIENT_FILE)
    again = setup.run("\n\n\n\n\n", "--ip-master", "198.51.100.1")
    assert again.returncode == 0, again.stderr
    assert VPN_CONFIG_QUESTION + " [keep]:" in again.stdout
    assert f"keep the VPN client file {setup.platform}/vpn/client.conf" in again.stdout


SERVER_VPN_CONFIG_QUESTION = ("OpenVPN client file of this machine, from 'rcmp_n vpn client NAME --server' on the "
                              "master (none: you run the VPN yourself)")


def test_a_server_vm_is_asked_for_a_server_certificate_and_refuses_a_robots(tmp_path):
    setup = Setup(tmp_path, "robot")
    robot_file = tmp_path / "robot1.conf"
    robot_file.write_text("# Certificate role: robot\n" + CLIENT_FILE)
    server_file = tmp_path / "vm1.conf"
    server_file.write_text("# Certificate role: server\n" + CLIENT_FILE)
    old_file = tmp_path / "old.conf"                   # written before certificate roles: counts as a robot's
    old_file.write_text(CLIENT_FILE)
    # the wizard names the command with --server, and asks again for a robot's file
    asked = setup.run(f"\nno\nvm1\n{robot_file}\n{old_file}\n{server_file}\n198.51.100.1\nno\n")
    assert asked.returncode == 0, asked.stderr
    assert SERVER_VPN_CONFIG_QUESTION + " [none]:" in asked.stdout
    assert (f"'{robot_file}' holds a robot's certificate; a server VM needs a server certificate: on the master, "
            f"'rcmp_n vpn client NAME --server -o FILE'.") in asked.stdout
    assert f"'{old_file}' holds a certificate issued before certificate roles" in asked.stdout
    assert f"install {server_file} as {setup.platform}/vpn/client.conf (mode 0600)" in asked.stdout
    # options: refused before anything changes, either way round
    for robot, client, message in (("no", robot_file, "holds a robot's certificate"),
                                   ("yes", server_file, "holds a server VM's certificate")):
        result = setup.run("", "-n", "--robot", robot, "--name", "vm1", "--vpn-config", str(client))
        assert result.returncode == 2, result.stdout
        assert f"--vpn-config: '{client}' {message}" in result.stderr
        assert not setup.platform.exists()
    assert setup.run("", "-n", "--robot", "no", "--name", "vm1", "--vpn-config", str(server_file)).returncode == 0
    assert setup.run("", "-n", "--robot", "yes", "--name", "r1", "--vpn-config", str(robot_file)).returncode == 0
    # a re-run that keeps an installed robot's file refuses to turn the machine into a server VM with it
    (setup.platform / "vpn").mkdir(parents=True)
    (setup.platform / "vpn" / "client.conf").write_text(robot_file.read_text())
    kept = setup.run("", "-n", "--robot", "no", "--name", "vm1", "--ip-master", "198.51.100.1")
    assert kept.returncode != 0 and "the installed client file holds a robot's certificate" in kept.stderr
