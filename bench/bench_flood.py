"""Flood benchmark: the RDAPI stays answerable while the agent port is flooded to its cap.

Starts a real master (``/usr/bin/python3 -m rcm_platform --home TMP``) on loopback with the open-file limit the
installed daemon gives it (``rcmpd``: 65536, or this machine's hard limit if lower), provisions 100 robots, then
measures ``GET /platform_instance/read`` three times with ``wrk`` (keep-alive) and with fresh connections (one TCP
connection per request, as ``curl`` does):

1. quiet;
2. with the agent port flooded: connections from many loopback addresses (up to the port's per-address cap
   each), half idle, half sending a frame a byte every 2 s, reconnecting 0.2 s after the agent closes them,
   aiming at the port's cap plus 64 (the extra ones are refused);
3. as 2, plus the RDAPI itself held by idle and slow connections from other addresses up to its own cap less
   the connections the measurement needs.

Target: RDAPI p99 under 100 ms in every phase. Results go to docs/PERFORMANCE.md (``bench.report``); ``main``
returns 1 when the target is missed. Measure at a quiet moment: the table records the load average.
"""

import argparse
import asyncio
import http.client
import json
import math
import os
import resource
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

from bench.bench_rdapi import median_run, post, run_wrk  # noqa: E402
from bench.report import percentile, write_section  # noqa: E402
from tests.support.processes import ProcessGroup  # noqa: E402
from tests.support.rcmp_agent import RcmpAgent  # noqa: E402

ROBOTS = 100
TARGET_P99_MS = 100.0
DAEMON_NOFILE = 65536          # what rcmpd gives the agent
WRK_CONNECTIONS = 8
RECONNECT_DELAY = 0.2
SLOW_INTERVAL = 2.0


class Flood:
    """Keeps ``count`` connections to ``host:port`` open from the given source addresses, in a thread of its own.

    Half are idle, half slow (a frame header announcing 4000 bytes, then a byte every ``SLOW_INTERVAL``). A
    connection the server closes (or refuses) is opened again ``RECONNECT_DELAY`` later, as an attacker would.
    """

    def __init__(self, host, port, sources, count, slow_payload):
        self.host, self.port = host, port
        self.slots = [(sources[i % len(sources)], i % 2 == 1) for i in range(count)]
        self.slow_payload = slow_payload
        self.loop = asyncio.new_event_loop()
        self.stopping = False
        self.connects = 0
        self.closed_by_server = 0
        self.connect_errors = 0
        self.thread = threading.Thread(target=self._run, daemon=True)
        self._tasks = []

    def start(self):
        self.thread.start()
        return self

    def _run(self):
        asyncio.set_event_loop(self.loop)
        self._tasks = [self.loop.create_task(self._slot(source, slow)) for source, slow in self.slots]
        self.loop.run_until_complete(self._until_stopped())

    async def _until_stopped(self):
        while not self.stopping:
            await asyncio.sleep(0.1)
        for t in self._tasks:
            t.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)

    async def _slot(self, source, slow):
        while not self.stopping:
            try:
                reader, writer = await asyncio.open_connection(self.host, self.port, local_addr=(source, 0))
            except OSError:
                self.connect_errors += 1
                await asyncio.sleep(RECONNECT_DELAY)
                continue
            self.connects += 1
            payload = iter(self.slow_payload)
            try:
                while True:
                    try:
                        data = await asyncio.wait_for(reader.read(4096), SLOW_INTERVAL)
                    except asyncio.TimeoutError:
                        if slow:
                            byte = next(payload, b" ")
                            writer.write(byte if isinstance(byte, bytes) else bytes([byte]))
                        continue
                    if not data:
                        self.closed_by_server += 1
                        break
            except (OSError, asyncio.IncompleteReadError):
                self.closed_by_server += 1
            finally:
                writer.close()
            await asyncio.sleep(RECONNECT_DELAY)

    def stop(self):
        self.stopping = True
        self.thread.join(30)


