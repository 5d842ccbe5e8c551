"""The platform's VPN PKI and its command line (``rcmp_n vpn init | client | revoke | list``), CONTRACTS §7.

Real files, real certificates checked with ``cryptography``, the real command line in a child process. What needs
a running OpenVPN (connected clients, revocation cutting one off) is in tests/system/test_vpn_hosts.py.
"""

import json
import os
import stat
import subprocess

import pytest
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from rcm_platform import rcmp_vpn
from tests.support.paths import REPO

SUBNET = "198.51.100.0/24"
REMOTE = "203.0.113.1"


def rcmp_n(home, *args):
    return subprocess.run(["/usr/bin/python3", "-m", "rcm_platform", "--home", str(home), *args], cwd=REPO,
                          capture_output=True, text=True, timeout=60)


@pytest.fixture
def home(tmp_path):
    h = tmp_path / "home"
    h.mkdir()
    result = rcmp_n(h, "vpn", "init", "--subnet", SUBNET, "--remote", REMOTE, "--port", "1300")
    assert result.returncode == 0, result.stderr
    return h


def inline(text, tag):
    return text.split(f"<{tag}>\n", 1)[1].split(f"\n</{tag}>", 1)[0] + "\n"


def snapshot(folder):
    """Every file under ``folder`` with its bytes: to show that a refused command changed nothing."""
    files = {}
    for root, _, names in os.walk(folder):
        for name in names:
            path = os.path.join(root, name)
            with open(path, "rb") as f:
                files[os.path.relpath(path, folder)] = f.read()
    return files


def signed_by(cert, ca):
    ca.public_key().verify(cert.signature, cert.tbs_certificate_bytes, ec.ECDSA(cert.signature_hash_algorithm))
    return cert.issuer == ca.subject


def crl_serials(home):
    with open(os.path.join(home, "vpn", "crl.pem"), "rb") as f:
        crl = x509.load_pem_x509_crl(f.read())
    return {entry.serial_number for entry in crl}


def test_init_makes_a_private_folder_with_a_ca_a_server_and_its_configuration(home):
    folder = home / "vpn"
    assert stat.S_IMODE(folder.stat().st_mode) == 0o700
    for secret in ("ca.key", "server.key", "tc.key", "issued.json"):
        assert stat.S_IMODE((folder / secret).stat().st_mode) == 0o600, secret
    ca = x509.load_pem_x509_certificate((folder / "ca.crt").read_bytes())
    server = x509.load_pem_x509_certificate((folder / "server.crt").read_bytes())
    assert signed_by(server, ca)
    assert server.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == rcmp_vpn.SERVER_CN
    eku = server.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
    assert ExtendedKeyUsageOID.SERVER_AUTH in eku
    conf = (folder / "server.conf").read_text()
    for line in ("dev tun0", "proto udp", "port 1300", "topology subnet",
                 "server 198.51.100.0 255.255.255.0 nopool", "crl-verify crl.pem", "client-config-dir ccd",
                 "ccd-exclusive", "management management.sock unix"):
        assert line + "\n" in conf, line
    assert crl_serials(home) == set()
    # nothing left over from building it aside
    assert sorted(p.name for p in home.iterdir()) == ["vpn"]


def test_init_refuses_to_replace_a_vpn_without_force_and_replaces_it_with_force(home):
    before = snapshot(home / "vpn")
    result = rcmp_n(home, "vpn", "init", "--subnet", SUBNET, "--remote", REMOTE)
    assert result.returncode == 1
    assert result.stderr.count("\n") == 1 and "already exists" in result.stderr and "--force" in result.stderr
    assert snapshot(home / "vpn") == before
    result = rcmp_n(home, "vpn", "init", "--subnet", "198.51.100.0/25", "--remote", REMOTE, "--force")
    assert result.returncode == 0, result.stderr
    assert (home / "vpn" / "ca.key").read_bytes() != before["ca.key"]
    assert "198.51.100.0/25" in result.stdout and "198.51.100.1" in result.stdout
    assert sorted(p.name for p in home.iterdir()) == ["vpn"]


def test_init_defaults_the_remote_to_the_masters_external_address(tmp_path):
    h = tmp_path / "m"
    h.mkdir()
    (h / ".init.cfg").write_text("[main]\next_address=203.0.113.7\n")
    result = rcmp_n(h, "vpn", "init", "--subnet", SUBNET)
    assert result.returncode == 0, result.stderr
    register = json.loads((h / "vpn" / "issued.json").read_text())
    assert register["remote"] == "203.0.113.7" and register["port"] == 1194


