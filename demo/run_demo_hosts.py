"""`./run demo-hosts`: the platform as it is deployed, a master and two robots on machines of their own, joined by
the platform's own VPN, on this one computer. Runs until Ctrl-C.

Each machine is a Linux network namespace (``tests/support/hosts.py``, the test hosts) with its own ``eth0`` on a
private LAN ``203.0.113.0/24`` whose bridge lives in a namespace of its own (nothing reaches the real network),
plus an ``office`` machine for the person's curl commands. On the master ``rcmp_n vpn init`` creates the VPN
(``198.51.100.0/24``) and ``rcmp_n vpn client`` issues each robot's client file, copied into the robot's
``HOME/vpn/client.conf``. Every agent runs with its default configuration (``tun0``, ``eth0``, ports 80 and 9999,
no address keys) and starts its own OpenVPN. The demo provisions the ``demo_patrol`` service logic (the simulated
robot on the robot side, the brain that steers it on the server side) for both robots, waits until both are
paired, and prints the original FIWARE Robotics guide's curl commands with the master's ``eth0`` address, run
from the office machine.

The master's RDAPI and console listen only inside the master's machine; so that this machine's browser can open
the console, a loopback port here (``--console-port``, default 8080 or the next free one) is forwarded to the
master's ``eth0`` port 80 (``demo/netns_relay.py``), and the demo prints the console's address as soon as the
master answers, then the robots' page links once they are paired.

Ctrl-C, SIGTERM or SIGHUP stops every agent (each stops its ROS processes, then its OpenVPN), closes the forwarded
port and removes every namespace, however the demo was started: in the foreground, in the background of a shell
(which starts background jobs with SIGINT ignored), through ``./run`` and make, or with no terminal. The demo
installs its own handlers for these signals for that reason (SIGHUP only when it is not ignored, as ``nohup``
asks); a second signal while it stops is answered with a line, not by leaving a half-removed network. Needs root.
"""

import argparse
import os
import shutil
import signal
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

from demo.run_demo import (  # noqa: E402  (the same service logic and console link as ./run demo)
    SERVICE_LOGIC, DemoError, console_link, first_free_port, port_is_free)

ROBOTS = ("robot1", "robot2")
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


class Stop(BaseException):
    """A stop signal arrived (Ctrl-C, SIGTERM, SIGHUP): unwind, removing everything on the way. A BaseException,
    as KeyboardInterrupt is, so that no ``except Exception`` on the way (a polling loop) takes it for a failure."""


def _say(text):
    """One line on standard output from a signal handler: os.write, as print may be half-way through a line."""
    try:
        os.write(sys.stdout.fileno(), text.encode() + b"\n")
    except (OSError, ValueError):
        pass


def _stopping_already(signum, frame):
    _say(f"demo-hosts: {signal.Signals(signum).name} again: still removing the machines, please wait")


def _stop(signum, frame):
    _say(f"\ndemo-hosts: {signal.Signals(signum).name}: stopping every agent and removing the machines")
    for sig in STOP_SIGNALS:
        if signal.getsignal(sig) is _stop:
            signal.signal(sig, _stopping_already)
    raise Stop(signal.Signals(signum).name)


def install_stop_handlers():
    """Our own handlers for SIGINT, SIGTERM and SIGHUP: SIGINT even when the shell that started the demo in the
    background set it to be ignored (Python then installs no KeyboardInterrupt of its own), SIGHUP unless it is
    ignored (``nohup``)."""
    for sig in STOP_SIGNALS:
        if sig == signal.SIGHUP and signal.getsignal(sig) == signal.SIG_IGN:
            continue
        signal.signal(sig, _stop)


def describe(p, robots, console):
    links = "\n  ".join(f"{name}: {console_link(console, name)}" for name in robots)
    office = p.office.netns
    base = f"http://{p.master_address}"
    run = f"ip netns exec {office} "
    lines = "\n".join(f"  {name}: VPN address {agent.vpn_address()}, paired" for name, agent in robots.items())
    print(f"""
The demo is running: the master's RDAPI on its eth0, {base} (VPN address 198.51.100.1), and two robots:
{lines}
The original guide's commands, run from the office machine on the same LAN (public_ip_master is {p.master_address}):

  {run}curl {base}
  {run}curl {base}/platform_instance/read
  {run}curl {base}/service_logic/read
  {run}curl "{base}/service_space/read?ss_name=robot1"

The platform's VPN, as the master sees it:

  cd {ROOT} && ip netns exec {p.master_host.netns} /usr/bin/python3 -m rcm_platform --home {p.master.home} vpn list

Watch them in a browser on this machine (the console, forwarded from the master's eth0 to this machine's
loopback; each robot's page opens on its /pose):

  Console: {console}/console/
  {links}

Logs: {os.path.join(p.root, '<machine>', 'log')} (rcmp.log, openvpn.log). Press Ctrl-C to stop everything.
""", flush=True)


