"""The platform's own VPN (docs/VPN.md): its PKI, its OpenVPN configurations, and OpenVPN run by the agent.

Owns:
- ``HOME/vpn/`` (mode 0700) and everything in it: the certificate authority (``ca.crt``, ``ca.key``), the server's
  certificate and key, the tls-crypt key, the revocation list ``crl.pem``, OpenVPN's client-config-dir ``ccd/``
  (one file per name: its fixed address, or ``disable`` once revoked), ``server.conf`` and the register of names
  issued ``issued.json`` (address, current serial, role, revoked or not). Keys are made in this process with the
  ``cryptography`` package (EC P-256) and never leave the folder except inside the client file ``vpn client``
  writes for its robot. Every change is made under a lock, each file written whole and renamed into place,
  the register last, so an interrupted command leaves the previous state (docs/DECISIONS.md, docs/VPN.md);
- certificate roles: a client certificate says what its holder may be, a robot (``vpn client NAME``) or a server
  VM (``vpn client NAME --server``), in its subject's organizational unit (``OU=robot`` / ``OU=server``) and in
  the register; a certificate issued before roles (no OU, no ``role`` in the register) counts as a robot's;
- the command line ``rcmp_n vpn init | client NAME [--server] | revoke NAME | list`` (``add_parser``, ``run``),
  with the exit statuses of every ``rcmp_n`` command (``rcmp_config.EXIT_STATUSES``): 0 done, 1 it cannot be done
  (one line on stderr, nothing changed), 2 bad usage (the command line, the platform folder: missing, not a folder,
  a robot's), 3 a missing package (``cryptography``: ``rcmp_node`` says which);
- OpenVPN's management interface on the Unix socket ``HOME/vpn/management.sock``: ``kill`` (revocation cuts a
  connected client at once) and ``status`` (who is connected, for ``vpn list``);
- ``certificate_of(home, name)``: what the register says of NAME (its fixed address, its certificate's role, revoked
  or not) when this master's VPN is managed, for the master's hello check and for r_provisioning's advice;
- ``ManagedVpn``: with ``HOME/vpn/server.conf`` (master) or ``HOME/vpn/client.conf`` (robot, server VM) the agent
  runs OpenVPN as a child of its process table before anything else, restarts it with backoff when it exits,
  stops it last, and logs its state changes. Without those files this module does nothing to the agent.

About 930 lines: the PKI, the OpenVPN files made from it and the OpenVPN the agent runs are one job (each
command changes the certificates and the files OpenVPN reads together), so they stay one module.
"""

import argparse
import collections
import datetime
import fcntl
import ipaddress
import json
import logging
import os
import re
import secrets
import shutil
import socket
import sys
import tempfile

from .rcmp_config import EXIT_FAILED, EXIT_OK, EXIT_STATUSES, EXIT_USAGE, MAX_NAME_LENGTH, folder_problem, is_name
from .rcmp_process import FAILED, STARTING

log = logging.getLogger("rcmp.vpn")

VPN_DIR = "vpn"
SERVER_CONF = "server.conf"
CLIENT_CONF = "client.conf"
REGISTER = "issued.json"
MANAGEMENT_SOCKET = "management.sock"
SERVER_CN = "rcmp-vpn-server"         # not a valid instance name (a dash), so no robot can be issued it
DEFAULT_SUBNET = "10.11.12.0/24"      # the original guide's example
DEFAULT_PORT = 1194
CERT_DAYS = 3650
CRL_DAYS = 3650                       # rewritten at every change; OpenVPN refuses everyone once it expires
OPENVPN = "/usr/sbin/openvpn"
MANAGEMENT_TIMEOUT = 5.0
HOST_RE = re.compile(r"[A-Za-z0-9]([A-Za-z0-9.-]{0,251}[A-Za-z0-9])?\Z")
ROBOT = "robot"
SERVER = "server"
ROLES = (ROBOT, SERVER)               # what a client certificate lets its holder be (its subject's OU)
UNRECORDED_ROLE = ROBOT               # the role of a certificate issued before roles existed (no OU, no "role")


class VpnError(Exception):
    """A VPN command cannot be done; ``str()`` is one line. Nothing was changed. ``status``: the exit status,
    ``EXIT_FAILED`` unless the command was asked wrongly (``EXIT_USAGE``)."""

    def __init__(self, message, status=EXIT_FAILED):
        super().__init__(message)
        self.status = status


# -- paths and the register ---------------------------------------------------------------------------------

def vpn_dir(home):
    return os.path.join(os.path.abspath(home), VPN_DIR)


def _register_path(home):
    return os.path.join(vpn_dir(home), REGISTER)


