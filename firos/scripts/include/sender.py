"""The ROS → broker path after the ROS callback: one sender thread per FIROS.

Owns what waits to be sent and when: ROS callbacks only `offer()` a message (a dict store under a lock, never a
network call), keeping only the newest message per attribute (a replaced one counts as skipped). The thread
converts what it takes (so skipped messages are never converted), adds `firosstamp` and `COMMAND`, sends all ready
attributes of all robots in one batch, honours `pub_frequency` (minimum milliseconds between two sends of one
attribute), and also carries out entity creation and deletion so that they stay in order with updates.
Broker trouble: log it, keep the newest values, retry with backoff up to `retry_max_delay`, and when the broker
answers again re-create every entity with its newest values and tell the subscriptions (`on_recovered`).
"""

import collections
import logging
import threading
import time

from include.ngsi_client import COMMAND, BrokerError, BrokerUnavailable
from include.ngsi_encoding import FIROSSTAMP, NgsiEncodingError, split_firosstamp, with_firosstamp
from include.ros_conversion import ConversionError, message_to_dict

log = logging.getLogger("firos.sender")

MAX_BATCH = 1000
OWN_STAMPS_KEPT = 64


class Sender:
    """Entity lifecycle and attribute updates towards the broker, on one thread with its own client."""

    def __init__(self, client, settings, on_created=None, on_removed=None, on_recovered=None):
        self.client = client
        self.min_interval = settings.pub_frequency / 1000.0
        self.retry_max_delay = settings.retry_max_delay
        self.on_created = on_created or (lambda robot: None)
        self.on_removed = on_removed or (lambda robot: None)
        self.on_recovered = on_recovered or (lambda: None)
        self._cond = threading.Condition()
        self._pending = {}                 # (robot, attr) -> (type, msg, stamp)
        self._ops = collections.deque()    # ("create", robot) | ("delete", robot)
        self._robots = {}                  # robot -> {"created": bool, "static": {attr: (type, value)}}
        self._last_values = {}             # robot -> {attr: (type, value)} as last sent
        self._last_sent = {}               # (robot, attr) -> monotonic time
        self._own_stamps = {}              # (robot, attr) -> deque of firosstamps FIROS sent
        self._down_since = None
        self._retry_at = 0.0
        self._delay = 0.0
        self._stop = False
        self.stats = {"offered": 0, "forwarded": 0, "skipped": 0, "requests": 0, "errors": 0,
                      "conversion_errors": 0}
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
            self._pending[key] = (atype, msg, stamp)
            self._cond.notify()

    def create(self, robot, static_attrs):
        """Create (or re-create) the robot's entity with ``static_attrs`` ({attr: (type, value)})."""
        with self._cond:
            self._robots[robot] = {"created": False, "static": dict(static_attrs)}
            self._ops.append(("create", robot))
            self._cond.notify()

    def delete(self, robot):
        """Forget the robot's waiting values and delete its entity."""
        with self._cond:
            self._robots.pop(robot, None)
            for key in [k for k in self._pending if k[0] == robot]:
                del self._pending[key]
            self._ops.append(("delete", robot))
            self._cond.notify()

    def forget(self, robot, attr):
        """robot.attr is no longer mapped: drop its waiting value and send it no more."""
        with self._cond:
            if self._pending.pop((robot, attr), None) is not None:
                self.stats["skipped"] += 1
            self._last_values.get(robot, {}).pop(attr, None)

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
                ready_at = self._last_sent.get(key, -1e9) + self.min_interval
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
                with self._cond:
                    state = self._robots.get(robot)
                    if state is None:
                        return
                    attrs = dict(state["static"])
                    attrs.update(self._last_values.get(robot, {}))
                sent = [a for a in attrs if a != COMMAND]
                attrs[COMMAND] = (COMMAND, sent)
                self.client.update({robot: attrs})
                with self._cond:
                    if robot in self._robots:
                        self._robots[robot]["created"] = True
                self._broker_answered()
                log.info("entity %s created in the context broker", robot)
                self.on_created(robot)
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

    def _send(self, batch):
        entities = {}
        stamps = []
        for (robot, attr), (atype, msg, stamp) in batch:
            try:
                value = with_firosstamp(msg if isinstance(msg, dict) else message_to_dict(msg), stamp)
            except (ConversionError, NgsiEncodingError) as exc:
                self.stats["conversion_errors"] += 1
                log.error("cannot convert a message of %s.%s: %s", robot, attr, exc)
                continue
            entities.setdefault(robot, {})[attr] = (atype, value)
            stamps.append(((robot, attr), stamp))
        if not entities:
            return
        for robot, attrs in entities.items():
            attrs[COMMAND] = (COMMAND, [a for a in attrs if a != COMMAND])
        try:
            self.stats["requests"] += 1
            self.client.update(entities)
        except BrokerUnavailable as exc:
            with self._cond:
                for key, item in batch:          # keep the newest: a value that arrived meanwhile wins
                    if key[0] in self._robots:
                        self._pending.setdefault(key, item)
            self._broker_failed(exc)
            return
        except (BrokerError, ValueError) as exc:
            self.stats["errors"] += 1
            log.error("the context broker refused an update of %s: %s", ", ".join(sorted(entities)), exc)
            return
        now = time.monotonic()
        with self._cond:
            for robot, attrs in entities.items():
                values = self._last_values.setdefault(robot, {})
                for attr, item in attrs.items():
                    if attr != COMMAND:
                        values[attr] = item
            for key, stamp in stamps:
                self._last_sent[key] = now
                self._own_stamps.setdefault(key, collections.deque(maxlen=OWN_STAMPS_KEPT)).append(stamp)
            self.stats["forwarded"] += len(stamps)
        self._broker_answered()

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
