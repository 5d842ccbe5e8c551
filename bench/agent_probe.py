"""Runs the RCM agent with probes a benchmark switches on for one phase of a run: the event loop's lateness,
garbage-collection pauses and, when asked, ``cProfile`` of the main thread (the reactor).

``python3 -m bench.agent_probe [--profile] PREFIX AGENT_ARGS...`` runs ``rcm_platform``'s ``main(AGENT_ARGS)``
(the same default reactor the agent installs). On SIGUSR1 a phase starts (its name read from ``PREFIX.phase``,
which the benchmark writes first); on SIGUSR2 it ends and ``PREFIX-PHASE.json`` is written:

- ``lag``: seconds each look at the loop (every ``LAG_EVERY`` s) came late;
- ``gc``: seconds each collection of the oldest generation took;
- ``objects``: objects the collector tracks at the end, and ``kinds``, the most common types among them;
- ``stalls``: while the loop has not looked for ``STALL`` s, a thread samples the main thread's stack every
  ``STALL_EVERY`` s (the way a ``faulthandler`` probe does); the samples counted by their innermost frames (a
  sample that found the interpreter held by a collection comes late and names what ran after it).

With ``--profile`` also ``PREFIX-PHASE.prof`` (read it with ``pstats``). Threads (the SQLite writes,
``deferToThread``) are not profiled: compare the process's CPU with its main thread's
(``/proc/PID/task/PID/stat``). Generators (``inlineCallbacks``) count one call per resumption. The looks cost a
few microseconds ten times a second.
"""

import cProfile
import collections
import gc
import json
import sys
import threading
import time
import traceback

LAG_EVERY = 0.1
STALL = 1.0          # seconds without a look at the loop that count as a stall
STALL_EVERY = 0.2    # seconds between two samples of a stalled main thread
STALL_FRAMES = 8     # innermost frames kept per sample


class Probe:
    def __init__(self, prefix, profile):
        self.prefix = prefix
        self.profile_wanted = profile
        self.profile = None
        self.phase = None
        self.lag = []
        self.gc = []
        self._at = None
        self._gc_began = None
        self.stalls = collections.Counter()
        self.main_ident = threading.get_ident()

    def watch_stalls(self):
        """In a thread: sample the main thread's stack while its loop is stalled."""
        while True:
            time.sleep(STALL_EVERY)
            at = self._at
            if self.phase is None or at is None or time.monotonic() - at < STALL:
                continue
            frame = sys._current_frames().get(self.main_ident)
            if frame is None:
                continue
            lines = traceback.format_stack(frame)[-STALL_FRAMES:]
            self.stalls["".join(line.split("\n")[0].strip() + "\n" for line in lines)] += 1

    def look(self):
        now = time.monotonic()
        if self._at is not None and self.phase is not None:
            self.lag.append(max(0.0, now - self._at - LAG_EVERY))
        self._at = now

    def collected(self, what, info):
        if info.get("generation") != 2:
            return
        if what == "start":
            self._gc_began = time.monotonic()
        elif self._gc_began is not None and self.phase is not None:
            self.gc.append(time.monotonic() - self._gc_began)

    def start(self, signum, frame):
        try:
            with open(self.prefix + ".phase") as f:
                self.phase = f.read().strip() or "run"
        except OSError:
            self.phase = "run"
        self.lag, self.gc = [], []
        self.stalls = collections.Counter()
        if self.profile_wanted:
            self.profile = cProfile.Profile()
            self.profile.enable()

    def stop(self, signum, frame):
        profile, self.profile = self.profile, None
        if profile is not None:
            profile.disable()
            profile.dump_stats(f"{self.prefix}-{self.phase}.prof")
        with open(f"{self.prefix}-{self.phase}.json", "w") as f:
            objects = gc.get_objects()
            kinds = collections.Counter(type(o).__qualname__ for o in objects).most_common(15)
            json.dump({"lag": self.lag, "gc": self.gc, "objects": len(objects), "kinds": kinds,
                       "stalls": self.stalls.most_common(20)}, f)
            del objects
        self.phase = None


def main(argv=None):
    import signal
    argv = sys.argv[1:] if argv is None else argv
    profile = argv[:1] == ["--profile"]
    if profile:
        argv = argv[1:]
    probe = Probe(argv[0], profile)
    signal.signal(signal.SIGUSR1, probe.start)
    signal.signal(signal.SIGUSR2, probe.stop)
    gc.callbacks.append(probe.collected)
    threading.Thread(target=probe.watch_stalls, name="agent-probe", daemon=True).start()
    from twisted.internet import reactor, task
    loop = task.LoopingCall(probe.look)
    reactor.callWhenRunning(loop.start, LAG_EVERY)
    from rcm_platform.rcmp_node import main as agent_main
    return agent_main(argv[1:])


if __name__ == "__main__":
    sys.exit(main())