def _load_register(home):
    path = _register_path(home)
    if not os.path.exists(path):
        raise VpnError(f"{vpn_dir(home)}: no platform VPN here (run 'rcmp_n vpn init' first)")
    try:
        with open(path, encoding="utf-8") as f:
            register = json.load(f)
        register["clients"]  # noqa: B018 - the one key every register has
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise VpnError(f"{path}: unreadable register of issued names: {exc}") from None
    return register


def _write_file(path, data, mode=0o600):
    """Write ``data`` (bytes or str) to ``path`` whole: a temporary file in the same folder, renamed over it."""
    if isinstance(data, str):
        data = data.encode("utf-8")
    folder = os.path.dirname(path)
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", dir=folder)
    try:
        os.fchmod(fd, mode)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


class _Lock:
    """An exclusive lock on ``HOME/vpn/.lock`` for the length of one command that changes the VPN."""

    def __init__(self, home):
        self.path = os.path.join(vpn_dir(home), ".lock")

    def __enter__(self):
        self.fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o600)
        fcntl.flock(self.fd, fcntl.LOCK_EX)
        return self

    def __exit__(self, *exc):
        os.close(self.fd)


# -- PKI --------------------------------------------------------------------------------------------------

def _backend():
    """``cryptography``'s backend, which versions before 3.1 (Ubuntu 20.04: 2.8) require as an argument and later
    ones accept and ignore: passed to every call that takes one."""
    from cryptography.hazmat.backends import default_backend
    return default_backend()


def _crypto():
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID
    return x509, hashes, serialization, ec, ExtendedKeyUsageOID, NameOID


def _now():
    return datetime.datetime.now(datetime.timezone.utc).replace(microsecond=0)


def _new_key():
    _, _, _, ec, _, _ = _crypto()
    return ec.generate_private_key(ec.SECP256R1(), _backend())


def _key_pem(key):
    _, _, serialization, _, _, _ = _crypto()
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption()).decode("ascii")


def _cert_pem(cert):
    _, _, serialization, _, _, _ = _crypto()
    return cert.public_bytes(serialization.Encoding.PEM).decode("ascii")


def _make_ca():
    x509, hashes, _, _, _, NameOID = _crypto()
    key = _new_key()
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "RCM platform VPN CA")])
    now = _now()
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days=CERT_DAYS))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=False, content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False, key_cert_sign=True,
                                         crl_sign=True, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
            .sign(key, hashes.SHA256(), _backend()))
    return key, cert


def _issue(ca_key, ca_cert, common_name, tls_server, role=None):
    """A new key and a certificate for ``common_name`` signed by the CA: TLS server usage (the OpenVPN server's),
    or client usage with the platform ``role`` (robot or server VM) as the subject's organizational unit."""
    x509, hashes, _, _, ExtendedKeyUsageOID, NameOID = _crypto()
    key = _new_key()
    now = _now()
    usage = ExtendedKeyUsageOID.SERVER_AUTH if tls_server else ExtendedKeyUsageOID.CLIENT_AUTH
    subject = [x509.NameAttribute(NameOID.COMMON_NAME, common_name)]
    if role is not None:
        subject.insert(0, x509.NameAttribute(NameOID.ORGANIZATIONAL_UNIT_NAME, role))
    cert = (x509.CertificateBuilder()
            .subject_name(x509.Name(subject))
            .issuer_name(ca_cert.subject).public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days=CERT_DAYS))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=True, key_cert_sign=False,
                                         crl_sign=False, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.ExtendedKeyUsage([usage]), critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
            .sign(ca_key, hashes.SHA256(), _backend()))
    return key, cert


def _crl_pem(ca_key, ca_cert, revoked):
    """The revocation list: ``revoked`` is a list of ``{"serial": int, "date": ISO text}``."""
    x509, hashes, _, _, _, _ = _crypto()
    now = _now()
    builder = (x509.CertificateRevocationListBuilder().issuer_name(ca_cert.subject).last_update(now)
               .next_update(now + datetime.timedelta(days=CRL_DAYS)))
    for entry in revoked:
        builder = builder.add_revoked_certificate(
            x509.RevokedCertificateBuilder().serial_number(entry["serial"])
            .revocation_date(datetime.datetime.fromisoformat(entry["date"])).build(_backend()))
    _, _, serialization, _, _, _ = _crypto()
    return builder.sign(ca_key, hashes.SHA256(), _backend()).public_bytes(serialization.Encoding.PEM).decode("ascii")


def _load_ca(home):
    x509, _, serialization, _, _, _ = _crypto()
    folder = vpn_dir(home)
    try:
        with open(os.path.join(folder, "ca.key"), "rb") as f:
            key = serialization.load_pem_private_key(f.read(), password=None, backend=_backend())
        with open(os.path.join(folder, "ca.crt"), "rb") as f:
            cert = x509.load_pem_x509_certificate(f.read(), _backend())
    except (OSError, ValueError) as exc:
        raise VpnError(f"{folder}: cannot read the certificate authority: {exc}") from None
    return key, cert


