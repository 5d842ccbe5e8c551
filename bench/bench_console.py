"""Console benchmark: how long a state change takes to show on the page, with 100 robots provisioned (issue 11).

Starts a real master (``/usr/bin/python3 -m rcm_platform --home TMP``) on loopback, provisions a service logic
with 50 service nodes and 100 robots with it through the RDAPI, opens the console in a real headless Chromium
(the browser tests' ``tests.support.browser``) and then, ``ROUNDS`` times, provisions one more robot (a committed
write of the robotics data) and removes it again. Each change is timed from just before its RDAPI call to the
moment the page's DOM shows it (a MutationObserver in the page notes ``Date.now()``; the benchmark and the browser
read the same clock). Beside that, a plain event-stream client (``/console/api/events``) times the push alone,
and the page reports how long rendering a full snapshot of 100 robots takes. Results go to docs/PERFORMANCE.md.
Target (issue 11): p99 under 1 s from a change to the page. ``main`` returns 1 when it is missed.
"""

import argparse
import datetime
import json
import os
import re
import statistics
import sys
import tempfile
import threading
import time
import urllib.request

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

from bench.report import percentile, write_section  # noqa: E402
from tests.support.browser import Browser  # noqa: E402
from tests.support.polling import wait_until  # noqa: E402
from tests.support.ports import ros_port_base  # noqa: E402
from tests.support.processes import ProcessGroup  # noqa: E402
from tests.support.rcmp_agent import RcmpAgent  # noqa: E402

ROBOTS = 100
ITEMS = 50
ROUNDS = 40
LIVE_ROUNDS = 5
TARGET_P99_S = 1.0

WATCH_JS = """
window.benchSeen = {};
const note = () => {
  for (const row of document.querySelectorAll('#robots tbody tr')) {
    const name = row.dataset.name;
    if (name.startsWith('lat_') && !(name in window.benchSeen)) window.benchSeen[name] = Date.now();
  }
  for (const name of Object.keys(window.benchSeen)) {
    const gone = 'gone:' + name;
    if (!name.startsWith('gone:') && !(gone in window.benchSeen)
        && !document.querySelector(`#robots tr[data-name="${name}"]`)) window.benchSeen[gone] = Date.now();
  }
};
new MutationObserver(note).observe(document.querySelector('#robots tbody'), {childList: true, subtree: true});
"""


LIVE_JS = """
window.liveSeen = {};
const look = () => {
  const row = document.querySelector('#robots tr[data-name="live_bot"]');
  if (!row) return;
  const state = row.cells[2].textContent + ' / ' + row.cells[3].textContent;
  if (!(state in window.liveSeen)) window.liveSeen[state] = Date.now();
};
new MutationObserver(look).observe(document.querySelector('#robots tbody'),
                                   {childList: true, subtree: true, characterData: true});
"""


def log_time(text, pattern):
    """Epoch seconds of the last log line matching ``pattern`` (the log's local-time stamps, ms resolution)."""
    stamps = re.findall(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}) .*" + pattern, text, re.M)
    if not stamps:
        return None
    return datetime.datetime.strptime(stamps[-1], "%Y-%m-%d %H:%M:%S,%f").timestamp()


class StreamClock:
    """A plain client of /console/api/events noting when each robot name first (and last) appears in a push."""

    def __init__(self, url):
        self.seen = {}
        self.present = set()
        self.response = urllib.request.urlopen(url, timeout=60)
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self):
        event = None
        try:
            for raw in self.response:
                line = raw.decode().rstrip("\n")
                if line.startswith("event: "):
                    event = line[7:]
                elif line.startswith("data: ") and event in ("snapshot", "patch"):
                    robots = json.loads(line[6:]).get("robots")
                    if robots is None:
                        continue
                    now = time.time()
                    if isinstance(robots, list):        # a snapshot: every robot
                        names = {r["pi_name"] for r in robots}
                    else:                               # a patch: the rows changed and the names gone
                        names = (self.present | set(robots.get("changed", {}))) - set(robots.get("gone", []))
                    for name in names - self.present:
                        self.seen.setdefault(name, now)
                    for name in self.present - names:
                        self.seen.setdefault("gone:" + name, now)
                    self.present = names
        except (OSError, ValueError, AttributeError):  # closed under the reader at the end
            pass

    def close(self):
        self.response.close()


