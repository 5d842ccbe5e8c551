"""rcmp_vpn's certificate roles (issue 18 row 6), in this process: the role in the certificate, the client file and
the register, ``vpn list``'s column, ``certificate_of`` (what the master checks hellos against), re-issuing a name
with another role, certificates issued before roles, and the command line's errors.

The rest of the PKI and its command line as a child process are in ``tests/system/test_vpn_pki.py``; roles with
real OpenVPN in ``tests/system/test_vpn_roles.py``.
"""

import io
import json
import os

import pytest
from cryptography import x509
from cryptography.hazmat.backends import default_backend
from cryptography.x509.oid import NameOID

from rcm_platform import rcmp_node, rcmp_vpn

SUBNET = "198.51.100.0/24"


@pytest.fixture
def home(tmp_path):
    h = tmp_path / "home"
    h.mkdir()
    status, out, err = vpn(h, "init", "--subnet", SUBNET, "--remote", "203.0.113.1")
    assert status == 0, err
    return str(h)


def vpn(home, *args):
    """``rcmp_n --home HOME vpn ARGS`` run in this process: (exit status, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    try:
        parsed = rcmp_node.parse_args(["--home", str(home), "vpn", *args])
    except SystemExit as exc:            # argparse's usage error
        return exc.code, "", ""
    status = rcmp_vpn.run(parsed, out=out, err=err)
    return status, out.getvalue(), err.getvalue()


def inline(text, tag):
    return text.split(f"<{tag}>\n", 1)[1].split(f"\n</{tag}>", 1)[0] + "\n"


def certificate(text):
    return x509.load_pem_x509_certificate(inline(text, "cert").encode(), default_backend())   # cryptography 2.8 too


def subject(cert, oid):
    return [attribute.value for attribute in cert.subject.get_attributes_for_oid(oid)]


def register(home):
    with open(os.path.join(home, "vpn", "issued.json")) as f:
        return json.load(f)


def snapshot(folder):
    files = {}
    for root, _, names in os.walk(folder):
        for name in names:
            with open(os.path.join(root, name), "rb") as f:
                files[os.path.relpath(os.path.join(root, name), folder)] = f.read()
    return files


def test_a_robots_and_a_server_vms_certificates_say_what_their_holders_may_be(home):
    status, robot, _ = vpn(home, "client", "robot1")
    assert status == 0
    status, server, _ = vpn(home, "client", "vm1", "--server")
    assert status == 0
    for text, name, role in ((robot, "robot1", "robot"), (server, "vm1", "server")):
        cert = certificate(text)
        assert subject(cert, NameOID.COMMON_NAME) == [name]           # OpenVPN's ccd/ and status: still the CN
        assert subject(cert, NameOID.ORGANIZATIONAL_UNIT_NAME) == [role]
        assert f"# Certificate role: {role}\n" in text                # for the installer
        assert register(home)["clients"][name]["role"] == role
    assert "on its server VM (robot=no)" in server and "on its robot." in robot
    status, out, _ = vpn(home, "list")
    assert out == "robot1 198.51.100.2 disconnected robot\nvm1 198.51.100.3 disconnected server\n"
    assert rcmp_vpn.certificate_of(home, "robot1") == rcmp_vpn.Certificate("198.51.100.2", "robot", False, None)
    assert rcmp_vpn.certificate_of(home, "vm1") == rcmp_vpn.Certificate("198.51.100.3", "server", False, None)


def test_the_client_command_says_the_role_it_issued(home, tmp_path):
    status, out, _ = vpn(home, "client", "vm1", "--server", "-o", str(tmp_path / "vm1.conf"))
    assert status == 0
    assert out == f"vm1: VPN address 198.51.100.2, server certificate; client file written to {tmp_path}/vm1.conf\n"


def test_a_name_keeps_its_role_unless_told_to_change_it(home):
    vpn(home, "client", "robot1")
    before = snapshot(os.path.join(home, "vpn"))
    status, out, err = vpn(home, "client", "robot1", "--server")
    assert status == 1 and out == ""
    assert err == ("rcmp_n vpn client: 'robot1' was issued a robot certificate; to issue it a server certificate "
                   "instead, give --change-role (its robot certificate is revoked)\n")
    assert snapshot(os.path.join(home, "vpn")) == before              # nothing changed
    old_serial = register(home)["clients"]["robot1"]["serial"]
    status, text, _ = vpn(home, "client", "robot1", "--server", "--change-role")
    assert status == 0
    assert subject(certificate(text), NameOID.ORGANIZATIONAL_UNIT_NAME) == ["server"]
    assert old_serial in {entry["serial"] for entry in register(home)["revoked"]}   # the robot's file stops working
    assert rcmp_vpn.certificate_of(home, "robot1").role == "server"
    # the same role again needs nothing; back to a robot needs the flag again
    assert vpn(home, "client", "robot1", "--server")[0] == 0
    assert vpn(home, "client", "robot1")[0] == 1
    # a revoked name keeps its role too
    vpn(home, "client", "vm9", "--server")
    vpn(home, "revoke", "vm9")
    status, _, err = vpn(home, "client", "vm9")
    assert status == 1 and "--change-role" in err
    assert rcmp_vpn.certificate_of(home, "vm9") == rcmp_vpn.Certificate("198.51.100.3", "server", True, None)


def test_certificates_issued_before_roles_are_robots_and_take_either_role_once(home):
    vpn(home, "client", "old_robot")
    vpn(home, "client", "old_vm")
    data = register(home)
    for name in ("old_robot", "old_vm"):
        del data["clients"][name]["role"]                            # as a register written before roles
    with open(os.path.join(home, "vpn", "issued.json"), "w") as f:
        json.dump(data, f)
    assert rcmp_vpn.certificate_of(home, "old_vm").role == "robot"
    assert vpn(home, "list")[1] == ("old_robot 198.51.100.2 disconnected robot\n"
                                    "old_vm 198.51.100.3 disconnected robot\n")
    # the upgrade: a server VM's name issued again with --server, no other flag (its role was never chosen)
    status, text, _ = vpn(home, "client", "old_vm", "--server")
    assert status == 0 and subject(certificate(text), NameOID.ORGANIZATIONAL_UNIT_NAME) == ["server"]
    assert rcmp_vpn.certificate_of(home, "old_vm") == rcmp_vpn.Certificate("198.51.100.3", "server", False, None)
    assert vpn(home, "client", "old_robot")[0] == 0
    assert register(home)["clients"]["old_robot"]["role"] == "robot"


def test_certificate_of_without_a_managed_vpn_a_name_never_issued_and_an_unreadable_register(home, tmp_path):
    assert rcmp_vpn.certificate_of(str(tmp_path), "robot1") is None   # no HOME/vpn/server.conf: no rule
    never = rcmp_vpn.certificate_of(home, "robot7")
    assert never.address is None and never.role is None and "no VPN certificate was issued" in never.missing
    with open(os.path.join(home, "vpn", "issued.json"), "w") as f:
        f.write("{not json")
    broken = rcmp_vpn.certificate_of(home, "robot7")
    assert broken.address is None and broken.missing == "the VPN register cannot be read"


@pytest.mark.parametrize("args", [
    ["client", "robot1", "--server=yes"],
    ["client", "robot1", "--role", "server"],
    ["client", "--server"],
])
def test_bad_usage_is_refused_and_changes_nothing(home, args):
    before = snapshot(os.path.join(home, "vpn"))
    status, _, _ = vpn(home, *args)
    assert status == 2
    assert snapshot(os.path.join(home, "vpn")) == before


def test_client_refuses_a_role_that_does_not_exist(home):
    with pytest.raises(rcmp_vpn.VpnError, match="robot or server"):
        rcmp_vpn.client(home, "robot1", role="admin")
    assert register(home)["clients"] == {}