def _tls_crypt_key():
    """An OpenVPN static key (2048 bits), the format ``openvpn --genkey secret`` writes."""
    hexa = secrets.token_bytes(256).hex()
    lines = [hexa[i:i + 32] for i in range(0, len(hexa), 32)]
    return ("#\n# 2048 bit OpenVPN static key\n#\n-----BEGIN OpenVPN Static key V1-----\n"
            + "\n".join(lines) + "\n-----END OpenVPN Static key V1-----\n")


# -- configurations ---------------------------------------------------------------------------------------

def _server_conf(network, port):
    return f"""\
# The RCM platform's VPN server, written by 'rcmp_n vpn init' (see docs/VPN.md in the platform's sources).
# Paths are relative to this folder: run as  openvpn --cd {{this folder}} --config {SERVER_CONF}
dev tun0
dev-type tun
proto udp
port {port}
topology subnet
server {network.network_address} {network.netmask} nopool
ca ca.crt
cert server.crt
key server.key
dh none
tls-crypt tc.key
crl-verify crl.pem
remote-cert-tls client
tls-version-min 1.2
client-config-dir ccd
ccd-exclusive
keepalive 2 10
explicit-exit-notify 1
persist-key
management {MANAGEMENT_SOCKET} unix
verb 3
"""


def _client_conf(remote, port, ca_pem, cert_pem, key_pem, tls_crypt, role):
    machine = "robot" if role == ROBOT else "server VM (robot=no)"
    return f"""\
# The RCM platform's VPN, client side, written by 'rcmp_n vpn client' (see docs/VPN.md in the platform's sources).
# It holds this machine's private key: copy it only to HOME/vpn/client.conf (mode 0600) on its {machine}.
# {ROLE_LINE}{role}
client
dev tun0
dev-type tun
proto udp
remote {remote} {port}
nobind
resolv-retry infinite
connect-retry 1 5
remote-cert-tls server
verify-x509-name {SERVER_CN} name
tls-version-min 1.2
persist-key
verb 3
<ca>
{ca_pem.strip()}
</ca>
<cert>
{cert_pem.strip()}
</cert>
<key>
{key_pem.strip()}
</key>
<tls-crypt>
{tls_crypt.strip()}
</tls-crypt>
"""


# -- validation -------------------------------------------------------------------------------------------

def _name(value):
    if not is_name(value):
        raise argparse.ArgumentTypeError(
            f"not a valid name (a letter, then letters, digits and underscores, at most {MAX_NAME_LENGTH}): "
            f"{value[:80]!r}")
    return value


def _subnet(value):
    try:
        network = ipaddress.IPv4Network(value, strict=True)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"not an IPv4 subnet such as {DEFAULT_SUBNET}: {value[:80]!r} ({exc})") \
            from None
    if not 8 <= network.prefixlen <= 29:
        raise argparse.ArgumentTypeError(f"the subnet's prefix must be between /8 and /29: {value!r}")
    return network


def _port(value):
    if not value.isdigit() or not 1 <= int(value) <= 65535:
        raise argparse.ArgumentTypeError(f"not a port number (1-65535): {value[:80]!r}")
    return int(value)


def _host(value):
    if not HOST_RE.match(value):
        raise argparse.ArgumentTypeError(f"not a host name or IPv4 address: {value[:80]!r}")
    return value


def _host_port(value):
    host, sep, port = value.rpartition(":")
    if not sep:
        return _host(value), None
    return _host(host), _port(port)


# -- the commands -----------------------------------------------------------------------------------------

def _check_home(home, command):
    """VpnError (bad usage) unless ``home`` is a master's platform folder this user may use for ``command``
    (``init`` writes in it; the others read it, and change ``vpn/`` under their lock)."""
    problem = folder_problem(home, write=command == "init")
    if problem:
        raise VpnError(f"{home}: {problem}", EXIT_USAGE)
    if os.path.exists(os.path.join(home, "init.cfg")):
        raise VpnError(f"{home}: has init.cfg, so it is a robot or a server VM; 'vpn {command}' runs on the master",
                       EXIT_USAGE)


