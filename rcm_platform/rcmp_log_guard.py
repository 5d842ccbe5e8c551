"""What the agent writes into its log on a peer's behalf: every string a peer controls capped, and every line a peer
can cause at will rate-limited, so that no flood rolls the log (and the evidence in it) away.

Owns two things, used by every listener of the agent (the RDAPI, the agent port, the console's streams and its
watcher port, the rcm_driver link) and by nothing else:

- ``shown(value, limit)``: a peer's value as log text: a string or bytes as its ``repr`` cut to ``limit``
  characters (control characters escaped, so a peer cannot forge a line), with the full length when cut; any
  other value through ``reprlib``, which never renders more than it shows (a 1 MB dict costs nothing);
- ``Budget``: the lines a peer can trigger, at most ``burst`` per window of ``period`` seconds. A window whose
  budget ran out doubles the next one (up to ``longest``), so a flood that goes on writes fewer and fewer lines;
  the count of the lines left out is written with the first line of the next window (or by ``flush()``), and a
  quiet window brings the period back. ``BudgetFilter`` puts a logger (Twisted's, whose lines about idle or
  broken connections any client can cause) under one.

rcm_driver (package ``rcm``) cannot import this package on every machine and carries its own few lines of the
same rule.
"""

import logging
import reprlib
import time

LOGGED_TEXT = 200        # characters of a peer's free text (paths, reasons, reports) that go into the log
BURST = 10               # lines a budget writes per window
PERIOD = 10.0            # seconds of a window while nothing is left out
LONGEST = 3600.0         # seconds a window grows to while a flood goes on

_REPR = reprlib.Repr()
_REPR.maxlevel = 3
_REPR.maxdict = _REPR.maxlist = _REPR.maxtuple = _REPR.maxset = 8
_REPR.maxstring = _REPR.maxother = 60


def shown(value, limit=LOGGED_TEXT):
    """``value`` as text for the log, at most about ``limit`` characters (see the module's docstring)."""
    if isinstance(value, bytes):
        total = len(value)
        text = repr(value[:limit])
    elif isinstance(value, str):
        total = len(value)
        text = repr(value[:limit])
    else:
        total = None
        text = _REPR.repr(value)
        if len(text) > limit:
            text = text[:limit] + "..."
    if total is not None and total > limit:
        text += f"... ({total} characters)"
    return text


class Budget:
    """At most ``burst`` lines per window into ``logger``; ``what`` names them in the line that counts the rest
    ("warnings about connections not admitted"), written at ``count_level`` (a warning unless the lines left out
    are ordinary news, such as a fleet's hellos). ``clock`` gives seconds (``reactor.seconds`` in the agent)."""

    def __init__(self, logger, what, clock=time.monotonic, burst=BURST, period=PERIOD, longest=LONGEST,
                 count_level=logging.WARNING):
        self.logger = logger
        self.count_level = count_level   # the level of the line counting what was left out
        self.what = what
        self.clock = clock
        self.burst = burst
        self.period = period
        self.longest = longest
        self.left_out = 0            # in the current window
        self.left_out_total = 0
        self._start = None
        self._length = period
        self._written = 0

    def admit(self):
        """True when the window has room for one more line (counted as written), else counts it left out."""
        now = self.clock()
        if self._start is None or now >= self._start + self._length:
            self._next_window(now)
        if self._written < self.burst:
            self._written += 1
            return True
        self.left_out += 1
        self.left_out_total += 1
        return False

    def log(self, level, message, *args):
        """Log one line if the window has room; True when it was written."""
        if self.admit():
            self.logger.log(level, message, *args)
            return True
        return False

    def warning(self, message, *args):
        return self.log(logging.WARNING, message, *args)

    def info(self, message, *args):
        return self.log(logging.INFO, message, *args)

    def flush(self):
        """Write the count of the lines left out so far in this window (a listener that stops calls it)."""
        if self.left_out:
            self._count_left_out()

    def _count_left_out(self):
        self.logger.log(self.count_level, "%d more %s were left out of the log in the last %.0f s", self.left_out,
                        self.what, self._length)
        self.left_out = 0

    def _next_window(self, now):
        flooded = self.left_out > 0
        if flooded:
            self._count_left_out()
        quiet = self._start is None or now >= self._start + 2 * self._length
        self._length = min(self.longest, self._length * 2) if flooded and not quiet else self.period
        self._start = now
        self._written = 0


class BudgetFilter(logging.Filter):
    """A logging filter putting a logger's lines below ``logging.ERROR`` under a ``Budget`` (errors always pass)."""

    def __init__(self, budget):
        super().__init__()
        self.budget = budget
        self._inside = False

    def filter(self, record):
        if record.levelno >= logging.ERROR or self._inside:
            return True
        self._inside = True          # the budget's count of left-out lines goes through this logger too
        try:
            return self.budget.admit()
        finally:
            self._inside = False
