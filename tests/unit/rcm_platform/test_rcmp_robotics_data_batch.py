"""RoboticsData.write_batch on real SQLite files: a batch is one transaction (one commit, ``generation`` bumped
once, observers told once), its writes run in order, a failing write is rolled back alone (nothing of it is
left) and the others kept, a batch whose commit fails keeps nothing, and the data works as before afterwards."""

import sqlite3
import threading

import pytest

from rcm_platform.rcmp_command import NotFound
from rcm_platform.rcmp_robotics_data import RoboticsData
from tests.unit.rcm_platform.test_rcmp_robotics_data import LAUNCHER, NODE, path  # noqa: F401 (a fixture)


@pytest.fixture
def data(path):
    db = RoboticsData(path)
    for name in ("r1", "r2", "r3"):
        db.provision_platform_instance(name, "fiware_base")
    yield db
    db.close()


def connections(path):
    db = sqlite3.connect(path)
    try:
        return dict(db.execute("SELECT pi_name, paired FROM connection").fetchall())
    finally:
        db.close()


def test_a_batch_is_one_transaction_told_once(data, path):
    told = []
    data.observers.append(told.append)
    before = data.generation
    results = data.write_batch([(data.set_connected, ("r1", "198.51.100.6")),
                                (data.set_connected, ("r2", "198.51.100.7")),
                                (data.set_paired, ("r1", True)),
                                (data.set_service_space, ("r1", "http://198.51.100.1:11311/", 10100))])
    assert results == [(True, None), (True, None), (True, True), (True, None)]
    assert data.generation == before + 1
    assert told == [before + 1]
    assert connections(path) == {"r1": 1, "r2": 0}      # committed: another connection sees it
    assert data.service_space("r1")["inbound_port"] == 10100


def test_writes_run_in_the_order_given(data):
    data.write_batch([(data.set_connected, ("r1", "198.51.100.6")), (data.set_paired, ("r1", True)),
                      (data.set_disconnected, ("r1",)), (data.set_connected, ("r1", "198.51.100.9"))])
    assert data.platform_instance("r1") == {"pi_name": "r1", "service_logic": "fiware_base", "connected": True,
                                            "paired": False, "address": "198.51.100.9"}
    results = data.write_batch([(data.set_disconnected, ("r1",)), (data.set_paired, ("r1", True))])
    assert results[1] == (True, False)                  # paired after disconnected: nothing to pair


def test_a_failing_write_is_rolled_back_alone(data, path):
    def half_then_fail():
        def write():
            data._db.execute("INSERT INTO connection (pi_name, address, paired, since) VALUES ('r3', 'x', 1, 'now')")
            raise RuntimeError("broken after its first statement")
        return data._write(write)

    before = data.generation
    results = data.write_batch([(data.set_connected, ("r1", "198.51.100.6")),
                                (half_then_fail, ()),
                                (data.set_connected, ("ghost", "198.51.100.9")),
                                (data.set_connected, ("r2", "198.51.100.7"))])
    assert results[0] == (True, None) and results[3] == (True, None)
    assert not results[1][0] and isinstance(results[1][1], RuntimeError)
    assert not results[2][0] and isinstance(results[2][1], NotFound)
    assert connections(path) == {"r1": 0, "r2": 0}      # nothing of the failing write's first statement
    assert data.generation == before + 1


def test_a_batch_whose_commit_fails_keeps_nothing(data, path):
    blocker = sqlite3.connect(path, isolation_level=None)
    data._db.execute("PRAGMA busy_timeout = 0")         # the commit below gives up at once
    blocker.execute("BEGIN")
    blocker.execute("SELECT count(*) FROM connection").fetchone()   # a reader holding its lock: COMMIT is busy
    before = data.generation
    try:
        with pytest.raises(sqlite3.OperationalError):
            data.write_batch([(data.set_connected, ("r1", "198.51.100.6")), (data.set_connected, ("r2", "198.51.100.7"))])
    finally:
        blocker.execute("ROLLBACK")
        blocker.close()
    assert data.generation == before
    assert connections(path) == {}
    data._db.execute("PRAGMA busy_timeout = 30000")
    data.set_connected("r1", "198.51.100.6")                # the lock and the connection are fine afterwards
    assert connections(path) == {"r1": 0}


def test_other_threads_wait_for_a_batch_and_do_not_join_it(data):
    release = threading.Event()
    inside = threading.Event()

    def slow():
        inside.set()
        release.wait(5)

    batch = threading.Thread(target=data.write_batch, args=([(slow, ()), (data.set_connected, ("r1", "a"))],))
    batch.start()
    assert inside.wait(5)
    other = threading.Thread(target=data.set_connected, args=("r2", "b"))
    other.start()
    other.join(0.2)
    assert other.is_alive()                            # it waits for the batch's transaction
    generation = data.generation
    release.set()
    batch.join(5)
    other.join(5)
    assert data.generation == generation + 2           # the batch, then the other write: two commits
    assert data.platform_instance("r2")["connected"] is True


def test_provisioning_in_a_batch_is_atomic_per_write(data):
    bad = dict(LAUNCHER, sl_side="X")
    results = data.write_batch([(data.provision_service_logic, ("half", [NODE], [bad])),
                                (data.provision_service_logic, ("whole", [NODE], []))])
    assert not results[0][0] and isinstance(results[0][1], sqlite3.IntegrityError)
    assert data.service_logic("half") is None
    assert data.service_logic("whole")["sn_list"][0]["sn_name"] == "n1"