def init(home, subnet=None, port=DEFAULT_PORT, remote=None, force=False, default_remote=None):
    """Create HOME/vpn: CA, server certificate and key, tls-crypt key, CRL, ccd/, server.conf, register."""
    home = os.path.abspath(home)
    _check_home(home, "init")
    folder = vpn_dir(home)
    if os.path.lexists(folder) and not force:
        raise VpnError(f"{folder}: a VPN already exists (give --force to replace it: every client file issued so "
                       f"far stops working)")
    network = subnet or ipaddress.IPv4Network(DEFAULT_SUBNET)
    if remote is None:
        # ``default_remote(home)`` (rcmp_node passes it in: the address of ``ext_interface``) returns the address
        # or raises VpnError with its sentence; this module never imports rcmp_node (imports go one way down)
        if default_remote is None:
            raise VpnError("no address to put in client files: give --remote HOST", EXIT_USAGE)
        remote = default_remote(home)
    server_address = str(next(network.hosts()))

    ca_key, ca_cert = _make_ca()
    server_key, server_cert = _issue(ca_key, ca_cert, SERVER_CN, tls_server=True)
    register = {"version": 1, "subnet": str(network), "server_address": server_address, "port": port,
                "remote": remote, "clients": {}, "revoked": []}
    new = tempfile.mkdtemp(prefix=".vpn-new-", dir=home)  # mode 0700
    try:
        os.chmod(new, 0o700)
        os.mkdir(os.path.join(new, "ccd"), 0o700)
        _write_file(os.path.join(new, "ca.key"), _key_pem(ca_key))
        _write_file(os.path.join(new, "ca.crt"), _cert_pem(ca_cert), 0o644)
        _write_file(os.path.join(new, "server.key"), _key_pem(server_key))
        _write_file(os.path.join(new, "server.crt"), _cert_pem(server_cert), 0o644)
        _write_file(os.path.join(new, "tc.key"), _tls_crypt_key())
        _write_file(os.path.join(new, "crl.pem"), _crl_pem(ca_key, ca_cert, []), 0o644)
        _write_file(os.path.join(new, SERVER_CONF), _server_conf(network, port), 0o644)
        _write_file(os.path.join(new, REGISTER), json.dumps(register, indent=1) + "\n")
        old = None
        if os.path.lexists(folder):
            old = tempfile.mkdtemp(prefix=".vpn-old-", dir=home)
            os.replace(folder, os.path.join(old, VPN_DIR))
        os.replace(new, folder)
    except BaseException:
        shutil.rmtree(new, ignore_errors=True)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    return register


ROLE_LINE = "Certificate role: "      # the client file's comment naming its role (read by the installer)


def role_of(entry):
    """The role a register entry's certificate grants: its ``role``, or robot for one issued before roles."""
    role = entry.get("role")
    return role if role in ROLES else UNRECORDED_ROLE


def _next_address(register):
    network = ipaddress.IPv4Network(register["subnet"])
    taken = {register["server_address"]} | {c["address"] for c in register["clients"].values()}
    for host in network.hosts():
        if str(host) not in taken:
            return str(host)
    raise VpnError(f"the VPN subnet {network} has no free address left")


def client(home, name, remote=None, port=None, stage=None, role=ROBOT, change_role=False):
    """Issue NAME a certificate for ``role`` (robot or server; its earlier ones revoked) at its fixed address;
    return (address, client file).

    A name keeps the role it was first issued with: issuing it with the other role is refused unless
    ``change_role`` (its certificate of the old role is then revoked like any earlier one). A name issued before
    roles has none recorded and takes either without ``change_role``.

    ``stage(text)``, when given, is called with the client file before anything is committed (it writes the file
    to a temporary place, and raises to abandon the command) and returns a callable run after the commit.
    """
    if role not in ROLES:
        raise VpnError(f"a certificate's role is robot or server, not {str(role)[:40]!r}")
    folder = vpn_dir(home)
    _load_register(home)
    with _Lock(home):
        register = _load_register(home)
        ca_key, ca_cert = _load_ca(home)
        try:
            with open(os.path.join(folder, "tc.key"), encoding="ascii") as f:
                tls_crypt = f.read()
        except OSError as exc:
            raise VpnError(f"{folder}: cannot read tc.key: {exc.strerror or exc}") from None
        entry = register["clients"].get(name)
        if entry and entry.get("role") in ROLES and entry["role"] != role and not change_role:
            old = entry["role"]
            raise VpnError(f"'{name}' was issued a {old} certificate; to issue it a {role} certificate instead, "
                           f"give --change-role (its {old} certificate is revoked)")
        address = entry["address"] if entry else _next_address(register)
        key, cert = _issue(ca_key, ca_cert, name, tls_server=False, role=role)
        text = _client_conf(remote or register["remote"], port or register["port"], _cert_pem(ca_cert),
                            _cert_pem(cert), _key_pem(key), tls_crypt, role)
        finish = stage(text) if stage else None
        now = _now().isoformat()
        if entry and not entry.get("revoked"):   # only the newest file of a name works
            register["revoked"].append({"serial": entry["serial"], "date": now})
        register["clients"][name] = {"address": address, "serial": cert.serial_number, "revoked": False,
                                     "issued": now, "role": role}
        netmask = ipaddress.IPv4Network(register["subnet"]).netmask
        try:
            _write_file(os.path.join(folder, "ccd", name), f"ifconfig-push {address} {netmask}\n", 0o644)
            _write_file(os.path.join(folder, "crl.pem"), _crl_pem(ca_key, ca_cert, register["revoked"]), 0o644)
            _write_file(_register_path(home), json.dumps(register, indent=1) + "\n")
        except BaseException:
            if finish is not None:
                finish(False)
            raise
        if finish is not None:
            finish(True)
    return address, text


