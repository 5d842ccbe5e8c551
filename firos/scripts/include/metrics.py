"""FIROS's metrics for Prometheus: what ``GET /metrics`` on FIROS's HTTP server answers.

Owns FIROS's own ``CollectorRegistry`` (never prometheus_client's global one, so that tests and several FIROS in one
process do not share series), every metric's name, help text, labels and buckets (docs/METRICS.md lists them for
users), and how each value is had:

- read at scrape time from what FIROS's modules count anyway, by a collector of its own (``FirosState``): robots
  and mapped topics (``bridge.Firos``), broker subscriptions, values waiting and whether the broker answers, values
  forwarded and skipped by reason (``Sender.stats``, ``Sender.skips``), commands published and skipped by reason
  (``Firos.commands``), the HTTP server's connections held and refused (``server.WorkerPool``) and its requests by
  route and status (``server.Tally``);
- observed as they happen, through hooks the modules offer without importing prometheus_client: each request to
  the broker by status class, and its duration (``NgsiClient.observer``); each value the broker took, timed from
  its arrival at FIROS to the broker's answer (``Sender.forward_observers``);
- the process' own (``process_*``) and ``python_info``, from prometheus_client's collectors on this registry.

Every label takes its values from a set fixed in the code (``SKIP_REASONS``, ``COMMAND_SKIPS``, ``BROKER_STATUSES``,
the server's route labels, the statuses FIROS answers, two directions): never a robot, a topic, an entity or an
address. Works with prometheus_client 0.7.1 (Ubuntu 20.04) to 0.21 (Debian 13). Without it ``make_metrics`` gives
an ``Unavailable``: FIROS runs, logs once which package to install, and answers ``/metrics`` with 503 and that
sentence.
"""

import logging

from include.bridge import COMMAND_SKIPS, ApiError
from include.sender import SKIP_REASONS

try:
    import prometheus_client
    from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily
except ImportError:   # FIROS where python3-prometheus-client is not installed: make_metrics says which package
    prometheus_client = None

log = logging.getLogger("firos.metrics")

MISSING = ("the Python package prometheus_client is missing: install python3-prometheus-client (Debian, Ubuntu) "
           "and restart FIROS")
BROKER_STATUSES = ("2xx", "3xx", "4xx", "5xx", "timeout", "connection")
BROKER_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0)
FORWARD_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)
DIRECTIONS = (("ros_to_broker", "subscriber"), ("broker_to_ros", "publisher"))   # label, the whitelist's kind


def _one(family_class, name, documentation, value):
    family = family_class(name, documentation)
    family.add_metric([], value)
    return family


def _by(family_class, name, documentation, label, counts, values):
    """A family with one series per value of ``values`` (0 when ``counts`` has none)."""
    family = family_class(name, documentation, labels=[label])
    for value in values:
        family.add_metric([value], counts.get(value, 0))
    return family