def established(port):
    """Connections the server side of ``port`` holds now (``ss``: established, local port ``port``)."""
    out = subprocess.run(["ss", "-Htn", "state", "established", f"( sport = :{port} )"], capture_output=True,
                         text=True, timeout=30, check=True).stdout
    return sum(1 for line in out.splitlines() if line.strip())


def fresh_connection_latencies(host, port, count):
    """Milliseconds of ``count`` sequential GETs, each on a new connection; failures as None."""
    out = []
    for _ in range(count):
        start = time.perf_counter()
        try:
            conn = http.client.HTTPConnection(host, port, timeout=5)
            conn.request("GET", "/platform_instance/read")
            resp = conn.getresponse()
            resp.read()
            conn.close()
            out.append((time.perf_counter() - start) * 1000 if resp.status == 200 else None)
        except (OSError, http.client.HTTPException):
            out.append(None)
    return out


def addresses(prefix_octet, count):
    return [f"127.{prefix_octet}.{i // 250}.{i % 250 + 1}" for i in range(count)]


def main(argv=None):
    parser = argparse.ArgumentParser(prog="bench_flood", description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=int, default=8, help="seconds per wrk run (default 8)")
    parser.add_argument("--repeat", type=int, default=3, help="wrk runs per phase; the median is shown")
    parser.add_argument("--fresh", type=int, default=200, help="fresh-connection requests per phase")
    parser.add_argument("--no-report", action="store_true", help="print only; do not write docs/PERFORMANCE.md")
    args = parser.parse_args([] if argv is None else argv)

    from rcm_platform import rcmp_ext_connector as rdapi, rcmp_inter_communication as ic
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    nofile = DAEMON_NOFILE if hard == resource.RLIM_INFINITY else min(hard, DAEMON_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (nofile, hard))   # the master inherits it, as from rcmpd
    port_cap = ic.default_max_connections() if hasattr(ic, "default_max_connections") else None
    per_address = getattr(ic, "MAX_PER_ADDRESS", 8)
    flood_count = (port_cap or 1100) + 64
    rdapi_flood = rdapi.MAX_CONNECTIONS - WRK_CONNECTIONS - 8

    results, counts = {}, {}
    with tempfile.TemporaryDirectory(prefix="bench-flood-") as tmp, ProcessGroup(log_dir=tmp) as procs:
        master = RcmpAgent(procs, os.path.join(tmp, "master"), args=["--no-stderr", "--log-level", "WARNING"])
        master.start()
        base = master.base_url
        post(base, "/service_logic/provisioning", {"slg_name": "bench_logic"})
        for i in range(ROBOTS):
            post(base, "/platform_instance/provisioning", {"pi_name": f"bench_robot_{i}",
                                                           "pi_service_logic": "bench_logic"})
        url = base + "/platform_instance/read"
        load_before = os.getloadavg()[0]

        def measure(phase):
            run_wrk(url, WRK_CONNECTIONS, 1, 1)  # warm-up
            wrk = median_run([run_wrk(url, WRK_CONNECTIONS, 1, args.duration) for _ in range(args.repeat)])
            fresh = fresh_connection_latencies(master.host, master.ext_port, args.fresh)
            ok = [v for v in fresh if v is not None]
            results[phase] = dict(wrk, fresh_p50=percentile(ok, 0.5) if ok else float("nan"),
                                  fresh_p99=percentile(ok, 0.99) if ok else float("nan"),
                                  fresh_failed=len(fresh) - len(ok))

        measure("quiet")

        frame = b"\x00\x00\x0f\xa0" + b'{"v": 1, "id": 1, "kind": "req", "op": "hello", "body": {"name": "'
        agent_flood = Flood(master.host, master.ic_port, addresses(2, math.ceil(flood_count / per_address)),
                            flood_count, frame).start()
        expected = min(port_cap or flood_count, flood_count)
        deadline = time.monotonic() + 60
        while established(master.ic_port) < expected * 0.95 and time.monotonic() < deadline:
            time.sleep(0.5)
        counts["agent port held"] = established(master.ic_port)
        measure("agent port flooded")
        counts["agent port held after"] = established(master.ic_port)

        rdapi_slow = b"GET /platform_instance/read HTTP/1.1\r\nHost: x\r\nX-Slow: "
        rdapi_holders = Flood(master.host, master.ext_port,
                              addresses(3, math.ceil(rdapi_flood / rdapi.MAX_PER_ADDRESS)), rdapi_flood,
                              rdapi_slow).start()
        deadline = time.monotonic() + 30
        while established(master.ext_port) < rdapi_flood * 0.95 and time.monotonic() < deadline:
            time.sleep(0.5)
        counts["RDAPI held"] = established(master.ext_port)
        measure("agent port and RDAPI flooded")
        counts["agent port held at the end"] = established(master.ic_port)
        rdapi_holders.stop()
        agent_flood.stop()
        counts["flood connects"] = agent_flood.connects + rdapi_holders.connects
        counts["closed or refused by the master"] = agent_flood.closed_by_server + rdapi_holders.closed_by_server
        alive = json.loads(urllib.request.urlopen(url, timeout=10).read())["result"] == "OK"
        load_after = os.getloadavg()[0]
        assert master.stop() == 0

    failed = [f"{phase}: p99 {r['p99']:.1f} ms (wrk), {r['fresh_p99']:.1f} ms (fresh connections)"
              for phase, r in results.items()
              if not (r["p99"] < TARGET_P99_MS and r["fresh_p99"] < TARGET_P99_MS) or r["errors"] or r["non2xx"]
              or r["fresh_failed"]]
    if not alive:
        failed.append("the RDAPI did not answer after the flood")
    rows = ["| phase | requests/s | p50 ms | p99 ms | errors | fresh connections p50 ms | p99 ms | failed |",
            "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for phase, r in results.items():
        rows.append(f"| {phase} | {r['rps']:.0f} | {r['p50']:.2f} | {r['p99']:.2f} | {r['errors'] + r['non2xx']} | "
                    f"{r['fresh_p50']:.2f} | {r['fresh_p99']:.2f} | {r['fresh_failed']} of {args.fresh} |")
    cap_text = (f"the agent port's cap is {port_cap} connections ({per_address} per address; a quarter of the "
                f"{nofile} open files)" if port_cap else
                f"the agent port has no cap in this build: {flood_count} connections were aimed at it")
    body = "\n".join([
        f"`bench/bench_flood.py`: a real master on loopback, open-file limit {nofile} (as `rcmpd` sets it), "
        f"{ROBOTS} provisioned robots; `GET /platform_instance/read` measured with `wrk -t1 -c{WRK_CONNECTIONS}` "
        f"(median of {args.repeat} runs of {args.duration} s) and with {args.fresh} requests each on a new "
        f"connection. Flood: {flood_count} connections aimed at the agent port from "
        f"{math.ceil(flood_count / per_address)} loopback addresses, half idle, half sending a frame a byte "
        f"every {SLOW_INTERVAL:g} s, each reconnecting {RECONNECT_DELAY:g} s after it is closed; {cap_text}. "
        f"In the last phase {rdapi_flood} more idle/slow connections hold the RDAPI (its cap is "
        f"{rdapi.MAX_CONNECTIONS}, {rdapi.MAX_PER_ADDRESS} per address). 1-minute load average "
        f"{load_before:.1f} before, {load_after:.1f} after.",
        "",
        *rows,
        "",
        "Connections held: " + ", ".join(f"{k} {v}" for k, v in counts.items()) + ".",
        "",
        f"Target: RDAPI p99 under {TARGET_P99_MS:.0f} ms with the agent port flooded: "
        f"{'met' if not failed else 'MISSED: ' + '; '.join(failed)}.",
    ])
    print(body)
    if not args.no_report:
        write_section("flood", "RDAPI under a connection flood", body)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