def revoke(home, name):
    """Revoke NAME's certificate, refuse it in ccd/, and cut it off if connected. Returns what was done."""
    folder = vpn_dir(home)
    _load_register(home)
    with _Lock(home):
        register = _load_register(home)
        entry = register["clients"].get(name)
        if entry is None:
            raise VpnError(f"no VPN certificate was issued to '{name}' (see 'rcmp_n vpn list')")
        already = entry.get("revoked", False)
        if not already:
            ca_key, ca_cert = _load_ca(home)
            register["revoked"].append({"serial": entry["serial"], "date": _now().isoformat()})
            entry["revoked"] = True
            _write_file(os.path.join(folder, "crl.pem"), _crl_pem(ca_key, ca_cert, register["revoked"]), 0o644)
            _write_file(os.path.join(folder, "ccd", name), "disable\n", 0o644)
            _write_file(_register_path(home), json.dumps(register, indent=1) + "\n")
    killed = kill_client(home, name)
    return already, killed


def _client_rows(home):
    """The server's connected clients as dicts keyed by the status header's names, or None when it is silent."""
    answer = _management(home, "status 3")
    if answer is None:
        return None
    header, rows = None, []
    for line in answer:
        fields = line.split("\t")
        if fields[:2] == ["HEADER", "CLIENT_LIST"]:
            header = fields[2:]
        elif fields[0] == "CLIENT_LIST" and header:
            rows.append(dict(zip(header, fields[1:])))
    return rows


def connected_names(home):
    """The common names connected to the running OpenVPN server, or None when its management socket is silent."""
    rows = _client_rows(home)
    return None if rows is None else {row.get("Common Name") for row in rows}


def kill_client(home, name):
    """Cut NAME's connection through the management interface at once; True if a client was cut.

    ``client-kill`` tells the client to restart (so it tries again now and is refused, rather than noticing the
    cut only at its next keepalive timeout); ``kill NAME`` is the fallback when the client id is not listed.
    """
    rows = _client_rows(home)
    if rows is None:
        return False
    ids = [row["Client ID"] for row in rows if row.get("Common Name") == name and row.get("Client ID", "").isdigit()]
    if not ids:
        answer = _management(home, f"kill {name}")
        return bool(answer) and answer[0].startswith("SUCCESS")
    cut = False
    for cid in ids:
        answer = _management(home, f"client-kill {cid}")
        cut = cut or (bool(answer) and answer[0].startswith("SUCCESS"))
    return cut


def _management(home, command):
    """Send one command to OpenVPN's management socket; its answer lines, or None when no server listens."""
    path = os.path.join(vpn_dir(home), MANAGEMENT_SOCKET)
    if not os.path.exists(path):
        return None
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.settimeout(MANAGEMENT_TIMEOUT)
    try:
        sock.connect(path)
        reader = sock.makefile("r", encoding="utf-8", errors="replace", newline="\n")
        sock.sendall(command.encode("ascii") + b"\n")
        lines = []
        multiline = command.startswith("status")
        for raw in reader:
            line = raw.rstrip("\r\n")
            if line.startswith(">"):          # greeting and real-time notifications
                continue
            lines.append(line)
            if not multiline or line == "END":
                break
        try:
            sock.sendall(b"quit\n")
        except OSError:
            pass
        return lines
    except OSError as exc:
        log.debug("management socket %s: %s", path, exc)
        return None
    finally:
        sock.close()


def listing(home):
    """``[(name, address, state, role)]`` sorted by name; state is connected, disconnected or revoked, role robot
    or server (robot for a certificate issued before roles)."""
    register = _load_register(home)
    connected = connected_names(home) or set()
    rows = []
    for name in sorted(register["clients"]):
        entry = register["clients"][name]
        state = "revoked" if entry.get("revoked") else ("connected" if name in connected else "disconnected")
        rows.append((name, entry["address"], state, role_of(entry)))
    return rows


def managed_server(home):
    return os.path.exists(os.path.join(vpn_dir(home), SERVER_CONF))


