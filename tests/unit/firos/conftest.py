"""Fixtures of FIROS's unit tests: FIROS's modules on the import path, and the stand-in broker served in-process
(real HTTP on loopback, no child process)."""

import logging

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


@pytest.fixture
def firos_log(caplog):
    """caplog with FIROS's own logger attached (core.setup_logging stops it propagating to the root logger)."""
    logger = logging.getLogger("firos")
    logger.addHandler(caplog.handler)
    old = logger.level, logger.propagate
    logger.setLevel(logging.DEBUG)
    logger.propagate = False          # each line once, whatever an earlier test did to the logger
    try:
        yield caplog
    finally:
        logger.removeHandler(caplog.handler)
        logger.setLevel(old[0])
        logger.propagate = old[1]