@pytest.mark.parametrize("args, message", [
    (["--subnet", "198.51.100.1/24"], "not an IPv4 subnet"),
    (["--subnet", "198.51.100.0/30"], "between /8 and /29"),
    (["--port", "70000"], "not a port number"),
    (["--remote", "bad host;rm"], "not a host name"),
])
def test_init_refuses_bad_values_with_one_line_and_creates_nothing(tmp_path, args, message):
    h = tmp_path / "m"
    h.mkdir()
    result = rcmp_n(h, "vpn", "init", "--remote", REMOTE, *args)
    assert result.returncode == 2
    assert message in result.stderr and "Traceback" not in result.stderr
    assert list(h.iterdir()) == []


def test_init_refuses_a_robot_home_and_a_master_without_an_external_address(tmp_path):
    robot = tmp_path / "r"
    robot.mkdir()
    (robot / "init.cfg").write_text("[main]\nname=robot1\n")
    result = rcmp_n(robot, "vpn", "init", "--remote", REMOTE)
    assert result.returncode == 2 and "runs on the master" in result.stderr
    master = tmp_path / "m"
    master.mkdir()
    (master / ".init.cfg").write_text("[main]\next_interface=nosuchif0\n")
    result = rcmp_n(master, "vpn", "init")
    assert result.returncode == 2 and "nosuchif0" in result.stderr and "--remote" in result.stderr
    assert not (master / "vpn").exists() and not (robot / "vpn").exists()


def test_client_file_is_self_contained_and_names_the_robot(home, tmp_path):
    out = tmp_path / "robot1.conf"
    result = rcmp_n(home, "vpn", "client", "robot1", "-o", str(out))
    assert result.returncode == 0, result.stderr
    assert "198.51.100.2" in result.stdout
    assert stat.S_IMODE(out.stat().st_mode) == 0o600
    text = out.read_text()
    assert "remote 203.0.113.1 1300\n" in text and "dev tun0\n" in text
    assert f"verify-x509-name {rcmp_vpn.SERVER_CN} name\n" in text
    ca = x509.load_pem_x509_certificate(inline(text, "ca").encode())
    assert ca == x509.load_pem_x509_certificate((home / "vpn" / "ca.crt").read_bytes())
    cert = x509.load_pem_x509_certificate(inline(text, "cert").encode())
    assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == "robot1"
    assert signed_by(cert, ca)
    assert ExtendedKeyUsageOID.CLIENT_AUTH in cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
    key = serialization.load_pem_private_key(inline(text, "key").encode(), password=None)
    assert key.public_key().public_numbers() == cert.public_key().public_numbers()
    assert inline(text, "tls-crypt") == (home / "vpn" / "tc.key").read_text()
    assert (home / "vpn" / "ccd" / "robot1").read_text() == "ifconfig-push 198.51.100.2 255.255.255.0\n"
    # the robot's key is nowhere in the master's folder
    assert all(inline(text, "key").encode() not in data for data in snapshot(home / "vpn").values())


def test_the_same_name_gets_the_same_address_and_only_its_newest_file_works(home):
    first = rcmp_n(home, "vpn", "client", "robot1")
    second = rcmp_n(home, "vpn", "client", "robot2", "--remote", "vpn.example.org:1400")
    again = rcmp_n(home, "vpn", "client", "robot1")
    assert first.returncode == second.returncode == again.returncode == 0
    assert "remote vpn.example.org 1400\n" in second.stdout
    old = x509.load_pem_x509_certificate(inline(first.stdout, "cert").encode())
    new = x509.load_pem_x509_certificate(inline(again.stdout, "cert").encode())
    assert old.serial_number != new.serial_number
    assert crl_serials(home) == {old.serial_number}
    assert rcmp_n(home, "vpn", "list").stdout == ("robot1 198.51.100.2 disconnected robot\n"
                                                  "robot2 198.51.100.3 disconnected robot\n")
    assert rcmp_vpn.certificate_of(str(home), "robot1").address == "198.51.100.2"
    assert rcmp_vpn.certificate_of(str(home), "robot2").address == "198.51.100.3"