_cache = {}


class Certificate(collections.namedtuple("Certificate", "address role revoked missing")):
    """What the managed VPN's register says of one name: ``address``, its fixed VPN address, or None when no
    address is its own (``missing`` then says why: never issued, or the register cannot be read); ``role``, what
    its current certificate lets it be (robot or server); ``revoked``."""


def certificate_of(home, name):
    """What this master's managed VPN (HOME/vpn/server.conf) says of NAME, a ``Certificate``; None when the VPN is
    not managed (no rule from certificates then).

    A name that was never issued a certificate has no address (a hello naming it is refused wherever it comes
    from) and no role. A revoked name keeps its address and role (nobody holds them). The register is read again
    only when its file changed.
    """
    if not managed_server(home):
        return None
    path = _register_path(home)
    try:
        stamp = os.stat(path).st_mtime_ns
        cached = _cache.get(path)
        if cached is None or cached[0] != stamp:
            with open(path, encoding="utf-8") as f:
                cached = (stamp, json.load(f))
            _cache[path] = cached
        entry = cached[1]["clients"].get(name)
        if entry is not None:
            return Certificate(str(entry["address"]), role_of(entry), bool(entry.get("revoked")), None)
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        log.error("cannot read the VPN register %s: %s", path, exc)
        return Certificate(None, None, False, "the VPN register cannot be read")
    return Certificate(None, None, False, "no VPN certificate was issued to it")


# -- the managed VPN in the agent ---------------------------------------------------------------------------

RESTART_INITIAL = 1.0     # seconds before OpenVPN is started again after it exited
RESTART_CAP = 30.0        # longest wait between two restarts
STABLE_AFTER = 60.0       # a run this long resets the backoff
ADDRESS_POLL = 0.1        # seconds between two looks for the VPN address (a netifaces call)


def managed_config(config):
    """The OpenVPN configuration the agent runs itself: HOME/vpn/server.conf (master) or client.conf, or None."""
    path = os.path.join(vpn_dir(config.home), SERVER_CONF if config.role == "master" else CLIENT_CONF)
    return path if os.path.isfile(path) else None


def openvpn_argv(conf_path):
    binary = shutil.which("openvpn", path="/usr/sbin:/usr/bin:/sbin:/bin") or OPENVPN
    return [binary, "--cd", os.path.dirname(conf_path), "--config", os.path.basename(conf_path)]


def _service_base():
    from twisted.application import service
    return service.Service


class ManagedVpn(_service_base()):
    """OpenVPN as a child of the agent's process table: started first, restarted with backoff, stopped last.

    ``wait_for_address()`` fires with the agent's platform address once ``vpn_interface`` has one.
    """

    name = "vpn"
    KEY = "openvpn"

    def __init__(self, config, conf_path, table, reactor, address_of):
        self.config = config
        self.address_of = address_of          # () -> the platform address or None (rcmp_config.platform_address)
        self.conf_path = conf_path
        self.table = table
        self.reactor = reactor
        self.delay = RESTART_INITIAL
        self.process = None
        self.restarts = 0
        self._restart_call = None
        self._address_call = None
        self._address_waiters = []
        self._up_logged = False

    def startService(self):
        super().startService()
        folder = os.path.dirname(self.conf_path)
        if os.stat(folder).st_mode & 0o077 or os.stat(self.conf_path).st_mode & 0o077:
            log.warning("managed VPN: %s and %s readable by others; making them private (0700, 0600)",
                        folder, self.conf_path)
            os.chmod(folder, 0o700)
            os.chmod(self.conf_path, 0o600)
        log.info("managed VPN: starting OpenVPN with %s", self.conf_path)
        self._spawn()
        self._poll_address()

    def _spawn(self):
        self._restart_call = None
        if not self.running:
            return
        self.table.forget(self.KEY)
        env = {"PATH": "/usr/sbin:/usr/bin:/sbin:/bin", "LANG": "C.UTF-8"}
        self.process = self.table.spawn(self.KEY, openvpn_argv(self.conf_path), env, "openvpn")
        self.process.listeners.append(self._changed)
        if self.process.state == FAILED:   # could not even be spawned
            self._changed(self.process, STARTING, FAILED)

    def _changed(self, process, old, new):
        if process is not self.process or new != FAILED or not self.running:
            return
        ran = self.reactor.seconds() - (process.started_at or self.reactor.seconds())
        if ran >= STABLE_AFTER:
            self.delay = RESTART_INITIAL
        self.restarts += 1
        self._up_logged = False
        why = " ".join(str(process.error).split())   # one log line, whatever OpenVPN printed
        log.warning("managed VPN: OpenVPN ended (%s); starting it again in %g s", why, self.delay)
        self._restart_call = self.reactor.callLater(self.delay, self._spawn)
        self.delay = min(RESTART_CAP, self.delay * 2)

    def _poll_address(self):
        self._address_call = None
        if not self.running:
            return
        address = self.address_of()
        if address is not None and not self._up_logged:
            self._up_logged = True
            log.info("managed VPN: up, %s has address %s", self.config.vpn_interface, address)
            waiters, self._address_waiters = self._address_waiters, []
            for d in waiters:
                d.callback(address)
        elif address is None and self._up_logged:
            self._up_logged = False
            log.warning("managed VPN: down, %s has no address", self.config.vpn_interface)
        self._address_call = self.reactor.callLater(ADDRESS_POLL, self._poll_address)

    def wait_for_address(self):
        from twisted.internet import defer
        address = self.address_of() if self.running else None
        if address is not None:
            return defer.succeed(address)
        d = defer.Deferred()
        self._address_waiters.append(d)
        return d

    def stopService(self):
        super().stopService()
        for call in (self._restart_call, self._address_call):
            if call is not None and call.active():
                call.cancel()
        self._restart_call = self._address_call = None
        self._address_waiters = []
        log.info("managed VPN: stopping OpenVPN")
        d = self.table.stop(self.KEY)
        d.addCallback(lambda _: log.info("managed VPN: OpenVPN stopped"))
        return d


