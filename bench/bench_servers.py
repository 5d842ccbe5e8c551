"""Server VMs benchmark: spreading robots over the master and two server VMs, and moving
the spaces of a server VM that dies.

(spread) ``--robots`` robots (default 100; one S-side and one R-side ``talker.py`` each) started at once against a
    master and two server VMs (agents with ``robot=no`` on 127.0.3.10 and .11, each with its own
    ``ros_port_base``), every one with ``max_service_spaces`` 100: the time until all are paired, p50/p99 per robot,
    and how many spaces each server got (``platform_instance/read?pi_type=S``). The load rule should spread them
    evenly (ties to the master, then by name).
(failover) ``--failover-spaces`` robots (default 30) paired with their spaces on server VM vm1 (the master a pure
    coordinator, ``max_service_spaces=0``), then vm2 joins and vm1 is SIGKILLed: the time from the kill until every
    one of those robots is paired again on vm2 (target: under 30 s), and the robot sessions that ended on the way
    (should be none: the robots do nothing).

Real agents and real ROS on loopback, as the lifecycle tests (``tests.support.lifecycle``). ``--quick``: 12 robots
and 6 spaces, to check the benchmark itself. Results go to docs/PERFORMANCE.md (section ``servers``) unless
``--no-write``; ``main`` returns 1 when a target is missed or a phase fails.

Run: ``bash scripts/with-overlay.sh /usr/bin/python3 -m bench.bench_servers [--quick] [--only spread|failover]``.
"""

import argparse
import contextlib
import os
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

from bench.bench_lifecycle import LOGIC  # noqa: E402
from bench.report import load_average, percentile, write_section  # noqa: E402
from tests.support.lifecycle import Platform  # noqa: E402
from tests.support.polling import WaitTimeout, wait_until  # noqa: E402
from tests.support.ports import ros_port_base  # noqa: E402
from tests.support.processes import ProcessGroup  # noqa: E402

OPTIONS = ("--quick",)           # what bench.run_all may pass on
TARGET_FAILOVER_S = 30.0
VM_ADDRESS = {"vm1": "127.0.3.10", "vm2": "127.0.3.11"}


class BenchFailure(Exception):
    """A phase could not be measured; str() says why."""


def start_server(plat, name, capacity):
    vm = plat.robot(name, VM_ADDRESS[name], role="server", max_service_spaces=capacity,
                    ros_port_base=ros_port_base(VM_ADDRESS[name]), log_max_bytes=10 * 1024 * 1024)
    vm.start()
    wait_until(lambda: name in servers(plat), timeout=30, message=f"server {name} to join")
    return vm


def servers(plat):
    status, answer = plat.master.get("/platform_instance/read?pi_type=S")
    if status != 200:
        raise BenchFailure(f"platform_instance/read?pi_type=S answered {status}: {answer}")
    return {row["pi_name"]: row for row in answer["reason"] if row["connected"]}


def provision(plat, names):
    plat.provision_logic("bench_servers", sn_list=LOGIC)
    for name in names:
        plat.provision_robot(name, "bench_servers")


def spread(plat, count, timeout):
    plat.master.start()
    start_server(plat, "vm1", 100)
    start_server(plat, "vm2", 100)
    names = [f"spreadbot{n}" for n in range(1, count + 1)]
    provision(plat, names)
    marks = plat.log_marks()
    load_before = load_average()
    started_at = time.monotonic()
    started = plat.start_herd(names, log_max_bytes=10 * 1024 * 1024)
    try:
        per_robot = plat.wait_all_paired(names, timeout=timeout, started=started, interval=0.2)
    except WaitTimeout as exc:
        raise BenchFailure(str(exc)) from None
    elapsed = time.monotonic() - started_at
    rows = servers(plat)
    sessions = plat.session_log(names, marks)
    figures = {"count": count, "elapsed": elapsed, "per_robot": sorted(per_robot.values()),
               "spread": {name: len(row["service_spaces"]) for name, row in rows.items()},
               "lost": len(sessions.ended), "load": (load_before, load_average())}
    plat.stop_robots(names)
    return figures


def failover(plat, count, timeout):
    plat.master.start()
    vm1 = start_server(plat, "vm1", count)
    names = [f"movebot{n}" for n in range(1, count + 1)]
    provision(plat, names)
    plat.start_herd(names, log_max_bytes=10 * 1024 * 1024)
    try:
        plat.wait_all_paired(names, timeout=timeout, interval=0.2)
    except WaitTimeout as exc:
        raise BenchFailure(f"before the kill: {exc}") from None
    if sorted(servers(plat)["vm1"]["service_spaces"]) != sorted(names):
        raise BenchFailure(f"vm1 does not host the {count} spaces: {servers(plat)}")
    start_server(plat, "vm2", count)
    marks = plat.log_marks()
    load_before = load_average()
    vm1.kill()
    killed = time.monotonic()

    def moved():
        rows = plat.instances()
        return all(rows[n]["connected"] and rows[n]["paired"] and rows[n].get("server") == "vm2" for n in names)
    try:
        wait_until(moved, timeout=timeout, interval=0.2, message=f"the {count} robots paired again on vm2")
    except WaitTimeout as exc:
        raise BenchFailure(str(exc)) from None
    elapsed = time.monotonic() - killed
    sessions = plat.session_log(names, marks)
    figures = {"count": count, "elapsed": elapsed, "lost": len(sessions.ended),
               "load": (load_before, load_average()), "heartbeat": plat.heartbeat}
    plat.stop_robots(names)
    return figures