def run(args):
    if os.geteuid() != 0:
        raise DemoError("the hosts are network namespaces: run it as root")
    from tests.support.hosts import Lan
    from demo.netns_relay import NetnsRelay
    from tests.support.vpn_hosts import VpnPlatform

    console_port = args.console_port or first_free_port("127.0.0.1", 8080)
    if not port_is_free("127.0.0.1", console_port):
        raise DemoError(f"port {console_port} on 127.0.0.1 is in use; choose another with --console-port")
    workdir = os.path.abspath(args.workdir)
    if os.path.isdir(workdir):
        shutil.rmtree(workdir)
    os.makedirs(workdir)
    with Lan(log_dir=None) as lan:
        print("demo-hosts: building the LAN, the master and the office machine; rcmp_n vpn init on the master",
              flush=True)
        p = VpnPlatform(lan, workdir, heartbeat=None)
        for name in ROBOTS:
            p.add_robot(name)
            print(f"demo-hosts: {name}: a machine of its own, its VPN client file from 'rcmp_n vpn client {name}'",
                  flush=True)
        print(f"demo-hosts: starting the master (RDAPI http://{p.master_address}/, OpenVPN on UDP 1194)", flush=True)
        p.master.start()
        try:
            p.wait_rdapi(timeout=60)
        except AssertionError as exc:
            raise DemoError(f"the master did not come up: {exc}; see {p.master.log_path}") from None
        relay = NetnsRelay(p.master_host.netns, p.master_address, 80, listen_port=console_port)
        try:
            relay.start()
        except OSError as exc:
            raise DemoError(f"cannot forward 127.0.0.1:{console_port} to the master: {exc}") from None
        try:
            console = f"http://127.0.0.1:{console_port}"
            print(f"demo-hosts: console on {console}/console/ (this machine's loopback, forwarded to the master's "
                  f"eth0 port 80): watch the robots connect", flush=True)
            p.rdapi_ok("POST", "/service_logic/provisioning", SERVICE_LOGIC)
            for name in ROBOTS:
                p.rdapi_ok("POST", "/platform_instance/provisioning",
                           {"pi_name": name, "pi_service_logic": SERVICE_LOGIC["slg_name"]})
                print(f"demo-hosts: provisioned {name}; starting its agent", flush=True)
                p.robots[name].start()
            for name in ROBOTS:
                try:
                    p.wait_state(name, True, True, timeout=args.timeout)
                except AssertionError as exc:
                    raise DemoError(f"{exc}; see {p.robots[name].log_path}") from None
            describe(p, p.robots, console)
            if args.exit_when_paired:
                return 0
            while True:
                for agent in [p.master, *p.robots.values()]:
                    if agent.process.poll() is not None:
                        raise DemoError(f"the agent of {agent.host.name} exited with status "
                                        f"{agent.process.returncode}; see {agent.log_path}")
                time.sleep(0.5)  # waiting for Ctrl-C
        finally:
            relay.stop()


def main(argv=None):
    install_stop_handlers()
    parser = argparse.ArgumentParser(prog="./run demo-hosts", description=__doc__.split("\n\n")[0])
    parser.add_argument("--workdir", default=os.path.join(ROOT, "build", "demo-hosts"),
                        help="where the machines' platform folders go (default: build/demo-hosts)")
    parser.add_argument("--console-port", type=int, default=int(os.environ.get("DEMO_CONSOLE_PORT", "0")),
                        help="the port on 127.0.0.1 forwarded to the master's console (default: 8080 or the next "
                             "free one; env DEMO_CONSOLE_PORT)")
    parser.add_argument("--timeout", type=float, default=120.0, help="seconds to wait for pairing (default 120)")
    parser.add_argument("--exit-when-paired", action="store_true",
                        help="stop everything as soon as both robots are paired (used by the tests)")
    status = 0
    try:
        args = parser.parse_args(argv)
        status = run(args)
    except DemoError as exc:
        print(f"demo-hosts: {exc}", file=sys.stderr)
        status = 1
    except Stop:
        pass        # said when it arrived; everything is removed by now
    except SystemExit as exc:       # argparse: --help, or a wrong option
        return exc.code
    print("demo-hosts: stopped; every machine (namespace) and process removed", flush=True)
    return status


if __name__ == "__main__":
    sys.exit(main())
