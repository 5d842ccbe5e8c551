"""The ROS → broker path after the ROS callback: one sender thread per FIROS.

Owns what waits to be sent, when, and whether it may be sent at all: ROS callbacks only `offer()` a message (a
dict store under a lock, never a network call), keeping only the newest message per attribute (a replaced one
counts as skipped). The thread converts what it takes (so skipped messages are never deserialized nor converted),
adds `firosstamp` and `COMMAND`, sends the ready attributes of all robots in as few requests as the broker's size
limit allows, honours `pub_frequency` and each topic's `max_rate` (the whitelist's), and also carries out entity
creation and deletion so that they stay in order with updates.

Big values never block small ones: each value is encoded once, and a value over its topic's `max_size` or too
big for a request of `max_request_size` bytes (Orion's 1 MB by default; a message still serialized is judged by
`ros_conversion.json_size_lower_bound` before it is converted) is not sent: counted (`too_large`) and logged at
most once a minute per attribute with its size; the others are packed into requests under the limit, a big one
riding alone. A broker's 413 is taken the same way: the request is halved until the value that is too big rides
alone and is dropped; nothing is retried for its size.
Broker trouble: log it, keep the newest values, retry with backoff up to `retry_max_delay`, and when the broker
answers again re-create every entity with its newest values and tell the subscriptions (`on_recovered`).

What it did is counted for `/stats` and the metrics: `stats` (totals) and `skips` (values not sent, by one word of
`SKIP_REASONS`), and each value the broker took is timed from its arrival at FIROS to the broker's answer for the
`forward_observers` (``fn(seconds list)``, called on the sender thread; they never fail it).
"""

import collections
import logging
import threading
import time

from include.log_guard import Budget, shown
from include.ngsi_client import COMMAND, BrokerError, BrokerUnavailable, RequestTooLarge, json_string
from include.ngsi_encoding import FIROSSTAMP, NgsiEncodingError, split_firosstamp, with_firosstamp
from include.ros_conversion import ConversionError, SerializedMessage, json_size_lower_bound, message_to_dict

log = logging.getLogger("firos.sender")

MAX_BATCH = 1000
# why a value was not sent: a newer one came while it waited (superseded; rate_limited when it waited for its
# topic's max_rate or pub_frequency), it was too big, it could not be converted, the broker refused the update
# that carried it (4xx), or its topic or robot stopped being mapped while it waited
SKIP_REASONS = ("superseded", "rate_limited", "too_large", "conversion_error", "refused", "unmapped")
OWN_STAMPS_KEPT = 64
TOO_LARGE_LOG_INTERVAL = 60.0      # seconds between two log lines about one attribute's values being too big
SMALL_VALUE = 64 * 1024            # serialized bytes: smaller values of a batch go before any bigger one
MAX_COSTS_KEPT = 4096              # robots' and attribute names' request bytes remembered
NO_LIMITS = (0.0, None)
# a bound on what an item adds to a request besides its text: a comma, its name in COMMAND, and for a robot not in
# the request yet the robot's entity and COMMAND (names and robots are at most 256 characters long)
MAX_ITEM_OVERHEAD = 2048            # an attribute without limits of its own: (seconds between sends, max_size)


