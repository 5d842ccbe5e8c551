"""Fixtures shared by the whole suite: owned child processes and a real ROS master on a free port."""


import pytest

from tests.support.processes import ProcessGroup
from tests.support.rosmaster import RosMaster


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
