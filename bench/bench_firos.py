"""FIROS benchmark: latency both ways at 10 Hz and the highest rate of distinct messages FIROS forwards for one
robot with ten topics before values start being skipped, with NGSI v2 and with NGSI-LD (one column each); and a
robot with real data: a whitelisted camera (`sensor_msgs/Image` 640x480 rgb8, 15 Hz) and a 2,000 x 2,000
`nav_msgs/OccupancyGrid` (1 Hz) beside its 10 Hz `geometry_msgs/Pose2D`, both too big for Orion's 1 MB: the
pose's ROS → broker latency (target p99 < 20 ms) and FIROS's CPU, with the pose alone first.
Writes its sections of docs/PERFORMANCE.md.

Everything is real and on loopback: a ROS master, the stand-in broker and FIROS (`rosrun firos core.py`) as
children; this process is the ROS peer (a rospy node) and the broker client.

- ROS → broker: publish a distinct std_msgs/String and time until the broker's own notification of the new
  value (a v2 or NGSI-LD subscription of this benchmark) reaches a receiver here (so the value is stored and
  readable; the notifier's delay is included).
- broker → ROS: `POST /v2/op/update` (NGSI-LD: `POST /ngsi-ld/v1/entities/{id}/attrs`) with `cmd` and `COMMAND`,
  timed until the rospy subscriber here gets it (broker notification → FIROS → ROS).
- Throughput: ten topics of std_msgs/Int32, distinct values round-robin at a fixed total rate for a few seconds;
  "skipped" = published − forwarded (FIROS keeps only the newest value per attribute waiting, so a value it could
  not send in time is replaced; this also counts messages rospy's queue dropped). The highest rate with at most
  1 % skipped is the sustained rate.

- Real data: the camera frames and the map are published pre-serialized (this process would otherwise spend
  its time serializing 4 M map cells), distinct poses at 10 Hz, each timed until the broker's notification of
  it arrives; FIROS's CPU is its process's user + system time over the run (`/proc/PID/stat`).

Run: `bash scripts/with-overlay.sh /usr/bin/python3 -m bench.bench_firos [--quick] [--big-only]`.
"""

import http.client
import io
import json
import os
import statistics
import sys
import tempfile
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from bench.report import load_average, percentile, write_section  # noqa: E402
from tests.ngsi_broker.testing import start_broker  # noqa: E402
from tests.support.firos import Firos, write_config  # noqa: E402
from tests.support.polling import wait_until  # noqa: E402
from tests.support.processes import ProcessGroup  # noqa: E402
from tests.support.rosmaster import RosMaster  # noqa: E402

ROBOT = "benchbot"
LD_ID = "urn:ngsi-ld:ROBOT:" + ROBOT
LD_LINK = ('<https://uri.etsi.org/ngsi-ld/v1/ngsi-ld-core-context.jsonld>; '
           'rel="http://www.w3.org/ns/json-ld#context"; type="application/ld+json"')
TOPICS = [f"t{i}" for i in range(10)]
RATES = [250, 500, 1000, 2000, 4000]


