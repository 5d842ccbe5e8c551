"""The master's metrics for Prometheus: what ``GET /metrics`` on the RDAPI answers (master only).

Owns the agent's own ``CollectorRegistry`` (never prometheus_client's global one, so that tests and several agents
in one process do not share series), every metric's name, help text, labels and buckets (docs/METRICS.md lists
them for users), and how each value is had:

- read at scrape time from the live state, by a collector of its own (``LiveState``), so nothing is kept in step
  by hand: robots provisioned, connected and paired (the rows ``platform_instance/read`` answers, through its read
  cache, so the two never disagree), servers, service spaces per server and state, spaces waiting for room, the
  counters the agent keeps itself (hellos refused by code, connections, heartbeats missed and timed out) and the
  connections of the agent port and the RDAPI;
- observed as they happen, through the hooks the agent's modules offer (they never import prometheus_client): the
  hello and pairing durations (``MasterAgent.timing_observers``), item failures by their ``ITEM_FAILURES`` word
  (``ServiceSpaceManager.observers`` and ``ServiceItem.failure``; each failed item counted once), the RDAPI's
  requests by route, method and status and their durations (``Rdapi.request_observers``);
- the process' own (``process_*``) and ``python_info``, from prometheus_client's collectors on this registry.

Every label has a bounded set of values: robot names are never labels; a server's name is (servers are the master
and the server VMs the operator runs, and only those known now are read at scrape time). Works with
prometheus_client 0.7.1 (Ubuntu 20.04) to 0.21 (Debian 13). Without it ``make_metrics`` gives an ``Unavailable``:
the master runs, logs once which package to install, and answers ``/metrics`` with 503 and that sentence.
"""

import collections
import logging
import weakref

from twisted.application import service
from twisted.internet import defer

from . import rcmp_deps
from .rcmp_command import Unavailable as UnavailableError
from .rcmp_process import FAILED
from .rcmp_service_item import ITEM_FAILURES

try:
    import prometheus_client
    from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily
except ImportError as exc:   # a master without python3-prometheus-client: make_metrics says which package
    prometheus_client = None
    _MISSING = exc
else:
    _MISSING = None

log = logging.getLogger("rcmp.metrics")

HELLO_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)
PAIRING_BUCKETS = (0.5, 1.0, 2.0, 3.0, 5.0, 7.5, 10.0, 15.0, 30.0, 60.0, 120.0, 300.0)
RDAPI_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)
SPACE_STATES = ("creating", "paired", "unpaired", "stopping")   # shown at 0 too; a space in another is shown as well
PEERS = ("robot", "server")


def _gauge(name, documentation, value):
    family = GaugeMetricFamily(name, documentation)
    family.add_metric([], value)
    return family


def _counter(name, documentation, value):
    family = CounterMetricFamily(name, documentation)
    family.add_metric([], value)
    return family


