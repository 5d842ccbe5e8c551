"""A stand-in for the FIWARE Orion context broker, for tests only (never shipped in any zip).

Orion needs MongoDB, which no registry here offers, so FIROS is tested against this package instead. It answers
the NGSI v2 calls FIROS makes (entities, attributes, ``op/update``, subscriptions with notifications) and the NGSI
v1 calls of Orion before 3.10 (``updateContext``, ``queryContext``, ``subscribeContext``, ``unsubscribeContext``,
``updateContextSubscription`` and their ``/NGSI10/`` twins), over one shared store, with Orion's answers and
error shapes, and NGSI-LD under ``/ngsi-ld/v1/`` as Orion-LD answers it (entities, attributes, batch upsert,
subscriptions, notifications, ``@context`` rules, ProblemDetails errors). ``docs/STANDIN_BROKER.md`` lists
which Orion and Orion-LD behaviours it copies, with links to their manuals.

Run it standalone with ``/usr/bin/python3 -m tests.ngsi_broker --port 1026``; in tests use
``tests.ngsi_broker.testing.start_broker`` (a real child process on a free port).

Modules: ``model`` (tenants, entities, attributes, validation, errors, time formats), ``subscriptions``
(subscriptions, matching, throttling, expiry, notification bodies, the notifier threads), ``ngsiv2`` and
``ngsiv1`` (the two APIs), ``ngsild`` (NGSI-LD: its own handlers, contexts, subscriptions and notification
bodies), ``server`` (HTTP: routing, tenants from headers, body limit, error rendering),
``testing`` (helpers for tests: the broker as a child process, a notification receiver).
"""

from .server import BrokerServer  # noqa: F401