class Broker:
    """The benchmark's own client of the broker, speaking NGSI ``version`` ("v2" or "ld")."""

    def __init__(self, port, version):
        self.conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
        self.version = version

    def call(self, method, path, body=None):
        data = None if body is None else json.dumps(body).encode()
        headers = {"Content-Type": "application/json"} if data is not None else {}
        if self.version == "ld":
            headers["Link"] = LD_LINK
        self.conn.request(method, path, body=data, headers=headers)
        resp = self.conn.getresponse()
        return resp.status, resp.read()

    def subscribe(self, url, attr="lat"):
        """Subscribe the benchmark's receiver to attribute ``attr`` of the robot."""
        if self.version == "ld":
            return self.call("POST", "/ngsi-ld/v1/subscriptions", {
                "type": "Subscription", "entities": [{"id": LD_ID, "type": "ROBOT"}], "watchedAttributes": [attr],
                "notification": {"attributes": [attr], "format": "normalized",
                                 "endpoint": {"uri": url, "accept": "application/json"}}})
        return self.call("POST", "/v2/subscriptions", {
            "subject": {"entities": [{"id": ROBOT, "type": "ROBOT"}], "condition": {"attrs": [attr]}},
            "notification": {"http": {"url": url}, "attrs": [attr]}})

    def command(self, token):
        """Write ``cmd`` and COMMAND as a user would; the status the broker answered (204 when accepted)."""
        if self.version == "ld":
            return self.call("POST", f"/ngsi-ld/v1/entities/{LD_ID}/attrs", {
                "cmd": {"type": "Property", "value": {"data": token},
                        "messageType": {"type": "Property", "value": "std_msgs.msg.String"}},
                "COMMAND": {"type": "Property", "value": ["cmd"]}})
        return self.call("POST", "/v2/op/update", {"actionType": "append", "entities": [
            {"id": ROBOT, "type": "ROBOT", "cmd": {"type": "std_msgs.msg.String", "value": {"data": token}},
             "COMMAND": {"type": "COMMAND", "value": ["cmd"]}}]})


class Receiver:
    """A notification receiver on loopback recording when each value of ``attr`` arrived (perf_counter), by its
    member ``field``."""

    def __init__(self, attr="lat", field="data"):
        self.arrivals = {}
        self.cond = threading.Condition()
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"
            disable_nagle_algorithm = True

            def log_message(self, *args):
                pass

            def do_POST(self):
                body = self.rfile.read(int(self.headers.get("Content-Length", 0)))
                now = time.perf_counter()
                try:
                    for entity in json.loads(body).get("data", []):
                        token = entity.get(attr, {}).get("value", {}).get(field)
                        with receiver.cond:
                            receiver.arrivals.setdefault(token, now)
                            receiver.cond.notify_all()
                except (ValueError, AttributeError):
                    pass
                self.send_response(200)
                self.send_header("Content-Length", "0")
                self.end_headers()

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/notify"
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def wait(self, token, timeout=5.0):
        with self.cond:
            self.cond.wait_for(lambda: token in self.arrivals, timeout)
            return self.arrivals.get(token)

    def close(self):
        self.httpd.shutdown()
        self.httpd.server_close()


def measure_ros_to_broker(rospy, String, broker, samples):
    """Publish, and time until the broker has stored the value: its v2 notification reaches us (the notifier's
    own delay is included, so this is an upper bound of "readable in the broker")."""
    receiver = Receiver()
    status, body = broker.subscribe(receiver.url)
    if status != 201:
        raise RuntimeError(f"broker refused the benchmark's subscription: {status} {body[:200]}")
    pub = rospy.Publisher(f"/{ROBOT}/lat", String, queue_size=10)
    wait_until(lambda: pub.get_num_connections() >= 1, timeout=20, message="FIROS to subscribe to lat")
    latencies = []
    try:
        for i in range(samples + 3):
            tick = time.monotonic()
            token = f"r{i}-{time.time()}"
            start = time.perf_counter()
            pub.publish(String(data=token))
            arrived = receiver.wait(token)
            if arrived is None:
                raise RuntimeError(f"value {token} never reached the broker")
            if i >= 3:                                    # the first ones warm up connections
                latencies.append((arrived - start) * 1000)
            time.sleep(max(0.0, 0.1 - (time.monotonic() - tick)))   # 10 Hz pacing (a benchmark, not a test)
    finally:
        receiver.close()
        pub.unregister()
    return latencies


