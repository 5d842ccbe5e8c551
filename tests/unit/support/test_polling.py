"""The test support's polling helpers: ``wait_until`` and ``until_deferred`` say what they waited for."""

import pytest
from twisted.trial import unittest as twisted_unittest

from tests.support.polling import WaitTimeout, until_deferred, wait_until


def test_wait_until_reports_what_it_waited_for():
    with pytest.raises(WaitTimeout, match="the impossible"):
        wait_until(lambda: False, timeout=0.1, message="the impossible")


class UntilDeferredTests(twisted_unittest.TestCase):
    """The reactor-side wait fires when the condition holds and fails, naming it, when it never does."""

    def test_fires_once_the_condition_holds(self):
        ticks = []
        return until_deferred(lambda: ticks.append(1) or len(ticks) >= 3, timeout=5)

    def test_fails_naming_what_it_waited_for(self):
        d = until_deferred(lambda: False, timeout=0.05, message="the impossible")
        d = self.assertFailure(d, WaitTimeout)
        d.addCallback(lambda exc: self.assertIn("the impossible", str(exc)))
        return d
