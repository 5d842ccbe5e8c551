"""Free TCP ports chosen at run time (never fixed numbers in tests)."""

import socket


def free_port(host="127.0.0.1"):
    """Return a TCP port on ``host`` that nothing listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((host, 0))
        return sock.getsockname()[1]


def free_ports(count, host="127.0.0.1"):
    """Return ``count`` distinct free ports (all held open together while choosing, so they differ)."""
    socks = []
    try:
        for _ in range(count):
            sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            sock.bind((host, 0))
            socks.append(sock)
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


def port_accepts(port, host="127.0.0.1", timeout=0.2):
    """True when something accepts TCP connections on host:port."""
    try:
        with socket.create_connection((host, port), timeout=timeout):
            return True
    except OSError:
        return False


def ros_port_base(span=64, host="127.0.0.1"):
    """A base for the ROS masters of service spaces: ``span`` consecutive free ports below the kernel's
    ephemeral range. Ports inside that range can be taken by any process's outgoing or port-0 sockets between
    the moment a port is found free and the moment rosmaster binds it, as 11311 (the product's default) cannot."""
    import random
    try:
        with open("/proc/sys/net/ipv4/ip_local_port_range") as f:
            ephemeral_low = int(f.read().split()[0])
    except (OSError, ValueError, IndexError):
        ephemeral_low = 32768
    rng = random.Random()
    for _ in range(200):
        base = rng.randrange(20000, ephemeral_low - span)
        if all(not port_accepts(port, host, timeout=0.05) and _bindable(port, host) for port in (base, base + 1)):
            return base
    raise RuntimeError(f"no free port base between 20000 and {ephemeral_low}")


def _bindable(port, host):
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        try:
            sock.bind((host, port))
            return True
        except OSError:
            return False