def _multi_service_base():
    from twisted.application import service
    return service.MultiService


class VpnFirst(_multi_service_base()):
    """The agent's top service with a managed VPN: OpenVPN started first and stopped last, after the agent.

    (Twisted's ``MultiService`` stops its children all at once; the agent needs the VPN while it says bye to its
    peer and while its ROS children unregister from their masters.)
    """

    def __init__(self, vpn, after):
        super().__init__()
        self.vpn = vpn
        self.after = after
        vpn.setServiceParent(self)
        after.setServiceParent(self)

    def stopService(self):
        from twisted.application import service
        from twisted.internet import defer
        service.Service.stopService(self)
        d = defer.maybeDeferred(self.after.stopService)
        d.addBoth(lambda _: self.vpn.stopService())
        return d


class AfterVpn(_service_base()):
    """The rest of the agent, built and started once the managed VPN gave the agent its address.

    ``build()`` returns the agent's service (or raises ``rcmp_node.StartupError``); ``on_error(message)`` is called
    when it cannot be built or started.
    """

    name = "after-vpn"

    def __init__(self, vpn, build, on_error):
        self.vpn = vpn
        self.build = build
        self.on_error = on_error
        self.agent = None

    def startService(self):
        super().startService()
        log.info("managed VPN: waiting for the address of %s before starting the agent", self.vpn.config.vpn_interface)
        self.vpn.wait_for_address().addCallback(self._start)

    def _start(self, address):
        if not self.running:
            return
        try:
            self.agent = self.build()
            self.agent.startService()
        except Exception as exc:  # StartupError, cannot listen: one line, as at a start without a managed VPN
            self.agent = None
            message = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            self.on_error(message)

    def stopService(self):
        super().stopService()
        agent, self.agent = self.agent, None
        if agent is not None and agent.running:
            return agent.stopService()
        return None


# -- command line -----------------------------------------------------------------------------------------

