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


def until_deferred(condition, timeout=5.0, interval=0.01, message=None, reactor=None):
    """For Twisted tests: a Deferred firing with True once ``condition()`` is true, polled on the reactor
    every ``interval`` seconds, and failing with WaitTimeout (naming ``message``) after ``timeout`` seconds."""
    from twisted.internet import defer, task
    if reactor is None:
        from twisted.internet import reactor
    d = defer.Deferred()
    deadline = reactor.seconds() + timeout

    def poll():
        if condition():
            loop.stop()
            d.callback(True)
        elif reactor.seconds() > deadline:
            loop.stop()
            what = message or getattr(condition, "__name__", repr(condition))
            d.errback(WaitTimeout(f"timed out after {timeout:.1f}s waiting for {what}"))

    loop = task.LoopingCall(poll)
    loop.clock = reactor
    loop.start(interval)
    return d
