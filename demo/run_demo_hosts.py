"""`./run demo-hosts`: the platform as it is deployed, a master and two robots on machines of their own, joined by
the platform's own VPN, on this one computer. Runs until Ctrl-C.

Each machine is a Linux network namespace (``tests/support/hosts.py``, the test hosts) with its own ``eth0`` on a
private LAN ``203.0.113.0/24`` whose bridge lives in a namespace of its own (nothing reaches the real network),
plus an ``office`` machine for the person's curl commands. On the master ``rcmp_n vpn init`` creates the VPN
(``198.51.100.0/24``) and ``rcmp_n vpn client`` issues each robot's client file, copied into the robot's
``HOME/vpn/client.conf``. Every agent runs with its default configuration (``tun0``, ``eth0``, ports 80 and 9999,
no address keys) and starts its own OpenVPN. The demo provisions the ``demo_patrol`` service logic (the simulated
robot on the robot side, the brain that steers it on the server side) for both robots, waits until both are
paired, and prints the seed guide's curl commands with the master's ``eth0`` address, run from the office machine.
Ctrl-C (or SIGTERM) stops every agent (each stops its ROS processes, then its OpenVPN) and removes every
namespace. Needs root.
"""

import argparse
import os
import shutil
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

from demo.run_demo import SERVICE_LOGIC  # noqa: E402  (the same service logic as ./run demo)

ROBOTS = ("robot1", "robot2")


class DemoError(Exception):
    """Something the person running the demo must fix; printed as one line."""


def describe(p, robots):
    office = p.office.netns
    base = f"http://{p.master_address}"
    run = f"ip netns exec {office} "
    lines = "\n".join(f"  {name}: VPN address {agent.vpn_address()}, paired" for name, agent in robots.items())
    print(f"""
The demo is running: the master's RDAPI on its eth0, {base} (VPN address 198.51.100.1), and two robots:
{lines}
The seed guide's commands, run from the office machine on the same LAN (public_ip_master is {p.master_address}):

  {run}curl {base}
  {run}curl {base}/platform_instance/read
  {run}curl {base}/service_logic/read
  {run}curl "{base}/service_space/read?ss_name=robot1"

The platform's VPN, as the master sees it:

  cd {ROOT} && ip netns exec {p.master_host.netns} /usr/bin/python3 -m rcm_platform --home {p.master.home} vpn list

Logs: {os.path.join(p.root, '<machine>', 'log')} (rcmp.log, openvpn.log). Press Ctrl-C to stop everything.
""", flush=True)


def run(args):
    if os.geteuid() != 0:
        raise DemoError("the hosts are network namespaces: run it as root")
    from tests.support.hosts import Lan
    from tests.support.polling import wait_until
    from tests.support.vpn_hosts import VpnPlatform

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
        describe(p, p.robots)
        if args.exit_when_paired:
            return 0
        while True:
            for agent in [p.master, *p.robots.values()]:
                if agent.process.poll() is not None:
                    raise DemoError(f"the agent of {agent.host.name} exited with status "
                                    f"{agent.process.returncode}; see {agent.log_path}")
            time.sleep(0.5)  # waiting for Ctrl-C


def main(argv=None):
    parser = argparse.ArgumentParser(prog="./run demo-hosts", description=__doc__.split("\n\n")[0])
    parser.add_argument("--workdir", default=os.path.join(ROOT, "build", "demo-hosts"),
                        help="where the machines' platform folders go (default: build/demo-hosts)")
    parser.add_argument("--timeout", type=float, default=120.0, help="seconds to wait for pairing (default 120)")
    parser.add_argument("--exit-when-paired", action="store_true",
                        help="stop everything as soon as both robots are paired (used by the tests)")
    args = parser.parse_args(argv)
    try:
        status = run(args)
    except DemoError as exc:
        print(f"demo-hosts: {exc}", file=sys.stderr)
        status = 1
    except (KeyboardInterrupt, SystemExit) as exc:  # Ctrl-C; SIGTERM arrives as SystemExit from the LAN
        status = 0 if isinstance(exc, KeyboardInterrupt) or exc.code in (None, 0, 143) else exc.code
    print("demo-hosts: stopped; every machine (namespace) and process removed", flush=True)
    return status


if __name__ == "__main__":
    sys.exit(main())