def add_parser(subparsers, home_default):
    """Add ``vpn`` and its four subcommands to ``rcmp_n``'s subcommands."""
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--home", metavar="DIR", default=argparse.SUPPRESS,
                        help=f"the platform folder (default: $RCMP_HOME, else {home_default})")
    vpn = subparsers.add_parser(
        "vpn", parents=[common], help="the platform's own VPN: init, client, revoke, list",
        description="The platform's own OpenVPN: its certificate authority and configurations live in HOME/vpn/ "
                    "(mode 0700). An agent whose HOME/vpn/ holds server.conf or client.conf runs OpenVPN itself.")
    commands = vpn.add_subparsers(dest="vpn_command", metavar="COMMAND", required=True)
    p = commands.add_parser("init", parents=[common], help="create the VPN on the master",
                            description="Create HOME/vpn/: a CA, the server's certificate and key, a revocation "
                                        "list and server.conf (OpenVPN 2.6, tun0, UDP, topology subnet, the "
                                        "master at the subnet's first host address).")
    p.add_argument("--subnet", type=_subnet, default=ipaddress.IPv4Network(DEFAULT_SUBNET), metavar="CIDR",
                   help=f"the VPN's subnet (default: {DEFAULT_SUBNET})")
    p.add_argument("--port", type=_port, default=DEFAULT_PORT, metavar="N",
                   help=f"OpenVPN's UDP port (default: {DEFAULT_PORT})")
    p.add_argument("--remote", type=_host, metavar="HOST",
                   help="the master's address as robots reach it (default: the address of ext_interface)")
    p.add_argument("--force", action="store_true", help="replace an existing VPN (every client file stops working)")
    p = commands.add_parser("client", parents=[common], help="issue a robot's (or, with --server, a server VM's) "
                                                             "client file",
                            description="Issue NAME a certificate (CN = NAME) and its fixed VPN address (the same "
                                        "every time) and write one self-contained OpenVPN client configuration. "
                                        "NAME's earlier certificates stop working. The certificate says what its "
                                        "holder may be: a robot, or with --server a server VM; the master accepts "
                                        "nothing else from it.")
    p.add_argument("name", type=_name, metavar="NAME",
                   help="the robot's instance name (its pi_name), or the server VM's name")
    p.add_argument("--server", action="store_true",
                   help="a server VM's certificate (its init.cfg says robot=no); default: a robot's")
    p.add_argument("--change-role", action="store_true",
                   help="issue NAME a certificate of the other role than it had (its old certificate is revoked)")
    p.add_argument("-o", "--output", metavar="FILE", help="write the client file here (mode 0600; default: stdout)")
    p.add_argument("--remote", type=_host_port, metavar="HOST[:PORT]",
                   help="the master as this robot reaches it (default: init's remote and port)")
    p = commands.add_parser("revoke", parents=[common], help="revoke a name's certificate and cut it off",
                            description="Revoke NAME's certificate; a connected client is cut off at once.")
    p.add_argument("name", type=_name, metavar="NAME")
    commands.add_parser("list", parents=[common], help="one line per name issued: NAME ADDRESS STATE ROLE",
                        description="One line per name issued: NAME ADDRESS connected|disconnected|revoked "
                                    "robot|server.")
    for parser in [vpn, *commands.choices.values()]:
        parser.epilog = EXIT_STATUSES
    return vpn


def _staged_file(output):
    """A ``stage`` for ``client``: the file is written beside ``output`` first and renamed once committed."""
    target = os.path.abspath(output)

    def stage(text):
        if os.path.isdir(target):
            raise VpnError(f"{output}: is a folder; give the client file's name", EXIT_USAGE)
        try:
            fd, tmp = tempfile.mkstemp(prefix=".rcmp-vpn-", dir=os.path.dirname(target))
            with os.fdopen(fd, "w", encoding="ascii") as f:
                os.fchmod(f.fileno(), 0o600)
                f.write(text)
                f.flush()
                os.fsync(f.fileno())
        except OSError as exc:
            raise VpnError(f"{output}: cannot write the client file: {exc.strerror or exc}") from None

        def finish(committed):
            if committed:
                os.replace(tmp, target)
            else:
                os.unlink(tmp)
        return finish
    return stage


def run(args, out=None, err=None, default_remote=None):
    """Run a parsed ``rcmp_n vpn ...`` command; returns the exit status. ``default_remote(home)``: see ``init``."""
    out = out or sys.stdout
    err = err or sys.stderr
    home = args.home
    try:
        if args.vpn_command != "init":
            _check_home(os.path.abspath(home), args.vpn_command)
        if args.vpn_command == "init":
            register = init(home, args.subnet, args.port, args.remote, args.force, default_remote)
            out.write(f"VPN created in {vpn_dir(home)}: subnet {register['subnet']}, master at "
                      f"{register['server_address']}, clients reach {register['remote']} UDP port "
                      f"{register['port']}\n")
        elif args.vpn_command == "client":
            remote, port = args.remote if args.remote else (None, None)
            stage = _staged_file(args.output) if args.output else None
            role = SERVER if args.server else ROBOT
            address, text = client(home, args.name, remote, port, stage=stage, role=role,
                                   change_role=args.change_role)
            if args.output:
                out.write(f"{args.name}: VPN address {address}, {role} certificate; client file written to "
                          f"{args.output}\n")
            else:
                out.write(text)
        elif args.vpn_command == "revoke":
            already, killed = revoke(home, args.name)
            state = "was already revoked" if already else "revoked"
            cut = "; its connection was cut" if killed else ""
            out.write(f"{args.name}: {state}{cut}\n")
        else:
            for name, address, state, role in listing(home):
                out.write(f"{name} {address} {state} {role}\n")
    except VpnError as exc:
        err.write(f"rcmp_n vpn {args.vpn_command}: {exc}\n")
        return exc.status
    except OSError as exc:
        err.write(f"rcmp_n vpn {args.vpn_command}: {exc.strerror or exc}"
                  f"{': ' + exc.filename if getattr(exc, 'filename', None) else ''}\n")
        return EXIT_FAILED
    return EXIT_OK
