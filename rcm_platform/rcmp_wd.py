"""Heartbeats ("watchdog"): who is late, and the callback when a peer is declared gone.

Both ends of an agent-to-agent connection run one ``Watchdog`` each. Every ``interval`` seconds it looks at when
the peer was last heard from (any frame counts: answers to our beats, the peer's own beats, other requests);
if the peer has been silent for ``misses * interval`` seconds it stops and calls ``on_gone(silent_seconds)``
once; otherwise it sends one beat through ``send_beat()`` (a callable returning a Deferred, whose failure only
means "not heard", never an error). A check that runs more than half an interval late means this agent itself
was stalled: frames may be waiting unread, so the peer is judged at the next check instead. Time comes from the ``clock`` (the reactor, or ``task.Clock`` in tests).
A check that has heard nothing from the peer for more than ``MISSED_AFTER`` intervals, the peer not yet gone, counts
a missed beat: ``on_miss()`` is told (the master counts them for ``/metrics``). Not "nothing since the check
before": a peer that beats by itself (the master sends no beats to one, ``rcmp_event``) has its beats land near
our checks, on either side as the two loops' lateness varies, so one interval may see two and the next none.
"""

import logging

from twisted.internet import task

log = logging.getLogger("rcmp.wd")

MISSED_AFTER = 1.5               # intervals of silence a check counts as a missed beat


class Watchdog:
    """Beats to one peer and declares it gone after ``misses`` intervals of silence."""

    def __init__(self, clock, interval, misses, send_beat, last_heard, on_gone, name="peer", on_miss=None):
        if interval <= 0:
            raise ValueError(f"heartbeat interval must be positive, got {interval!r}")
        if misses < 1:
            raise ValueError(f"heartbeat misses must be at least 1, got {misses!r}")
        self.clock = clock
        self.interval = float(interval)
        self.misses = int(misses)
        self.send_beat = send_beat
        self.last_heard = last_heard
        self.on_gone = on_gone
        self.on_miss = on_miss
        self.name = name
        self.gone = False
        self._loop = None
        self._last_tick = None

    @property
    def limit(self):
        """Seconds of silence after which the peer is gone."""
        return self.interval * self.misses

    @property
    def running(self):
        return self._loop is not None and self._loop.running

    def start(self):
        if self.running:
            return
        self._loop = task.LoopingCall(self._tick)
        self._loop.clock = self.clock
        self._last_tick = self.clock.seconds()
        self._loop.start(self.interval, now=False)

    def stop(self):
        if self.running:
            self._loop.stop()
        self._loop = None

    def silent_for(self):
        """Seconds since the peer was last heard from."""
        return self.clock.seconds() - self.last_heard()

    def _tick(self):
        now = self.clock.seconds()
        previous = self._last_tick      # when the last beat went out
        late = now - previous - self.interval
        self._last_tick = now
        silent = self.silent_for()
        if late > self.interval / 2:
            # this agent itself was stalled (busy machine): frames the peer sent meanwhile may be waiting
            # unread, so judge the peer at the next tick, after the reactor has read them
            log.debug("heartbeat check for %s ran %.1f s late; not judging this time", self.name, late)
        elif silent >= self.limit:
            self.stop()
            if not self.gone:
                self.gone = True
                log.warning("%s silent for %.1f s (limit %.1f s): gone", self.name, silent, self.limit)
                self.on_gone(silent)
            return
        elif self.on_miss is not None and silent > MISSED_AFTER * self.interval:
            self.on_miss()
        d = self.send_beat()
        if d is not None:
            d.addErrback(lambda f: log.debug("heartbeat to %s not answered: %s", self.name, f.getErrorMessage()))
