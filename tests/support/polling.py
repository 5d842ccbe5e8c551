"""Waiting in tests: poll a condition until a deadline, never sleep as synchronisation."""

import time


class WaitTimeout(AssertionError):
    """The condition was still false at the deadline."""


def wait_until(condition, timeout=10.0, interval=0.02, message=None):
    """Call ``condition()`` until it returns a truthy value and return that value.

    Raises WaitTimeout (an AssertionError, so pytest shows it as a failure) naming ``message`` or the
    condition when ``timeout`` seconds pass. Exceptions raised by the condition count as "not yet" and the
    last one is reported at the deadline.
    """
    deadline = time.monotonic() + timeout
    last_error = None
    while True:
        try:
            value = condition()
        except Exception as exc:  # not ready yet: remember why
            value, last_error = None, exc
        if value:
            return value
        if time.monotonic() >= deadline:
            what = message or getattr(condition, "__name__", repr(condition))
            detail = f" (last error: {last_error!r})" if last_error else ""
            raise WaitTimeout(f"timed out after {timeout:.1f}s waiting for {what}{detail}")
        time.sleep(interval)  # the polling interval, not synchronisation