def test_revoke_puts_the_certificate_in_the_crl_disables_the_name_and_list_says_so(home):
    issued = rcmp_n(home, "vpn", "client", "robot2")
    serial = x509.load_pem_x509_certificate(inline(issued.stdout, "cert").encode()).serial_number
    result = rcmp_n(home, "vpn", "revoke", "robot2")
    assert result.returncode == 0 and result.stdout == "robot2: revoked\n"
    assert crl_serials(home) == {serial}
    assert (home / "vpn" / "ccd" / "robot2").read_text() == "disable\n"
    assert rcmp_n(home, "vpn", "list").stdout == "robot2 198.51.100.2 revoked robot\n"
    # it keeps its address: a hello naming it from elsewhere is still refused
    assert rcmp_vpn.certificate_of(str(home), "robot2").address == "198.51.100.2"
    again = rcmp_n(home, "vpn", "revoke", "robot2")
    assert again.returncode == 0 and "already revoked" in again.stdout
    # a new file for it makes it work again, at the same address
    reissued = rcmp_n(home, "vpn", "client", "robot2")
    assert reissued.returncode == 0
    assert rcmp_n(home, "vpn", "list").stdout == "robot2 198.51.100.2 disconnected robot\n"
    assert crl_serials(home) == {serial}


def test_commands_refuse_bad_input_with_one_line_and_change_nothing(home, tmp_path):
    rcmp_n(home, "vpn", "client", "robot1")
    before = snapshot(home / "vpn")
    cases = [
        (["vpn", "client", "bad-name"], 2, "not a valid name"),
        (["vpn", "client", "robot_" + "x" * 70], 2, "not a valid name"),
        (["vpn", "client", "robot2", "--remote", "host:99999"], 2, "not a port number"),
        (["vpn", "client", "robot2", "-o", str(tmp_path / "no" / "such" / "dir" / "f.conf")], 1,
         "cannot write the client file"),
        (["vpn", "client", "robot2", "-o", str(tmp_path)], 2, "is a folder"),
        (["vpn", "revoke", "robot9"], 1, "no VPN certificate was issued to 'robot9'"),
        (["vpn", "frobnicate"], 2, "invalid choice"),
    ]
    for args, status, message in cases:
        result = rcmp_n(home, *args)
        assert result.returncode == status, (args, result.stderr)
        assert message in result.stderr, (args, result.stderr)
        assert "Traceback" not in result.stderr
        assert snapshot(home / "vpn") == before, args
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".rcmp-vpn-")]


def test_commands_without_a_vpn_say_so(tmp_path):
    h = tmp_path / "m"
    h.mkdir()
    for args in (["client", "robot1"], ["revoke", "robot1"], ["list"]):
        result = rcmp_n(h, "vpn", *args)
        assert result.returncode == 1 and "run 'rcmp_n vpn init' first" in result.stderr, args
    assert rcmp_vpn.certificate_of(str(h), "robot1") is None
    assert list(h.iterdir()) == []


def test_a_name_never_issued_has_no_address_under_a_managed_vpn(home):
    expected = rcmp_vpn.certificate_of(str(home), "robot7")
    assert expected is not None and expected.address is None


def test_addresses_run_out_with_a_clear_error(tmp_path):
    h = tmp_path / "m"
    h.mkdir()
    assert rcmp_n(h, "vpn", "init", "--subnet", "198.51.100.0/29", "--remote", REMOTE).returncode == 0
    addresses = [rcmp_vpn.client(str(h), f"r{i}")[0] for i in range(5)]   # .2 to .6: the master has .1
    assert addresses == [f"198.51.100.{i}" for i in range(2, 7)]
    result = rcmp_n(h, "vpn", "client", "r5")
    assert result.returncode == 1 and "no free address" in result.stderr


def test_help_lists_the_vpn_commands_and_the_agent_options_still_parse(tmp_path):
    top = rcmp_n(tmp_path, "--help")
    assert top.returncode == 0 and "vpn" in top.stdout and "--home" in top.stdout
    vpn = rcmp_n(tmp_path, "vpn", "--help")
    assert all(word in vpn.stdout for word in ("init", "client", "revoke", "list"))
    client = rcmp_n(tmp_path, "vpn", "client", "--help")
    assert "-o FILE" in client.stdout and "HOST[:PORT]" in client.stdout and "--server" in client.stdout
    from rcm_platform import rcmp_node
    args = rcmp_node.parse_args(["--home", str(tmp_path)])
    assert args.command is None and args.home == str(tmp_path)
    args = rcmp_node.parse_args(["vpn", "list", "--home", str(tmp_path)])
    assert args.command == "vpn" and args.vpn_command == "list" and args.home == str(tmp_path)
