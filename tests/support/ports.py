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


def _ephemeral_low():
    try:
        with open("/proc/sys/net/ipv4/ip_local_port_range") as f:
            return int(f.read().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


def stable_free_ports(count, host="127.0.0.1"):
    """``count`` distinct free ports below the kernel's ephemeral range, for servers that bind a port the test
    chose for them some time later (a ROS master, rcm_driver, FIROS): a port inside that range can be taken
    meanwhile by any process's outgoing or port-0 socket, as the product's defaults (11311, 9998, 10100) cannot."""
    import random
    rng = random.Random()
    chosen = []
    for _ in range(400 * count):
        port = rng.randrange(20000, _ephemeral_low() - 64)
        if port not in chosen and not port_accepts(port, host, timeout=0.05) and _bindable(port, host):
            chosen.append(port)
            if len(chosen) == count:
                return chosen
    raise RuntimeError(f"no {count} free ports between 20000 and {_ephemeral_low()}")


def ros_port_base(host="127.0.0.1"):
    """A base for the ROS masters of service spaces (see stable_free_ports): the manager takes it or the next
    free port above."""
    return stable_free_ports(1, host)[0]


def _bindable(port, host):
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        try:
            sock.bind((host, port))
            return True
        except OSError:
            return False