def main(argv=None):
    parser = argparse.ArgumentParser(prog="bench_console", description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=ROUNDS)
    parser.add_argument("--live-rounds", type=int, default=LIVE_ROUNDS)
    parser.add_argument("--no-write", action="store_true", help="print the results, leave PERFORMANCE.md alone")
    args = parser.parse_args(argv)
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="bench-console-") as tmp, ProcessGroup(log_dir=tmp) as procs:
        master = RcmpAgent(procs, os.path.join(tmp, "master"), args=["--no-stderr"],
                           ros_port_base=ros_port_base())
        master.start()
        nodes = [{"sn_package": "robotics_test", "sn_type": "talker.py", "sn_name": f"talker_{j}",
                  "sn_params": f"_topic:=chat_{j}", "sn_side": "S" if j % 2 else "R"} for j in range(ITEMS)]
        status, answer = master.post("/service_logic/provisioning", {"slg_name": "fifty", "sn_list": nodes})
        assert status == 200, answer
        for i in range(ROBOTS):
            status, answer = master.post("/platform_instance/provisioning",
                                         {"pi_name": f"robot_{i:03d}", "pi_service_logic": "fifty"})
            assert status == 200, answer
        browser = Browser(procs, os.path.join(tmp, "browser"))
        stream = None
        try:
            driver = browser.driver
            driver.get(master.base_url + "/console/")
            wait_until(lambda: driver.execute_script("return document.querySelectorAll('#robots tbody tr').length")
                       == ROBOTS, timeout=30, message="the console to show the 100 robots")
            render_ms = float(driver.execute_script("return document.body.dataset.renderMs") or 0)
            driver.execute_script(WATCH_JS)
            stream = StreamClock(master.base_url + "/console/api/events")
            page, push = [], []
            for n in range(args.rounds):
                name = f"lat_{n}"
                for kind, path in (("", "/platform_instance/provisioning"), ("gone:", "/platform_instance/r_provisioning")):
                    started = time.time()
                    body = {"pi_name": name, "pi_service_logic": "empty"} if not kind else {"pi_name": name}
                    status, answer = master.post(path, body)
                    assert status == 200, answer
                    key = kind + name
                    at = wait_until(lambda: driver.execute_script("return window.benchSeen[arguments[0]]", key),
                                    timeout=10, interval=0.005, message=f"the page to show {key}")
                    page.append(at / 1000.0 - started)
                    wait_until(lambda: key in stream.seen, timeout=10, interval=0.005,
                               message=f"the stream to push {key}")
                    push.append(stream.seen[key] - started)
            # live state: a real robot agent connects and pairs (no RDAPI call); timed from the master's log lines
            # ("robot live_bot connected from", "robot live_bot paired") to the page showing each state
            status, answer = master.post("/platform_instance/provisioning",
                                         {"pi_name": "live_bot", "pi_service_logic": "empty"})
            assert status == 200, answer
            connect, pair = [], []
            for n in range(args.live_rounds):
                driver.execute_script(LIVE_JS)
                robot = RcmpAgent(procs, os.path.join(tmp, f"live_bot{n}"), role="robot", name="live_bot",
                                  vpn_address="127.0.0.2", ip_master="127.0.0.1", ic_port=master.ic_port)
                robot.start()
                seen = wait_until(lambda: (lambda s: s if "connected / paired" in s else None)(
                    driver.execute_script("return window.liveSeen")), timeout=60, interval=0.05,
                    message="the page to show live_bot paired")
                text = master.log_text()
                connected_at = log_time(text, r"robot live_bot connected from")
                paired_at = log_time(text, r"robot live_bot paired")
                if "connected / not paired" in seen:
                    connect.append(seen["connected / not paired"] / 1000.0 - connected_at)
                pair.append(seen["connected / paired"] / 1000.0 - paired_at)
                robot.stop()
                wait_until(lambda: driver.execute_script(
                    "const r = document.querySelector('#robots tr[data-name=\"live_bot\"]');"
                    "return r && r.cells[2].textContent === 'not connected'"), timeout=30,
                    message="the page to show live_bot gone")
            errors = [e for e in browser.console_errors() if "Uncaught" in e.get("message", "")]
        finally:
            if stream is not None:
                stream.close()
            browser.quit()
            master.stop()

    load_after = os.getloadavg()[0]

    def row(what, values):
        ms = [v * 1000 for v in values]
        return (f"| {what} | {len(ms)} | {statistics.median(ms):.0f} | {percentile(ms, 0.99):.0f} | "
                f"{max(ms):.0f} |")
    p99 = max(percentile(values, 0.99) for values in (page, pair, connect) if values)
    verdict = "met" if p99 < TARGET_P99_S else "NOT met"
    body = "\n".join([
        f"{ROBOTS} robots provisioned (service logic with {ITEMS} service nodes), none connected; each change is "
        f"one RDAPI write (provisioning a robot, then removing it), {args.rounds} of each, or a robot agent "
        f"connecting and pairing, {args.live_rounds} times. Timed from just "
        f"before the RDAPI call to the page's DOM showing it (headless Chromium, a MutationObserver noting "
        f"`Date.now()`), and to the push reaching a plain event-stream client.",
        "",
        "| from a state change to | changes | p50 ms | p99 ms | max ms |",
        "| --- | --- | --- | --- | --- |",
        row("the page (DOM updated)", page),
        row("the event stream (push received)", push),
        row("the page, a robot agent connecting (from the master's log line)", connect) if connect else
        "| the page, a robot agent connecting | 0 | (the page went straight to paired) | | |",
        row("the page, its space paired (from the master's log line)", pair),
        "",
        "The last two rows are live state without any RDAPI call: a real robot agent (service logic `empty`) "
        "started and stopped again; their times start at the master's log lines, which have millisecond stamps "
        "and are written a little after the change itself.",
        "",
        f"Rendering a full snapshot of {ROBOTS} robots in the page: {render_ms:.0f} ms. "
        f"Uncaught JavaScript errors: {len(errors)}.",
        "",
        f"Load average (1 min) of the machine: {load_before:.1f} before, {load_after:.1f} after (other "
        f"engineers' tests were running; the machine has {os.cpu_count()} cores).",
        "",
        f"Target (issue 11): p99 from a change to the page under {TARGET_P99_S * 1000:.0f} ms: **{verdict}** "
        f"(the largest p99 of the page rows: {p99 * 1000:.0f} ms). The pushes are coalesced for 50 ms (`rcmp_console.COALESCE`), which is most of "
        f"the p50.",
    ])
    print(body)
    if not args.no_write:
        write_section("console", "Console: a state change to the page, 100 robots provisioned (issue 11)", body)
    return 0 if p99 < TARGET_P99_S and not errors else 1


if __name__ == "__main__":
    sys.exit(main())
