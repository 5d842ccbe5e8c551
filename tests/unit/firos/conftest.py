"""Fixtures of FIROS's unit tests: FIROS's modules on the import path, and the stand-in broker served in-process
(real HTTP on loopback, no child process)."""

import pytest

from tests.support.firos import import_firos

import_firos()


@pytest.fixture
def broker():
    """The stand-in broker on a free loopback port, in this process; shut down after the test."""
    from tests.ngsi_broker.server import BrokerServer
    server = BrokerServer(port=0, quiet=True).start()
    try:
        yield server
    finally:
        server.shutdown()