def run_phase(phase, tmp, args):
    procs = ProcessGroup(log_dir=os.path.join(tmp, phase))
    plat = Platform(procs, os.path.join(tmp, phase, "platform"), heartbeat=args.heartbeat, inbound_ports=0,
                    log_max_bytes=100 * 1024 * 1024, max_service_spaces=0 if phase == "failover" else 100)
    try:
        if phase == "spread":
            return spread(plat, args.robots, args.timeout)
        return failover(plat, args.failover_spaces, args.timeout)
    except BenchFailure as exc:
        return exc
    finally:
        try:
            procs.stop_all()
        finally:
            plat.kill_leftovers()


def section(results, args):
    ok = True
    parts = []
    figures = results.get("spread")
    if isinstance(figures, Exception):
        ok = False
        parts.append(f"### Spread\n\n**Not measured: {figures}**\n")
    elif figures is not None:
        per = figures["per_robot"]
        shares = ", ".join(f"{name} {n}" for name, n in figures["spread"].items())
        parts.append(f"""### Spread: {figures["count"]} robots over the master and two server VMs

`bench/bench_servers.py{" --quick" if args.quick else ""}`: {figures["count"]} robot agents started at once; the
master and server VMs vm1, vm2 (127.0.3.10, .11) each with `max_service_spaces` 100; heartbeats every
{args.heartbeat:g} s. Load average (1 / 5 min) {figures["load"][0]} before, {figures["load"][1]} after.

| measure | value |
| --- | --- |
| time until all {figures["count"]} are paired | **{figures["elapsed"]:.1f} s** |
| per robot, start → paired, p50 / p99 | {percentile(per, 0.5):.1f} s / {percentile(per, 0.99):.1f} s |
| spaces per server | {shares} |
| robot sessions ended on the way | {figures["lost"]} |
""")
    figures = results.get("failover")
    if isinstance(figures, Exception):
        ok = False
        parts.append(f"### Failover\n\n**Not measured: {figures}**\n")
    elif figures is not None:
        met = figures["elapsed"] < TARGET_FAILOVER_S
        ok = ok and met
        parts.append(f"""### Failover: a server VM hosting {figures["count"]} spaces SIGKILLed

The master a pure coordinator (`max_service_spaces=0`), {figures["count"]} robots paired with their spaces on vm1,
then vm2 joins and vm1 gets SIGKILL. Heartbeats every {figures["heartbeat"]:g} s, 3 misses: the master notices
after about {3 * figures["heartbeat"]:g} s. Load average {figures["load"][0]} before, {figures["load"][1]} after.

| measure | value | target |
| --- | --- | --- |
| SIGKILL → all {figures["count"]} robots paired again on vm2 | **{figures["elapsed"]:.1f} s** | < {TARGET_FAILOVER_S:.0f} s: {"met" if met else "NOT met"} |
| robot sessions ended on the way | {figures["lost"]} | 0 |
""")
    return "\n".join(parts), ok


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="12 robots and 6 spaces (checks the benchmark)")
    parser.add_argument("--robots", type=int, help="robots of the spread phase (default 100)")
    parser.add_argument("--failover-spaces", type=int, help="spaces on the killed server (default 30)")
    parser.add_argument("--only", choices=("spread", "failover"), help="run one phase")
    parser.add_argument("--heartbeat", type=float, default=2.0, help="heartbeat_interval (default 2.0)")
    parser.add_argument("--timeout", type=float, default=180.0, help="seconds to wait in each phase (default 180)")
    parser.add_argument("--work", metavar="DIR", help="keep the agents' folders and logs in DIR")
    parser.add_argument("--no-write", action="store_true", help="print, do not write docs/PERFORMANCE.md")
    args = parser.parse_args(argv)
    args.robots = args.robots or (12 if args.quick else 100)
    args.failover_spaces = args.failover_spaces or (6 if args.quick else 30)
    if args.work:
        os.makedirs(args.work, exist_ok=True)
    results = {}
    with (contextlib.nullcontext(args.work) if args.work
          else tempfile.TemporaryDirectory(prefix="bench-servers-")) as tmp:
        for phase in ("spread", "failover"):
            if args.only in (None, phase):
                results[phase] = run_phase(phase, tmp, args)
    body, ok = section(results, args)
    print(body)
    if not args.no_write:
        write_section("servers", "Server VMs: spread and failover", body)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