def measure_broker_to_ros(rospy, String, broker, firos, samples):
    arrivals = {}
    event = threading.Event()

    def got(msg):
        arrivals[msg.data] = time.perf_counter()
        event.set()

    sub = rospy.Subscriber(f"/{ROBOT}/cmd", String, got)
    wait_until(lambda: firos.stats()["subscriptions"].get(ROBOT), timeout=20, message="FIROS's subscription")
    latencies = []
    for i in range(samples + 3):
        tick = time.monotonic()
        token = f"c{i}-{time.time()}"
        event.clear()
        start = time.perf_counter()
        status, body = broker.command(token)
        if status != 204:
            raise RuntimeError(f"broker refused the command: {status} {body[:200]}")
        deadline = time.monotonic() + 5
        while token not in arrivals and time.monotonic() < deadline:
            event.wait(0.05)
            event.clear()
        if token not in arrivals:
            raise RuntimeError(f"command {token} never reached ROS")
        if i >= 3:
            latencies.append((arrivals[token] - start) * 1000)
        time.sleep(max(0.0, 0.1 - (time.monotonic() - tick)))
    sub.unregister()
    return latencies


def measure_throughput(rospy, Int32, firos, rate, seconds):
    pubs = [rospy.Publisher(f"/{ROBOT}/{t}", Int32, queue_size=100) for t in TOPICS]
    wait_until(lambda: all(p.get_num_connections() >= 1 for p in pubs), timeout=20,
               message="FIROS to subscribe to the ten topics")
    wait_until(lambda: firos.stats()["waiting"] == 0, timeout=20, message="FIROS idle")
    before = firos.stats()
    total = int(rate * seconds)
    start = time.perf_counter()
    value = int(time.time() * 1000) % 1_000_000_000
    for i in range(total):
        target = start + i / rate
        now = time.perf_counter()
        if target > now:
            time.sleep(target - now)
        pubs[i % len(pubs)].publish(Int32(data=value + i))
    sent_for = time.perf_counter() - start
    wait_until(lambda: firos.stats()["waiting"] == 0, timeout=30, message="FIROS to drain")
    after = firos.stats()
    forwarded = after["forwarded"] - before["forwarded"]
    requests = after["requests"] - before["requests"]
    for p in pubs:
        p.unregister()
    return {"rate": rate, "published": total, "achieved": total / sent_for, "forwarded": forwarded,
            "skipped": max(0, total - forwarded), "requests": requests}


def run_version(procs, master, tmp, version, samples, seconds):
    """Latency both ways and the throughput runs against a fresh broker and FIROS speaking ``version``."""
    import rospy
    from std_msgs.msg import Int32, String
    broker_proc = start_broker(procs, extra_args=["--quiet"])
    config = write_config(os.path.join(tmp, f"config-{version}"), broker_proc.port, version=version, whitelist={
        ROBOT: {"publisher": ["cmd"], "subscriber": ["lat", "t\\d"]}}, log_level="WARNING")
    firos = Firos(procs, master, config).start()
    try:
        broker = Broker(broker_proc.port, version)
        up = measure_ros_to_broker(rospy, String, broker, samples)
        down = measure_broker_to_ros(rospy, String, broker, firos, samples)
        runs = []
        for rate in RATES:
            run = measure_throughput(rospy, Int32, firos, rate, seconds)
            runs.append(run)
            print(f"{version} rate {rate}/s: {run}", flush=True)
            if run["skipped"] > 0.01 * run["published"] or run["achieved"] < 0.95 * rate:
                break
    finally:
        procs.stop(firos.process)
        procs.stop(broker_proc.process)
    sustained = max([r["forwarded"] / (r["published"] / r["achieved"]) for r in runs
                     if r["skipped"] <= 0.01 * r["published"] and r["achieved"] >= 0.95 * r["rate"]] or [0])
    clean = max([r["rate"] for r in runs if r["skipped"] == 0] or [0])
    return {"up": up, "down": down, "runs": runs, "sustained": sustained, "clean": clean}



CAMERA = (640, 480, 3)          # width, height, bytes per pixel (rgb8)
MAP_CELLS = 2000
RATES_HZ = {"pose": 10.0, "camera": 15.0, "map": 1.0}