class Sender:
    """Entity lifecycle and attribute updates towards the broker, on one thread with its own client."""

    def __init__(self, client, settings, on_created=None, on_removed=None, on_recovered=None):
        self.client = client
        self.min_interval = settings.pub_frequency / 1000.0
        self._no_limits = (self.min_interval, None)
        self.max_request_size = settings.max_request_size
        self._body_overhead = client.body_overhead()
        self._command_overhead = len(client.encode_attribute(COMMAND, COMMAND, [])) + 1
        self.retry_max_delay = settings.retry_max_delay
        self.on_created = on_created or (lambda robot: None)
        self.on_removed = on_removed or (lambda robot: None)
        self.on_recovered = on_recovered or (lambda: None)
        self._cond = threading.Condition()
        self._pending = {}                 # (robot, attr) -> (type, msg, stamp)
        self._ops = collections.deque()    # ("create", robot) | ("delete", robot)
        self._robots = {}                  # robot -> {"created": bool, "static": {attr: (type, value)}}
        self._last_values = {}             # robot -> {attr: its text in the last update the broker took}
        self._limits = {}                  # (robot, attr) -> (seconds between two sends, max_size or None)
        self._too_large_values = {}        # (robot, attr) -> {"count", "size", "logged"}
        self._costs = {}                   # robot -> bytes it adds to a request; ("name", attr) -> its name's bytes;
                                           # ("command", names...) -> COMMAND's text
        self._last_sent = {}               # (robot, attr) -> monotonic time
        self._own_stamps = {}              # (robot, attr) -> deque of firosstamps FIROS sent
        self._down_since = None
        self._retry_at = 0.0
        self._delay = 0.0
        self._stop = False
        self.stats = {"offered": 0, "forwarded": 0, "skipped": 0, "requests": 0, "errors": 0,
                      "conversion_errors": 0, "too_large": 0}
        self.skips = collections.Counter({reason: 0 for reason in SKIP_REASONS})
        self.forward_observers = []        # fn(list of seconds from a value's arrival to the broker's answer)
        self.notes = Budget(log, "lines about values not sent")
        self._thread = threading.Thread(target=self._run, name="firos-sender", daemon=True)

    # --- called from other threads ----------------------------------------------------------------------------
    def start(self):
        self._thread.start()

    def stop(self, timeout=5.0):
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        self._thread.join(timeout)

    def offer(self, robot, attr, atype, msg, stamp=None):
        """Called by ROS callbacks: remember ``msg`` as the newest value of robot.attr. Never blocks on I/O."""
        stamp = time.time() if stamp is None else stamp
        key = (robot, attr)
        with self._cond:
            if robot not in self._robots:
                return
            self.stats["offered"] += 1
            if key in self._pending:
                self.stats["skipped"] += 1
                interval = self._limits.get(key, self._no_limits)[0]
                held = interval and time.monotonic() < self._last_sent.get(key, -1e9) + interval
                self.skips["rate_limited" if held else "superseded"] += 1
            self._pending[key] = (atype, msg, stamp)
            self._cond.notify()

    def create(self, robot, static_attrs):
        """Create (or re-create) the robot's entity with ``static_attrs`` ({attr: (type, value)})."""
        with self._cond:
            self._robots[robot] = {"created": False, "static": dict(static_attrs)}
            self._ops.append(("create", robot))
            self._cond.notify()

    def delete(self, robot):
        """Forget the robot's waiting values and limits and delete its entity."""
        with self._cond:
            self._robots.pop(robot, None)
            self.skips["unmapped"] += sum(1 for key in self._pending if key[0] == robot)
            for table in (self._pending, self._limits, self._too_large_values):
                for key in [k for k in table if k[0] == robot]:
                    del table[key]
            self._ops.append(("delete", robot))
            self._cond.notify()

    def set_limits(self, robot, attr, max_rate=None, max_size=None):
        """robot.attr is sent at most ``max_rate`` times a second (besides pub_frequency) and only values of at
        most ``max_size`` bytes (besides the request limit); None: no limit of its own."""
        interval = max(self.min_interval, 1.0 / max_rate if max_rate else 0.0)
        with self._cond:
            self._limits[(robot, attr)] = (interval, max_size)
            self._cond.notify()

    def forget(self, robot, attr):
        """robot.attr is no longer mapped: drop its waiting value and send it no more."""
        with self._cond:
            if self._pending.pop((robot, attr), None) is not None:
                self.stats["skipped"] += 1
                self.skips["unmapped"] += 1
            self._last_values.get(robot, {}).pop(attr, None)
            self._limits.pop((robot, attr), None)

    def command_taken(self, robot):
        """FIROS published a command of ``robot``: write COMMAND back to [] (unless an update of FIROS's own
        that rewrites COMMAND anyway is waiting), so that a notification the broker sends later without a new
        update (a renewal, a change of another attribute) names no command."""
        with self._cond:
            if robot not in self._robots or ("ack", robot) in self._ops:
                return
            if any(key[0] == robot for key in self._pending):
                return
            self._ops.append(("ack", robot))
            self._cond.notify()

    def recreate(self, robot):
        """Send the robot's entity again with its newest values (the broker lost it)."""
        with self._cond:
            if robot in self._robots:
                self._ops.append(("create", robot))
                self._cond.notify()

    def is_own(self, robot, attr, value):
        """True when ``value`` carries a firosstamp that FIROS itself sent for robot.attr."""
        if not isinstance(value, dict) or FIROSSTAMP not in value:
            return False
        _, stamp = split_firosstamp(value)
        with self._cond:
            return stamp is not None and stamp in self._own_stamps.get((robot, attr), ())

    def broker_up(self):
        with self._cond:
            return self._down_since is None

    def snapshot_stats(self):
        with self._cond:
            stats = dict(self.stats)
            stats["waiting"] = len(self._pending)
            stats["broker_up"] = self._down_since is None
            too_large = {}
            for (robot, attr), entry in self._too_large_values.items():
                too_large.setdefault(robot, {})[attr] = {"count": entry["count"], "size": entry["size"]}
            stats["too_large_values"] = too_large
            return stats

    def wait_idle(self, timeout):
        """True once nothing waits to be sent (used at shutdown)."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while (self._pending or self._ops) and self._down_since is None:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(min(left, 0.05))
            return not self._pending and not self._ops

    # --- the thread -------------------------------------------------------------------------------------------
    def _run(self):
        while True:
            with self._cond:
                op, batch = self._wait_for_work()
                if op is None and batch is None:
                    return
            try:
                if op is not None:
                    self._do_op(op)
                else:
                    self._send(batch)
            except Exception:  # the sender thread must outlive any one bad batch
                log.exception("unexpected error while sending to the context broker")
            with self._cond:
                self._cond.notify_all()

    def _wait_for_work(self):
        """Under the lock: the next op, or the next batch of ready pending items; (None, None) to stop."""
        while True:
            if self._stop:
                return None, None
            now = time.monotonic()
            if now < self._retry_at:
                self._cond.wait(self._retry_at - now)
                continue
            if self._ops:
                return self._ops.popleft(), None
            batch, next_ready = [], None
            for key, item in self._pending.items():
                robot = key[0]
                state = self._robots.get(robot)
                if state is None or not state["created"]:
                    continue
                ready_at = self._last_sent.get(key, -1e9) + self._limits.get(key, self._no_limits)[0]
                if ready_at <= now:
                    batch.append((key, item))
                    if len(batch) >= MAX_BATCH:
                        break
                elif next_ready is None or ready_at < next_ready:
                    next_ready = ready_at
            if batch:
                for key, _ in batch:
                    del self._pending[key]
                return None, batch
            self._cond.wait(None if next_ready is None else max(0.0, next_ready - now))

    def _do_op(self, op):
        kind, robot = op
        try:
            if kind == "ack":
                with self._cond:
                    if robot not in self._robots or not self._robots[robot]["created"]:
                        return
                self.client.update({robot: {COMMAND: (COMMAND, [])}})
                self._broker_answered()
            elif kind == "create":
                self._create(robot)
            else:
                self.client.delete_entity(robot)
                with self._cond:
                    self._last_values.pop(robot, None)
                    for key in [k for k in self._last_sent if k[0] == robot]:
                        self._last_sent.pop(key, None)
                        self._own_stamps.pop(key, None)
                self._broker_answered()
                log.info("entity %s removed from the context broker", robot)
                self.on_removed(robot)
        except BrokerUnavailable as exc:
            with self._cond:
                self._ops.appendleft(op)
            self._broker_failed(exc)
        except (BrokerError, ValueError) as exc:
            self.stats["errors"] += 1
            log.error("the context broker refused to %s entity %s: %s", kind, robot, exc)

    def _create(self, robot):
        """Send the entity with its static attributes and the newest values sent before (the broker may have
        lost them), in as many requests as the size limit needs; created once the broker took one of them."""
        with self._cond:
            state = self._robots.get(robot)
            if state is None:
                return
            static = dict(state["static"])
            last = dict(self._last_values.get(robot, {}))
        items = [(robot, name, self.client.encode_attribute(name, atype, value), None)
                 for name, (atype, value) in static.items() if name not in last]
        items += [(robot, name, text, None) for name, text in last.items()]
        accepted = False
        for request in self._pack(items) or [[]]:
            _, ok = self._post(request, robots=() if request else (robot,), counted=False)
            accepted = accepted or ok
        if not accepted:
            return
        with self._cond:
            if robot in self._robots:
                self._robots[robot]["created"] = True
        self._broker_answered()
        log.info("entity %s created in the context broker", robot)
        self.on_created(robot)

    def _send(self, batch):
        """Convert and send a batch of waiting values: each value encoded once, the values packed into requests
        under the size limit (a big one rides alone), what is too big reported and dropped. Small values are
        converted and sent first, so that converting a big one never delays them."""
        groups = [[]]
        for entry in batch:
            if isinstance(entry[1][1], SerializedMessage) and entry[1][1].size >= SMALL_VALUE:
                groups.append([entry])
            else:
                groups[0].append(entry)
        sent_any = False
        for number, group in enumerate(groups):
            items = []
            for (robot, attr), (atype, msg, stamp) in group:
                text = self._encode(robot, attr, atype, msg, stamp)
                if text is not None:
                    items.append((robot, attr, text, stamp))
            requests = self._pack(items)
            for index, request in enumerate(requests):
                try:
                    sent, _ = self._post(request)
                except BrokerUnavailable as exc:
                    unsent = {(robot, attr) for req in requests[index:] for robot, attr, _, _ in req}
                    unsent.update(key for later in groups[number + 1:] for key, _ in later)
                    with self._cond:             # keep the newest: a value that arrived meanwhile wins
                        for key, item in batch:
                            if key in unsent and key[0] in self._robots:
                                self._pending.setdefault(key, item)
                    self._broker_failed(exc)
                    return
                self._record(sent)
                sent_any = True
        if sent_any:
            self._broker_answered()

    def _encode(self, robot, attr, atype, msg, stamp):
        """The attribute's text as the update carries it, or None when it cannot or may not be sent. A message
        still serialized whose JSON is sure to be over its limit is refused without being converted."""
        max_size = self._limits.get((robot, attr), NO_LIMITS)[1]     # one dict read: no lock needed
        try:
            if isinstance(msg, SerializedMessage):
                if msg.size >= SMALL_VALUE:
                    bound = json_size_lower_bound(msg.msg_class, msg.data)
                    cap, why = self._cap(robot, attr, max_size)
                    if bound > cap:
                        self._too_large(robot, attr, bound, why, estimated=True)
                        return None
                msg = msg.message()
            text = self.client.encode_attribute(
                attr, atype, with_firosstamp(msg if isinstance(msg, dict) else message_to_dict(msg), stamp))
        except (ConversionError, NgsiEncodingError, ValueError) as exc:
            self.stats["conversion_errors"] += 1
            self.skips["conversion_error"] += 1
            self.notes.log(logging.ERROR, "cannot convert a message of %s.%s: %s", robot, attr, shown(str(exc)))
            return None
        if len(text) > SMALL_VALUE or (max_size is not None and len(text) > max_size):
            cap, why = self._cap(robot, attr, max_size)
            if len(text) > cap:
                self._too_large(robot, attr, len(text), why)
                return None
        return text

    def _cap(self, robot, attr, max_size):
        """(the most bytes a value of robot.attr may take, and the limit that says so, as words)."""
        room = self.max_request_size - self._alone_overhead(robot, attr)
        if max_size is not None and max_size < room:
            return max_size, f"its max_size of {max_size} bytes"
        return room, f"the broker's request limit of {self.max_request_size} bytes (max_request_size)"

    def _alone_overhead(self, robot, attr):
        """Bytes of a request carrying one attribute besides the attribute's own text (COMMAND included)."""
        return self._body_overhead + self._entity_cost(robot) + self._command_overhead + 2 * self._name_cost(attr)

    def _entity_cost(self, robot):
        """Bytes one more robot adds to a request, besides its attributes (remembered: robots are few)."""
        cost = self._costs.get(robot)
        if cost is None:
            cost = self._remember(robot, self.client.entity_overhead(robot))
        return cost

    def _name_cost(self, name):
        """Bytes an attribute's name adds to COMMAND (remembered: attributes are the mapped topics)."""
        key = ("name", name)
        cost = self._costs.get(key)
        if cost is None:
            cost = self._remember(key, len(json_string(name)) + 1)
        return cost

    def _command_text(self, names):
        """COMMAND listing ``names``, as the update carries it (remembered: the same few lists come again)."""
        key = ("command",) + tuple(names)
        text = self._costs.get(key)
        if text is None:
            text = self._remember(key, self.client.encode_attribute(COMMAND, COMMAND, list(names)))
        return text

    def _remember(self, key, cost):
        if len(self._costs) >= MAX_COSTS_KEPT:      # robots and topics that came and went: start afresh
            self._costs.clear()
        self._costs[key] = cost
        return cost

    def _pack(self, items):
        """Requests (lists of items) each under max_request_size with every robot's COMMAND, items in order; an
        item too big even alone is reported and left out."""
        if not items:
            return []
        # the common case: small values that fit in one request whatever their names and robots
        if sum(len(item[2]) for item in items) + len(items) * MAX_ITEM_OVERHEAD <= self.max_request_size:
            return [items]
        requests, current, size, robots = [], [], self._body_overhead, set()
        for item in items:
            robot, name, text, _ = item
            cost = self._item_cost(item, robot not in robots)
            if size + cost > self.max_request_size and current:
                requests.append(current)
                current, size, robots = [], self._body_overhead, set()
                cost = self._item_cost(item, True)
            if size + cost > self.max_request_size:
                self._too_large(robot, name, len(text), f"the broker's request limit of {self.max_request_size} "
                                                        f"bytes (max_request_size)")
                continue
            current.append(item)
            size += cost
            robots.add(robot)
        if current:
            requests.append(current)
        return requests

    def _item_cost(self, item, new_robot):
        robot, name, text, _ = item
        cost = len(text) + 1 + self._name_cost(name)
        if new_robot:
            cost += self._entity_cost(robot) + self._command_overhead
        return cost

    def _post(self, items, robots=(), counted=True):
        """Send ``items`` (and COMMAND for their robots and ``robots``) in one update, halved on a 413 until a
        value rides alone. Returns (items the broker took, whether it took any request). BrokerUnavailable
        goes up; any other refusal is logged and counted. ``counted``: the request counts in stats' requests
        (updates of values; entity creations do not)."""
        encoded, names = {robot: [] for robot in robots}, {robot: [] for robot in robots}
        for robot, name, text, _ in items:
            encoded.setdefault(robot, []).append(text)
            names.setdefault(robot, []).append(name)
        for robot, texts in encoded.items():
            texts.append(self._command_text(names[robot]))
        try:
            self.stats["requests"] += counted
            self.client.send_update(encoded)
        except RequestTooLarge as exc:
            if len(items) > 1:
                half = len(items) // 2
                first = self._post(items[:half], robots, counted)
                second = self._post(items[half:], robots, counted)
                return first[0] + second[0], first[1] or second[1]
            for robot, name, text, _ in items:
                self._too_large(robot, name, exc.size or len(text), "what the broker takes (it answered 413)")
            return [], False
        except (BrokerError, ValueError) as exc:
            self.stats["errors"] += 1
            self.skips["refused"] += sum(1 for item in items if item[3] is not None)
            self.notes.log(logging.ERROR, "the context broker refused an update of %s: %s",
                           shown(", ".join(sorted(encoded))), exc)
            return [], False
        return list(items), True

    def _record(self, sent):
        """Remember what the broker took: the newest value of each attribute (re-sent when the entity is made
        again), when it was sent (rate limits) and its firosstamp (FIROS's own updates coming back)."""
        now, wall = time.monotonic(), time.time()
        latencies = []
        with self._cond:
            for robot, attr, text, stamp in sent:
                self._last_values.setdefault(robot, {})[attr] = text
                if stamp is None:
                    continue
                key = (robot, attr)
                self._last_sent[key] = now
                self._own_stamps.setdefault(key, collections.deque(maxlen=OWN_STAMPS_KEPT)).append(stamp)
                self.stats["forwarded"] += 1
                latencies.append(wall - stamp)
        for observe in list(self.forward_observers) if latencies else ():
            try:
                observe(latencies)
            except Exception:   # a metric must never stop the sender
                log.exception("a forward observer failed")

    def _too_large(self, robot, attr, size, why, estimated=False):
        """Count a value not sent for its size; log it at most once a TOO_LARGE_LOG_INTERVAL per attribute."""
        now = time.monotonic()
        with self._cond:
            self.stats["too_large"] += 1
            self.skips["too_large"] += 1
            entry = self._too_large_values.setdefault((robot, attr), {"count": 0, "size": 0, "logged": None})
            entry["count"] += 1
            entry["size"] = size
            due = entry["logged"] is None or now - entry["logged"] >= TOO_LARGE_LOG_INTERVAL
            if due:
                entry["logged"] = now
            count = entry["count"]
        if due:
            log.warning("%s.%s not sent: a value of %s%d bytes is over %s (%d not sent so far; said at most once "
                        "a minute)", robot, attr, "at least " if estimated else "", size, why, count)

    def _broker_failed(self, exc):
        with self._cond:
            self.stats["errors"] += 1
            first = self._down_since is None
            if first:
                self._down_since = time.monotonic()
                self._delay = 0.1
            else:
                self._delay = min(self._delay * 2, self.retry_max_delay)
            self._retry_at = time.monotonic() + self._delay
            if first:
                for robot, state in self._robots.items():   # the broker may come back empty: re-create
                    state["created"] = False                 # (the create ops are also the retries)
                    if ("create", robot) not in self._ops:
                        self._ops.append(("create", robot))
        if first:
            log.error("context broker unavailable (%s); keeping the newest values and retrying", exc)
        else:
            log.debug("context broker still unavailable (%s); next try in %.1fs", exc, self._delay)

    def _broker_answered(self):
        with self._cond:
            if self._down_since is None:
                return
            outage = time.monotonic() - self._down_since
            self._down_since = None
            self._delay = 0.0
            self._retry_at = 0.0
            for robot, state in self._robots.items():
                if not state["created"] and ("create", robot) not in self._ops:
                    self._ops.append(("create", robot))
        log.warning("context broker reachable again after %.1fs: re-creating entities and subscriptions", outage)
        self.on_recovered()
