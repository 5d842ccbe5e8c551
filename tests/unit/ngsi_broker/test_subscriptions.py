"""The stand-in broker's notifier: failures reported quickly, notifications kept in order."""

import threading

from tests.ngsi_broker.subscriptions import Notifier
from tests.ngsi_broker.testing import NotificationReceiver
from tests.support.polling import wait_until
from tests.support.ports import free_port


def test_notifier_reports_failures_quickly_and_keeps_order():
    notifier = Notifier(timeout=1.0)
    results = []
    done = threading.Event()
    try:
        notifier.post(f"http://127.0.0.1:{free_port()}/x", b"{}", {}, lambda ok, code, reason: (
            results.append(("dead", ok, code, reason)), done.set()))
        assert done.wait(5)
        assert results[0][1:3] == (False, None) and "connect" in results[0][3].lower()
        with NotificationReceiver() as receiver:
            for i in range(20):
                notifier.post(receiver.url, str(i).encode(), {"Content-Type": "application/json"},
                              lambda ok, code, reason: results.append((ok, code)))
            notes = receiver.wait_for(20)
            assert [n.json for n in notes] == list(range(20))
            wait_until(lambda: len(results) == 21, message="all results")
            assert results[1:] == [(True, 200)] * 20
    finally:
        notifier.close()
