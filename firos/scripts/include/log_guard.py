"""What FIROS writes into its log on a peer's behalf: every string a peer controls capped, and every line a peer can
cause at will rate-limited, so that no flood of requests rolls FIROS's log (stderr, /rosout and the node's own
rotating log file) and the evidence in it away.

Owns two things, used by FIROS's listeners (the HTTP server, the broker's notifications, the ROS control topics):

- ``shown(value, limit)``: a peer's value as log text: a string or bytes as its ``repr`` cut to ``limit``
  characters (control characters escaped, so a peer cannot write a line of its own), with the full length when
  cut; any other value through ``reprlib``, which never renders more than it shows;
- ``Budget``: the lines a peer can trigger, at most ``burst`` per window of ``period`` seconds; a window whose budget
  ran out doubles the next one (up to ``longest``), so a flood that goes on writes fewer and fewer lines; the count
  of the lines left out is written with the first line of the next window (or by ``flush()``), and a quiet window
  brings the period back.

The RCM agent has the same rule, with the same numbers, in ``rcm_platform.rcmp_log_guard``, and rcm_driver its own
few lines of it. FIROS cannot import the agent's: it is a catkin package that runs where ``rcm_platform`` is not
installed (a server VM, a ROS machine with FIROS alone, the ``firos.zip`` distribution). Its budget also differs in
one way: FIROS's HTTP workers are threads, so a budget takes a lock (the agent's lives in one reactor thread).
Keep the two rules the same when one changes.
"""

import logging
import reprlib
import threading
import time

LOGGED_TEXT = 200        # characters of a peer's free text (paths, names, reasons) that go into the log
BURST = 10               # lines a budget writes per window
PERIOD = 10.0            # seconds of a window while nothing is left out
LONGEST = 3600.0         # seconds a window grows to while a flood goes on

_SHORT = reprlib.Repr()
_SHORT.maxlevel = 3
_SHORT.maxdict = _SHORT.maxlist = _SHORT.maxtuple = _SHORT.maxset = 8
_SHORT.maxstring = _SHORT.maxother = 60


def shown(value, limit=LOGGED_TEXT):
    """``value`` as text for the log, at most about ``limit`` characters (see the module's docstring)."""
    if not isinstance(value, (str, bytes)):
        text = _SHORT.repr(value)
        return text if len(text) <= limit else text[:limit] + "..."
    text = repr(value[:limit])
    return text if len(value) <= limit else f"{text}... ({len(value)} characters)"


class Budget:
    """At most ``burst`` lines per window into ``logger``, from any thread; ``what`` names them in the line that
    counts the rest ("lines about refused requests")."""

    def __init__(self, logger, what, burst=BURST, period=PERIOD, longest=LONGEST, clock=time.monotonic):
        self.logger, self.what, self.clock = logger, what, clock
        self.burst, self.period, self.longest = burst, period, longest
        self.left_out = 0            # in the current window
        self.left_out_total = 0
        self._opened = None          # when the current window began
        self._window = period
        self._used = 0
        self._lock = threading.Lock()

    def admit(self):
        """True when the window has room for one more line (counted as written), else counts it left out."""
        with self._lock:
            now = self.clock()
            if self._opened is None or now - self._opened >= self._window:
                self._turn(now)
            if self._used >= self.burst:
                self.left_out += 1
                self.left_out_total += 1
                return False
            self._used += 1
            return True

    def log(self, level, message, *args):
        """Log one line if the window has room; True when it was written."""
        admitted = self.admit()
        if admitted:
            self.logger.log(level, message, *args)
        return admitted

    def warning(self, message, *args):
        return self.log(logging.WARNING, message, *args)

    def info(self, message, *args):
        return self.log(logging.INFO, message, *args)

    def flush(self):
        """Write the count of the lines left out so far in this window (a listener that stops calls it)."""
        with self._lock:
            self._say_left_out()

    def _say_left_out(self):
        if self.left_out:
            self.logger.warning("%d more %s were left out of the log in the last %.0f s", self.left_out,
                                self.what, self._window)
            self.left_out = 0

    def _turn(self, now):
        """Open the next window: twice as long after a flooded one that a new line follows at once, else the
        period again."""
        flooded = self.left_out > 0
        self._say_left_out()
        at_once = self._opened is not None and now - self._opened < 2 * self._window
        self._window = min(self.longest, 2 * self._window) if flooded and at_once else self.period
        self._opened, self._used = now, 0
