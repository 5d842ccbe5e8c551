"""The agent process's own resources: its open-file limit and its garbage collector.

Owns:

- ``raise_open_files()``: at start the soft ``RLIMIT_NOFILE`` goes up to the hard limit (at most
  ``NOFILE_CEILING``: the children inherit it, and a program that loops over every possible descriptor would pay
  for more). A master holds one descriptor per robot and server VM (2,035 for 2,000 robots and 20 server VMs),
  and a shell's usual soft limit of 1,024 capped its agent port at 256 connections; the agent port's default cap
  follows the limit (``rcmp_inter_communication.default_max_connections``).
- ``GcFreezer``: the garbage collector's full collections walk every object the agent tracks (about 65 per
  connected robot); at 2,000 robots each stopped the event loop for 0.1-0.4 s, 142 times while they paired.
  Every ``FREEZE_EVERY`` seconds the young generations are collected and everything that survived is frozen
  (``gc.freeze()``), so later collections walk only what is newer; every ``THAW_EVERY`` seconds everything is
  thawed and collected once (what became cyclic garbage while frozen, a session that ended, say, is freed
  then), and frozen again.
"""

import gc
import logging
import resource

from twisted.internet import task

log = logging.getLogger("rcmp.resources")

NOFILE_CEILING = 65536           # the most the soft open-file limit is raised to
FREEZE_EVERY = 10.0              # seconds between two freezes of what the agent holds
THAW_EVERY = 600.0               # seconds between two full collections of everything


def raise_open_files():
    """Raise the soft open-file limit to the hard one (at most ``NOFILE_CEILING``); ``(before, after)``."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    target = NOFILE_CEILING if hard == resource.RLIM_INFINITY else min(hard, NOFILE_CEILING)
    if soft != resource.RLIM_INFINITY and soft < target:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
        except (ValueError, OSError) as exc:
            log.warning("open-file limit stays %d (raising it to %d failed: %s)", soft, target, exc)
            return soft, soft
        log.info("open-file limit raised from %d to %d", soft, target)
        return soft, target
    return soft, soft


class GcFreezer:
    """Freezes what the agent holds every ``freeze_every`` seconds and thaws and collects it all every
    ``thaw_every`` seconds (see the module's docstring). ``clock``: the reactor, or ``task.Clock`` in tests."""

    def __init__(self, clock, freeze_every=FREEZE_EVERY, thaw_every=THAW_EVERY):
        self.clock = clock
        self.freeze_every = freeze_every
        self.thaw_every = thaw_every
        self._loop = None
        self._last_thaw = None
        self.freezes = 0
        self.thaws = 0

    def start(self):
        self._last_thaw = self.clock.seconds()
        self._loop = task.LoopingCall(self._tick)
        self._loop.clock = self.clock
        self._loop.start(self.freeze_every, now=False)

    def stop(self):
        if self._loop is not None and self._loop.running:
            self._loop.stop()
        self._loop = None
        gc.unfreeze()

    def _tick(self):
        now = self.clock.seconds()
        if now - self._last_thaw >= self.thaw_every:
            self._last_thaw = now
            gc.unfreeze()
            gc.collect()
            self.thaws += 1
        else:
            gc.collect(1)            # the young generations: their cyclic garbage must not be frozen
        gc.freeze()
        self.freezes += 1
