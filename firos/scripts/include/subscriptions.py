"""Broker subscriptions for broker → ROS: one per robot that has publisher topics, on its own thread and client.

Owns their life: create (v2 `POST /v2/subscriptions` with `expires` and `throttling`; v1 `subscribeContext`
ONCHANGE), refresh `subscription_refresh_delay` after each (re)subscription so that they never expire while FIROS
runs (v2 PATCH `expires`; v1 `updateContextSubscription`), re-create them when the broker forgot them or came back
after an outage, and remove them on disconnect and at shutdown. The condition lists the robot's publisher
attributes (an empty list means any attribute, used when the whitelist has patterns no known topic matched yet).
"""

import logging
import threading
import time

from include.ngsi_client import BrokerError, BrokerUnavailable

log = logging.getLogger("firos.subscriptions")


class Subscriptions:
    def __init__(self, client, settings, url, on_lost=None):
        self.client = client
        self.url = url
        self.length = settings.subscription_length
        self.refresh_delay = settings.subscription_refresh_delay
        self.throttling = settings.throttling
        self.retry_max_delay = settings.retry_max_delay
        self.on_lost = on_lost or (lambda robot: None)
        self._cond = threading.Condition()
        self._wanted = {}      # robot -> tuple(condition attrs)
        self._active = {}      # robot -> {"id", "attrs", "refresh_at"}
        self._obsolete = []    # subscription ids to remove
        self._retry_at = 0.0
        self._delay = 0.0
        self._stop = False
        self._thread = threading.Thread(target=self._run, name="firos-subscriptions", daemon=True)

    def start(self):
        self._thread.start()

    def set(self, robot, attrs):
        """Keep a subscription for ``robot`` with condition ``attrs`` (list; [] = any attribute)."""
        with self._cond:
            self._wanted[robot] = tuple(sorted(attrs))
            self._cond.notify()

    def remove(self, robot):
        with self._cond:
            self._wanted.pop(robot, None)
            active = self._active.pop(robot, None)
            if active:
                self._obsolete.append(active["id"])
            self._cond.notify()

    def renew_all(self):
        """The broker came back (maybe empty): subscribe every robot again, dropping the old ids."""
        with self._cond:
            for robot, active in list(self._active.items()):
                self._obsolete.append(active["id"])
                del self._active[robot]
            self._retry_at = 0.0
            self._cond.notify()

    def ids(self):
        with self._cond:
            return {robot: active["id"] for robot, active in self._active.items()}

    def stop(self, timeout=5.0):
        """Stop the thread and remove every subscription from the broker (best effort)."""
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        self._thread.join(timeout)
        with self._cond:
            ids = [a["id"] for a in self._active.values()] + self._obsolete
            self._active.clear()
            self._obsolete = []
        for sub_id in ids:
            try:
                with self.client.lock:
                    self.client.unsubscribe(sub_id)
            except (BrokerUnavailable, BrokerError) as exc:
                log.warning("could not remove subscription %s at shutdown: %s", sub_id, exc)

    # --- the thread -------------------------------------------------------------------------------------------
    def _next_job(self):
        while not self._stop:
            now = time.monotonic()
            if now < self._retry_at:
                self._cond.wait(self._retry_at - now)
                continue
            if self._obsolete:
                return ("unsubscribe", self._obsolete[0], None)
            next_at = None
            for robot, attrs in self._wanted.items():
                active = self._active.get(robot)
                if active is None or active["attrs"] != attrs:
                    return ("subscribe", robot, attrs)
                if active["refresh_at"] <= now:
                    return ("refresh", robot, active)
                next_at = active["refresh_at"] if next_at is None else min(next_at, active["refresh_at"])
            self._cond.wait(None if next_at is None else max(0.0, next_at - now))
        return None

    def _run(self):
        while True:
            with self._cond:
                job = self._next_job()
            if job is None:
                return
            try:
                self._do(job)
                with self._cond:
                    self._delay = 0.0
            except BrokerUnavailable as exc:
                with self._cond:
                    self._delay = min(max(self._delay * 2, 0.2), self.retry_max_delay)
                    self._retry_at = time.monotonic() + self._delay
                log.warning("subscriptions: broker unavailable (%s); retrying in %.1fs", exc, self._delay)
            except BrokerError as exc:
                log.error("subscriptions: the broker refused %s for %s: %s", job[0], job[1], exc)
                with self._cond:
                    if job[0] == "unsubscribe" and self._obsolete and self._obsolete[0] == job[1]:
                        self._obsolete.pop(0)
                    elif job[0] == "refresh":
                        self._active.pop(job[1], None)   # forgotten by the broker: subscribe again
                    else:
                        self._retry_at = time.monotonic() + self.retry_max_delay
                if job[0] == "refresh":
                    self.on_lost(job[1])

    def _do(self, job):
        kind, what, extra = job
        if kind == "unsubscribe":
            with self.client.lock:
                self.client.unsubscribe(what)
            with self._cond:
                if self._obsolete and self._obsolete[0] == what:
                    self._obsolete.pop(0)
            log.info("subscription %s removed", what)
        elif kind == "subscribe":
            with self.client.lock:
                sub_id = self.client.subscribe(what, self.url, self.length, self.throttling, time.time(), extra)
            with self._cond:
                old = self._active.get(what)
                if what in self._wanted:
                    self._active[what] = {"id": sub_id, "attrs": extra,
                                          "refresh_at": time.monotonic() + self.refresh_delay}
                    if old:
                        self._obsolete.append(old["id"])
                else:
                    self._obsolete.append(sub_id)
            log.info("subscribed to %s (condition %s) as %s, notifications to %s", what,
                     list(extra) or "any attribute", sub_id, self.url)
        else:
            with self.client.lock:
                self.client.refresh(extra["id"], self.length, time.time())
            with self._cond:
                if self._active.get(what) is extra:
                    extra["refresh_at"] = time.monotonic() + self.refresh_delay
            log.debug("subscription %s of %s refreshed", extra["id"], what)