class LiveState:
    """The collector of what is read from the live state at each scrape (``Metrics.rows``: the robots' rows of the
    scrape in progress)."""

    def __init__(self, metrics):
        self.metrics = metrics

    def collect(self):
        metrics = self.metrics
        rows = metrics.rows or []
        yield _gauge("rcm_robots_provisioned", "Robots provisioned on this platform (platform_instance/read).",
                     len(rows))
        yield _gauge("rcm_robots_connected", "Provisioned robots whose agent is connected to the master.",
                     sum(1 for r in rows if r.get("connected")))
        yield _gauge("rcm_robots_paired", "Connected robots whose service space is paired (every item runs).",
                     sum(1 for r in rows if r.get("paired")))
        yield from self._servers(metrics.spaces)
        yield from self._agent(metrics.agent)
        yield from self._rdapi(metrics.site)

    @staticmethod
    def _servers(spaces):
        servers = spaces.servers
        yield _gauge("rcm_servers_connected", "Servers that can host service spaces: the master and the connected "
                                              "server VMs.", len(servers))
        counts = collections.Counter((space.server, space.state) for space in spaces.spaces.values())
        names = sorted(set(servers) | {server for server, _ in counts if server is not None})
        states = list(SPACE_STATES) + sorted({state for _, state in counts} - set(SPACE_STATES))
        family = GaugeMetricFamily("rcm_service_spaces", "Service spaces by the server hosting them and their "
                                                         "state.", labels=["server", "state"])
        for name in names:
            for state in states:
                family.add_metric([name, state], counts.get((name, state), 0))
        yield family
        limit = GaugeMetricFamily("rcm_service_spaces_limit", "The most service spaces a server hosts "
                                                              "(max_service_spaces).", labels=["server"])
        for name in sorted(servers):
            limit.add_metric([name], servers[name].capacity)
        yield limit
        yield _gauge("rcm_service_spaces_waiting", "Service spaces waiting for a server with room.",
                     len(spaces.unplaced))

    @staticmethod
    def _agent(agent):
        counters = agent.counters
        refused = CounterMetricFamily("rcm_hellos_refused_total", "Hellos the master refused, by the code it "
                                                                  "answered.", labels=["code"])
        for key in sorted(k for k in counters if k.startswith("refused_")):
            refused.add_metric([key[len("refused_"):]], counters[key])
        yield refused
        yield _counter("rcm_robot_connections_total", "Robot sessions opened (accepted hellos of robots).",
                       counters["sessions_opened"])
        yield _counter("rcm_robot_disconnections_total", "Robot sessions ended (left, lost, replaced, removed).",
                       counters["sessions_ended"])
        for name, key, documentation in (
                ("rcm_heartbeat_misses_total", "heartbeat_misses",
                 "Heartbeat checks that found a peer silent for a whole interval (a missed beat), by kind of peer."),
                ("rcm_heartbeat_timeouts_total", "heartbeat_timeouts",
                 "Peers the master declared gone after heartbeat_misses intervals of silence, by kind of peer.")):
            family = CounterMetricFamily(name, documentation, labels=["peer"])
            for peer in PEERS:
                family.add_metric([peer], counters[f"{key}_{peer}"])
            yield family
        listening = agent.listening
        caps = getattr(getattr(listening, "factory", None), "caps", None)
        yield _gauge("rcm_agent_port_connections", "Connections open on the agent port (robots, server VMs, "
                                                   "agents saying hello).", len(caps.open) if caps else 0)

    @staticmethod
    def _rdapi(site):
        if site is None:
            return
        yield _gauge("rcm_rdapi_connections", "Connections open on the RDAPI.", len(site.caps.open))
        yield _counter("rcm_rdapi_connections_refused_total", "RDAPI connections refused (503) for being over "
                                                              "the connection caps.", site.refused)
        yield _counter("rcm_rdapi_connections_dropped_total", "RDAPI connections dropped because a request took "
                                                              "longer than the request deadline to arrive.",
                       site.slow_dropped)