def preserialized(cls, msg):
    """A message class whose instances publish ``msg``'s bytes as they are: this process then spends nothing on
    serializing the camera frames and the map (4 M cells) again for every publish."""
    import genpy
    buffer = io.BytesIO()
    msg.serialize(buffer)
    data = buffer.getvalue()

    class Preserialized(genpy.Message):
        _type, _md5sum, _full_text, _has_header = cls._type, cls._md5sum, cls._full_text, False
        __slots__ = []
        _slot_types = []

        def serialize(self, buff):
            buff.write(data)

    return Preserialized, len(data)


def cpu_seconds(pid):
    """User + system CPU time of a process so far (seconds)."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def run_phase(rospy, pubs, receiver, firos_pid, seconds, with_big):
    """Publish for ``seconds``: poses at 10 Hz (each a new x, timed to the broker's notification), and with
    ``with_big`` the camera at 15 Hz and the map at 1 Hz. Returns (pose latencies ms, FIROS CPU %, lost poses)."""
    from geometry_msgs.msg import Pose2D
    topics = ["pose"] + (["camera", "map"] if with_big else [])
    start = time.monotonic()
    due = {topic: start for topic in topics}
    sent = {}
    cpu_before, wall_before = cpu_seconds(firos_pid), time.monotonic()
    token = int(time.time() * 10) % 1_000_000 * 1000.0
    while time.monotonic() - start < seconds:
        topic = min(topics, key=due.get)
        wait = due[topic] - time.monotonic()
        if wait > 0:
            time.sleep(wait)                 # pacing the publishers (a benchmark, not a test)
        if topic == "pose":
            token += 1
            sent[token] = time.perf_counter()
            pubs["pose"].publish(Pose2D(x=token))
        else:
            pubs[topic][0].publish(pubs[topic][1]())
        due[topic] += 1.0 / RATES_HZ[topic]
    deadline = time.monotonic() + 5.0
    for token in sent:                       # the last ones may still be on their way
        receiver.wait(token, timeout=max(0.0, deadline - time.monotonic()))
    cpu = (cpu_seconds(firos_pid) - cpu_before) / (time.monotonic() - wall_before) * 100
    latencies = [(receiver.arrivals[t] - at) * 1000 for t, at in sent.items() if t in receiver.arrivals]
    return latencies[3:], cpu, len(sent) - len(latencies)


def run_big_values(procs, master, tmp, seconds):
    """The robot with a camera and a big map beside its pose, against a fresh broker and FIROS (NGSI v2)."""
    import rospy
    from geometry_msgs.msg import Pose2D
    from nav_msgs.msg import OccupancyGrid
    from sensor_msgs.msg import Image
    broker_proc = start_broker(procs, extra_args=["--quiet"])
    config = write_config(os.path.join(tmp, "config-big"), broker_proc.port, whitelist={
        ROBOT: {"subscriber": ["pose", "camera", "map"]}}, log_level="WARNING")
    firos = Firos(procs, master, config).start()
    receiver = Receiver(attr="pose", field="x")
    try:
        broker = Broker(broker_proc.port, "v2")
        status, body = broker.subscribe(receiver.url, "pose")
        if status != 201:
            raise RuntimeError(f"broker refused the benchmark's subscription: {status} {body[:200]}")
        width, height, depth = CAMERA
        camera_cls, camera_size = preserialized(Image, Image(height=height, width=width, encoding="rgb8",
                                                             step=width * depth,
                                                             data=bytes(range(256)) * (width * height * depth // 256)))
        grid = OccupancyGrid()
        grid.info.width = grid.info.height = MAP_CELLS
        grid.data = b"\x00" * (MAP_CELLS * MAP_CELLS)
        map_cls, map_size = preserialized(OccupancyGrid, grid)
        pubs = {"pose": rospy.Publisher(f"/{ROBOT}/pose", Pose2D, queue_size=10),
                "camera": (rospy.Publisher(f"/{ROBOT}/camera", camera_cls, queue_size=2), camera_cls),
                "map": (rospy.Publisher(f"/{ROBOT}/map", map_cls, queue_size=2), map_cls)}
        wait_until(lambda: pubs["pose"].get_num_connections() >= 1 and all(
            pubs[t][0].get_num_connections() >= 1 for t in ("camera", "map")), timeout=30,
            message="FIROS to subscribe to pose, camera and map")
        pid = firos.python_pid()
        alone = run_phase(rospy, pubs, receiver, pid, seconds, with_big=False)
        before = firos.stats()
        loaded = run_phase(rospy, pubs, receiver, pid, seconds, with_big=True)
        after = firos.stats()
    finally:
        receiver.close()
        procs.stop(firos.process)
        procs.stop(broker_proc.process)
    too_large = after["too_large_values"].get(ROBOT, {})
    return {"alone": alone, "loaded": loaded, "camera_size": camera_size, "map_size": map_size,
            "camera_too_large": too_large.get("camera", {}).get("count", 0),
            "map_too_large": too_large.get("map", {}).get("count", 0),
            "camera_json": too_large.get("camera", {}).get("size", 0),
            "map_json": too_large.get("map", {}).get("size", 0),
            "forwarded": after["forwarded"] - before["forwarded"], "errors": after["errors"] - before["errors"]}


def big_values_section(result, seconds, load_before):
    def row(label, phase):
        latencies, cpu, lost = phase
        return (f"| {label} | {len(latencies)} | {percentile(latencies, 0.5):.2f} ms | "
                f"{percentile(latencies, 0.99):.2f} ms | {max(latencies):.2f} ms | {lost} | {cpu:.1f} % |")
    p99 = percentile(result["loaded"][0], 0.99)
    width, height, _ = CAMERA
    return "\n".join([
        f"One robot (NGSI v2, the stand-in broker of docs/STANDIN_BROKER.md answering 413 above 1 MB as Orion "
        "does): a `Pose2D` at 10 Hz, "
        f"each a new value timed from its publication to the broker's notification of it; then the same beside a "
        f"whitelisted camera (`sensor_msgs/Image` {width}x{height} rgb8, {result['camera_size']:,} bytes "
        f"serialized, 15 Hz) and a {MAP_CELLS:,} x {MAP_CELLS:,} `nav_msgs/OccupancyGrid` "
        f"({result['map_size']:,} bytes, 1 Hz), {seconds:.0f} s each. FIROS's CPU: its process's user + system "
        f"time over the run (100 % = one core). Load average (1 / 5 min) before: {load_before}, after: "
        f"{result['load_after']}; the machine is shared with other work.",
        "",
        "| topics | poses timed | pose p50 | pose p99 | pose max | poses not notified | FIROS CPU |",
        "| --- | --- | --- | --- | --- | --- | --- |",
        row("pose alone", result["alone"]),
        row("pose + camera 15 Hz + map 1 Hz", result["loaded"]),
        "",
        f"Pose p99 beside the camera and the map: **{p99:.2f} ms** (target < 20 ms: "
        f"{'met' if p99 < 20 else 'NOT met'}). Neither big topic fits in Orion's 1 MB: each camera frame (at "
        f"least {result['camera_json']:,} bytes of JSON, its data in base64) and each map (at least "
        f"{result['map_json']:,} bytes) was judged from its serialized bytes without being deserialized or "
        f"converted, counted and not sent: {result['camera_too_large']} frames and {result['map_too_large']} maps; "
        f"{result['forwarded']} values forwarded, {result['errors']} errors. What FIROS's CPU does beside the pose "
        "is mostly rospy receiving the frames and maps (about 18 MB/s).",
    ])


VERSIONS = (("v2", "NGSI v2"), ("ld", "NGSI-LD"))


def main(argv=None):
    argv = list(sys.argv[1:] if argv is None else argv)
    quick = "--quick" in argv
    big_only = "--big-only" in argv
    samples = 30 if quick else 100
    seconds = 2.0 if quick else 4.0
    big_seconds = 10.0 if quick else 30.0
    tmp = tempfile.mkdtemp(prefix="bench-firos-")
    os.environ["ROS_LOG_DIR"] = os.path.join(tmp, "roslog")
    results = {}
    load_before = load_average()
    with ProcessGroup(log_dir=tmp) as procs:
        master = RosMaster(procs).start()
        os.environ["ROS_MASTER_URI"] = master.uri
        os.environ["ROS_IP"] = "127.0.0.1"
        import rospy
        rospy.init_node("bench_firos", anonymous=True, disable_signals=True)
        try:
            big = run_big_values(procs, master, tmp, big_seconds)
            big["load_after"] = load_average()
            if not big_only:
                for version, _ in VERSIONS:
                    results[version] = run_version(procs, master, tmp, version, samples, seconds)
        finally:
            rospy.signal_shutdown("benchmark done")
    big_body = big_values_section(big, big_seconds, load_before)
    write_section("firos-big", "FIROS: a camera and a big map beside a pose", big_body)
    print(big_body)
    if big_only:
        return 0
    load = os.getloadavg()

    def met(value, ok):
        return "met" if ok(value) else "NOT met"

    lines = [
        "FIROS with the stand-in broker (docs/STANDIN_BROKER.md), ROS master and this benchmark's rospy node on "
        "loopback "
        f"(`bench/bench_firos.py`{' --quick' if quick else ''}), once with NGSI v2 and once with NGSI-LD (a fresh "
        f"broker and FIROS each); load average at the end {load[0]:.1f} / {load[1]:.1f} (1 / 5 min): the figures "
        "drop when other work shares the two cores.",
        "",
        "| path (10 Hz, %d samples) | " % samples + " | ".join(
            f"{label} p50 | {label} p99 | {label} mean" for _, label in VERSIONS) + " | target p50 < 10 ms |",
        "| --- |" + " --- |" * (3 * len(VERSIONS) + 1),
    ]
    for key, what in (("up", "ROS publish → value readable in the broker"),
                      ("down", "broker update → ROS message arrives")):
        cells, verdicts = [], []
        for version, label in VERSIONS:
            values = results[version][key]
            p50 = percentile(values, 0.5)
            cells.append(f"{p50:.2f} ms | {percentile(values, 0.99):.2f} ms | {statistics.mean(values):.2f} ms")
            verdicts.append(f"{label} {met(p50, lambda v: v < 10)}")
        lines.append(f"| {what} | " + " | ".join(cells) + " | " + ", ".join(verdicts) + " |")
    lines += ["", "One robot, ten topics (std_msgs/Int32), distinct values round-robin, %.0f s per rate:" % seconds,
              "",
              "| NGSI | offered rate | achieved | published | forwarded | skipped | HTTP requests (batches) |",
              "| --- | --- | --- | --- | --- | --- | --- |"]
    for version, label in VERSIONS:
        for r in results[version]["runs"]:
            lines.append(f"| {label} | {r['rate']}/s | {r['achieved']:.0f}/s | {r['published']} | {r['forwarded']} | "
                         f"{r['skipped']} ({100.0 * r['skipped'] / r['published']:.1f} %) | {r['requests']} |")
    lines.append("")
    for version, label in VERSIONS:
        result = results[version]
        lines.append(f"{label}: highest sustained rate with at most 1 % skipped: **{result['sustained']:.0f} "
                     f"forwarded updates/s** (target >= 500/s: {met(result['sustained'], lambda v: v >= 500)}); "
                     f"highest offered rate with none skipped at all: {result['clean']}/s.")
        lines.append("")
    lines.append("The last rate tried is the first where more than 1 % were skipped, or the highest this "
                 "single-threaded publisher reaches. FIROS batches: at low rates one request carries one value, at "
                 "high rates several (compare forwarded with HTTP requests); NGSI-LD batches are "
                 "`entityOperations/upsert` requests.")
    body = "\n".join(lines)
    write_section("firos", "FIROS: latency and throughput (NGSI v2 and NGSI-LD)", body)
    print(body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