class FirosState:
    """The collector of what FIROS's modules count themselves, read at each scrape."""

    def __init__(self, firos, pool, tally, route_labels):
        self.firos = firos
        self.pool = pool
        self.tally = tally
        self.route_labels = route_labels

    def collect(self):
        firos = self.firos
        with firos._lock:
            topics = [info.kinds for robot in firos.robots.values() for info in robot.topics.values()]
            robots = len(firos.robots)
            commands = dict(firos.commands)
        stats = firos.sender.snapshot_stats()
        yield _one(GaugeMetricFamily, "firos_robots", "Robots FIROS maps to entities of the context broker.",
                   robots)
        mapped = GaugeMetricFamily("firos_topics", "Topics FIROS maps, by direction (a topic both ways counts in "
                                                   "each).", labels=["direction"])
        for label, kind in DIRECTIONS:
            mapped.add_metric([label], sum(1 for kinds in topics if kind in kinds))
        yield mapped
        yield _one(GaugeMetricFamily, "firos_subscriptions", "Broker subscriptions FIROS holds for commands.",
                   len(firos.subscriptions.ids()))
        yield _one(GaugeMetricFamily, "firos_values_waiting", "Topic values waiting to be sent to the broker (the "
                                                              "newest of each topic).", stats["waiting"])
        yield _one(GaugeMetricFamily, "firos_broker_up", "1 while the broker answers FIROS's updates, 0 while "
                                                         "FIROS keeps values and retries.", int(stats["broker_up"]))
        yield _one(CounterMetricFamily, "firos_values_forwarded_total", "Topic values (ROS messages) the broker "
                                                                        "took.", stats["forwarded"])
        yield _by(CounterMetricFamily, "firos_values_skipped_total", "Topic values not sent to the broker, by "
                  "reason.", "reason", dict(firos.sender.skips), SKIP_REASONS)
        yield _one(CounterMetricFamily, "firos_commands_published_total", "Broker commands FIROS published on "
                                                                          "ROS topics.", commands.get("published", 0))
        yield _by(CounterMetricFamily, "firos_commands_skipped_total", "Attributes a notification's COMMAND named "
                  "that FIROS did not publish, by reason.", "reason", commands, COMMAND_SKIPS)
        yield _one(GaugeMetricFamily, "firos_http_connections", "Connections FIROS's HTTP server holds (at a worker "
                                                                "or waiting for one).", self.pool.held())
        yield _one(CounterMetricFamily, "firos_http_connections_refused_total", "Connections refused (503): over "
                   "their address's share, or no worker and no waiting place left.", self.pool.refused)
        requests = CounterMetricFamily("firos_http_requests_total", "Requests FIROS's HTTP server answered, by route "
                                                                    "(other: any unknown path) and status.",
                                       labels=["route", "code"])
        for (route, code), count in sorted(self.tally.snapshot().items()):
            requests.add_metric([route if route in self.route_labels else "other", str(code)], count)
        yield requests


class Metrics:
    """FIROS's metrics: a registry of its own, the hooks FIROS's modules call, ``scrape()``."""

    def __init__(self, firos, pool, tally, route_labels):
        registry = self.registry = prometheus_client.CollectorRegistry()
        requests = prometheus_client.Counter(
            "firos_broker_requests", "Requests FIROS sent to the context broker, by the status class of the answer "
            "(timeout, connection: no answer).", ["status"], registry=registry)
        self._broker = {status: requests.labels(status) for status in BROKER_STATUSES}
        self._broker_duration = prometheus_client.Histogram(
            "firos_broker_request_duration_seconds", "Time from sending a request to the broker to its answer (or "
            "failure).", buckets=BROKER_BUCKETS, registry=registry)
        self._forward = prometheus_client.Histogram(
            "firos_forward_latency_seconds", "Time from a topic value's arrival at FIROS to the broker's answer to "
            "the update that carried it.", buckets=FORWARD_BUCKETS, registry=registry)
        registry.register(FirosState(firos, pool, tally, route_labels))
        prometheus_client.ProcessCollector(registry=registry)
        prometheus_client.PlatformCollector(registry=registry)

    def broker_request(self, status, seconds):
        """``NgsiClient.observer``: one request to the broker, answered with ``status``'s class after ``seconds``."""
        self._broker.get(status, self._broker["connection"]).inc()
        self._broker_duration.observe(max(0.0, seconds))

    def forwarded(self, latencies):
        """``Sender.forward_observers``: values the broker took, each ``seconds`` after it reached FIROS."""
        for seconds in latencies:
            self._forward.observe(max(0.0, seconds))

    def scrape(self):
        """(content type, the text exposition format) of every metric now."""
        return prometheus_client.CONTENT_TYPE_LATEST, prometheus_client.generate_latest(self.registry)


class Unavailable:
    """What serves ``/metrics`` where prometheus_client is not installed: 503 with the sentence naming it."""

    def broker_request(self, status, seconds):
        pass

    def forwarded(self, latencies):
        pass

    def scrape(self):
        raise ApiError(503, f"this FIROS serves no metrics: {MISSING}")


def make_metrics(firos, pool, tally, route_labels):
    """``Metrics`` for a FIROS, or ``Unavailable`` (after one warning) when prometheus_client cannot be imported."""
    if prometheus_client is None:
        log.warning("FIROS serves no /metrics: %s", MISSING)
        return Unavailable()
    return Metrics(firos, pool, tally, route_labels)