class Metrics(service.Service):
    """The master's metrics: a registry of its own, the hooks it listens to while running, ``scrape()``.

    ``agent``: the ``MasterAgent``; ``spaces``: its ``ServiceSpaceManager``; ``platform``: the
    ``PlatformCommands`` (``read()``); ``watch_site(site)``: the RDAPI's site, once made (it needs this object)."""

    name = "metrics"

    def __init__(self, agent, spaces, platform):
        self.agent = agent
        self.spaces = spaces
        self.platform = platform
        self.site = None
        self.rows = None
        self._counted = weakref.WeakSet()    # failed items already counted
        self._request_series = {}            # (route, method, code) -> (counter, histogram) children: labels()
                                             # takes a lock and builds a key each time, ~4x the cost of this
        registry = self.registry = prometheus_client.CollectorRegistry()
        self.hello = prometheus_client.Histogram(
            "rcm_hello_duration_seconds", "Time the master took to answer an accepted hello (robots and server "
            "VMs): admission, provisioning lookup, takeover.", buckets=HELLO_BUCKETS, registry=registry)
        self.pairing = prometheus_client.Histogram(
            "rcm_pairing_duration_seconds", "Time from a robot's hello to its service space paired (its first "
            "pairing in a session).", buckets=PAIRING_BUCKETS, registry=registry)
        self.item_failures = prometheus_client.Counter(
            "rcm_item_failures", "Service items that failed, by reason (each failed item once).", ["reason"],
            registry=registry)
        for reason in ITEM_FAILURES:
            self.item_failures.labels(reason)
        self.requests = prometheus_client.Counter(
            "rcm_rdapi_requests", "RDAPI requests by route (unknown paths: other), method and status (lost: the "
            "client left before the answer).", ["route", "method", "code"], registry=registry)
        self.request_duration = prometheus_client.Histogram(
            "rcm_rdapi_request_duration_seconds", "Time from a request's arrival (headers and body read) to its "
            "answer, by route.", ["route"], buckets=RDAPI_BUCKETS, registry=registry)
        registry.register(LiveState(self))
        prometheus_client.ProcessCollector(registry=registry)
        prometheus_client.PlatformCollector(registry=registry)

    def watch_site(self, site):
        self.site = site

    # -- hooks ---------------------------------------------------------------------------------------------------
    def startService(self):
        super().startService()
        self.agent.timing_observers.append(self._timed)
        self.spaces.observers.append(self._space_changed)
        if self.site is not None:
            self.site.resource.request_observers.append(self._request)

    def stopService(self):
        for hooks, fn in ((self.agent.timing_observers, self._timed), (self.spaces.observers, self._space_changed),
                          (self.site.resource.request_observers if self.site else [], self._request)):
            if fn in hooks:
                hooks.remove(fn)
        return super().stopService()

    def _timed(self, what, seconds):
        (self.hello if what == "hello" else self.pairing).observe(seconds)

    def _space_changed(self, ss_name):
        space = self.spaces.spaces.get(ss_name) if ss_name is not None else None
        for item in getattr(space, "items", ()):
            if item.state == FAILED and item not in self._counted:
                self._counted.add(item)
                self.item_failures.labels(item.failure or "other").inc()

    def _request(self, route, method, code, seconds):
        key = (route, method, code)
        series = self._request_series.get(key)
        if series is None:      # bounded: Rdapi.route_label and METHOD_LABELS, and the statuses the RDAPI answers
            series = self._request_series[key] = (self.requests.labels(*key), self.request_duration.labels(route))
        series[0].inc()
        series[1].observe(seconds)

    # -- the route -----------------------------------------------------------------------------------------------
    @defer.inlineCallbacks
    def scrape(self):
        """Deferred((content type, the text exposition format)) of every metric now."""
        rows = yield self.platform.read()
        self.rows = rows     # read by LiveState during generate_latest, which runs now, in this same call
        return prometheus_client.CONTENT_TYPE_LATEST, prometheus_client.generate_latest(self.registry)


class Unavailable(service.Service):
    """What serves ``/metrics`` on a master without prometheus_client: 503 with the line naming the package."""

    name = "metrics"

    def __init__(self, reason):
        self.reason = reason

    def watch_site(self, site):
        pass

    def startService(self):
        super().startService()
        log.warning("the RDAPI serves no /metrics: %s", self.reason)

    def scrape(self):
        return defer.fail(UnavailableError(f"this master serves no metrics: {self.reason}"))


def make_metrics(agent, spaces, platform):
    """``Metrics`` for the master, or ``Unavailable`` when prometheus_client cannot be imported."""
    if prometheus_client is None:
        return Unavailable(rcmp_deps.missing_line(_MISSING, why="for the RDAPI's /metrics"))
    return Metrics(agent, spaces, platform)
