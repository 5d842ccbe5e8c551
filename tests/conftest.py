"""Fixtures shared by the whole suite: owned child processes, a real ROS master on a free port, test hosts, RCM
agents as clients of rcm_driver; and the ``slow`` marker on every test of ``tests/system/`` (multi-process tests),
so that ``-m 'not slow'`` (``./run test-fast``) runs the unit tests."""

import os

import pytest

from tests.support.driver_client import AgentClient
from tests.support.processes import ProcessGroup
from tests.support.rosmaster import RosMaster


SYSTEM = os.path.join(os.path.dirname(os.path.abspath(__file__)), "system") + os.sep


def pytest_collection_modifyitems(items):
    """Every test under tests/system/ starts child processes: it is ``slow``, set here once for the folder."""
    for item in items:
        if str(item.fspath).startswith(SYSTEM):
            item.add_marker(pytest.mark.slow)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """Keep each phase's report on the test item (``item.rep_call``), so a fixture can tell the test failed."""
    outcome = yield
    report = outcome.get_result()
    setattr(item, f"rep_{report.when}", report)


@pytest.fixture
def procs(tmp_path):
    """Child processes of this test; all are stopped and checked gone when the test ends, even on failure."""
    log_dir = tmp_path / "proc-logs"
    log_dir.mkdir()
    group = ProcessGroup(log_dir=str(log_dir))
    try:
        yield group
    finally:
        group.stop_all()


@pytest.fixture
def ros_master(procs):
    """A running ROS master (``rosmaster --core``) on a free loopback port; stopped after the test."""
    return RosMaster(procs).start()


@pytest.fixture
def roscore(procs):
    """A ROS master plus ``rosout``, like ``roscore`` gives."""
    return RosMaster(procs, with_rosout=True).start()


@pytest.fixture
def lan(tmp_path):
    """A LAN of test hosts (``tests/support/hosts.py``): ``lan.add_host(name)``; every namespace, process and
    overlay is removed when the test ends, even on failure. Root only (the test is skipped otherwise)."""
    if os.geteuid() != 0:
        pytest.skip("test hosts need root (network namespaces)")
    from tests.support.hosts import Lan
    log_dir = tmp_path / "host-logs"
    log_dir.mkdir()
    with Lan(log_dir=str(log_dir)) as network:
        yield network


@pytest.fixture
def agents():
    """``agents(port)`` connects one more RCM agent (an ``AgentClient``) to an rcm_driver's port; all are closed
    when the test ends."""
    clients = []

    def connect(port):
        client = AgentClient(port)
        clients.append(client)
        return client

    yield connect
    for client in clients:
        client.close()
