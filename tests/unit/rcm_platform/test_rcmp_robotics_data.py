"""RoboticsData on real SQLite files: schema and version, defaults, provisioning rules, live state, atomic writes,
several threads at once."""

import sqlite3
import threading

import pytest

from rcm_platform.rcmp_command import Conflict, NotFound
from rcm_platform.rcmp_robotics_data import SCHEMA_VERSION, DataError, RoboticsData

NODE = {"sn_package": "pkg", "sn_type": "n.py", "sn_name": "n1", "sn_params": "-a 'b c'", "sn_side": "R"}
LAUNCHER = {"sl_package": "pkg", "sl_file_launcher": "x.launch", "sl_name": "l1", "sl_params": "", "sl_side": "S"}


@pytest.fixture
def path(tmp_path):
    return str(tmp_path / "robotics_data.db")


@pytest.fixture
def data(path):
    db = RoboticsData(path)
    yield db
    db.close()


def test_new_file_has_schema_version_and_defaults(data, path):
    assert data.service_logic_names() == ["empty", "fiware_base"]
    assert data.service_logic("empty") == {"ss_side": "S", "sn_list": [], "sl_list": []}
    base = data.service_logic("fiware_base")
    assert [(n["sn_package"], n["sn_type"], n["sn_name"], n["sn_side"]) for n in base["sn_list"]] == [
        ("rcm", "rcm_driver.py", "rcm_driver", "S"), ("firos", "core.py", "firos", "S")]
    assert data.platform_instances() == []
    db = sqlite3.connect(path)
    assert db.execute("SELECT version FROM schema_version").fetchall() == [(SCHEMA_VERSION,)]
    db.close()


def test_master_row_is_stored_but_not_listed(data, path):
    data.set_master("master", "198.51.100.1", [10100, 10101])
    assert data.master() == {"pi_name": "master", "address": "198.51.100.1", "inbound_open_ports": [10100, 10101]}
    assert data.platform_instances() == [] and data.platform_instance("master") is None
    data.set_master("hub", "198.51.100.1", [])   # renamed master replaces the old row
    assert data.master()["pi_name"] == "hub"
    db = sqlite3.connect(path)
    assert db.execute("SELECT pi_name FROM platform_instance WHERE is_master = 1").fetchall() == [("hub",)]
    db.close()
    with pytest.raises(Conflict):
        data.provision_platform_instance("hub", "empty")
    data.provision_platform_instance("r1", "empty")
    with pytest.raises(Conflict):
        data.set_master("r1", "198.51.100.1", [])


def test_provisioning_rules(data):
    data.provision_service_logic("sl1", [NODE], [LAUNCHER])
    assert data.service_logic("sl1") == {"ss_side": "S", "sn_list": [NODE], "sl_list": [LAUNCHER]}
    with pytest.raises(Conflict):
        data.provision_service_logic("sl1", [], [])
    with pytest.raises(NotFound):
        data.provision_platform_instance("r1", "nope")
    data.provision_platform_instance("r1", "sl1")
    data.provision_platform_instance("r2", "sl1")
    with pytest.raises(Conflict):
        data.provision_platform_instance("r1", "empty")
    assert [r["pi_name"] for r in data.platform_instances()] == ["r1", "r2"]
    with pytest.raises(Conflict, match="r1"):
        data.remove_service_logic("sl1")
    data.remove_platform_instance("r1")
    data.remove_platform_instance("r2")
    with pytest.raises(NotFound):
        data.remove_platform_instance("r2")
    data.remove_service_logic("sl1")
    assert data.service_logic("sl1") is None
    with pytest.raises(NotFound):
        data.remove_service_logic("sl1")


def test_live_state_and_forgetting_it_on_start(path):
    data = RoboticsData(path)
    data.provision_platform_instance("r1", "fiware_base")
    data.provision_platform_instance("r2", "fiware_base")
    assert data.set_paired("r1", True) is False  # not connected: nothing to pair
    data.set_connected("r1", "198.51.100.6")
    assert data.platform_instance("r1") == {"pi_name": "r1", "service_logic": "fiware_base", "connected": True,
                                            "paired": False, "address": "198.51.100.6"}
    assert data.set_paired("r1", True) is True
    data.set_service_space("r1", "http://198.51.100.1:11311/", 10100)
    assert data.service_space("r1") == {"ss_name": "r1", "ros_master_uri": "http://198.51.100.1:11311/",
                                        "inbound_port": 10100}
    assert data.platform_instances()[0] == {"pi_name": "r1", "service_logic": "fiware_base", "connected": True,
                                            "paired": True}
    with pytest.raises(NotFound):
        data.set_connected("ghost", "198.51.100.9")
    data.set_connected("r2", "198.51.100.7")
    data.set_disconnected("r2")
    data.set_disconnected("r2")  # twice is fine
    assert data.platform_instance("r2")["connected"] is False
    assert data.platform_instance("r2")["address"] == "198.51.100.7"  # last known address kept
    data.close()

    again = RoboticsData(path)   # a new life of the master
    assert [(r["pi_name"], r["connected"], r["paired"]) for r in again.platform_instances()] == [
        ("r1", False, False), ("r2", False, False)]
    assert again.service_space("r1") is None
    # removing a robot removes its live state too
    again.set_connected("r1", "198.51.100.6")
    again.set_service_space("r1", "http://x:1/", None)
    again.remove_platform_instance("r1")
    assert again.service_space("r1") is None
    again.close()


def test_a_failing_write_leaves_nothing_behind(data, path):
    before = data.generation
    bad = dict(LAUNCHER, sl_side="X")  # violates the CHECK constraint after the nodes are inserted
    with pytest.raises(sqlite3.IntegrityError):
        data.provision_service_logic("half", [NODE, dict(NODE, sn_name="n2")], [bad])
    assert data.service_logic("half") is None
    assert data.generation == before
    db = sqlite3.connect(path)
    assert db.execute("SELECT count(*) FROM service_node WHERE slg_name = 'half'").fetchone() == (0,)
    db.close()
    data.provision_service_logic("half", [NODE], [])  # the lock and the connection are fine afterwards
    assert data.generation == before + 1


def test_defaults_are_written_once_only(path):
    data = RoboticsData(path)
    data.remove_service_logic("fiware_base")
    data.close()
    data = RoboticsData(path)
    assert data.service_logic_names() == ["empty"]
    data.close()


def test_files_that_are_not_robotics_data(tmp_path):
    junk = tmp_path / "junk.db"
    junk.write_bytes(b"this is not sqlite at all" * 100)
    with pytest.raises(DataError, match="junk.db"):
        RoboticsData(str(junk))
    other = tmp_path / "other.db"
    db = sqlite3.connect(str(other))
    db.execute("CREATE TABLE t (x)")
    db.commit()
    db.close()
    with pytest.raises(DataError, match="no schema_version"):
        RoboticsData(str(other))
    newer = tmp_path / "newer.db"
    RoboticsData(str(newer)).close()
    db = sqlite3.connect(str(newer))
    db.execute("UPDATE schema_version SET version = 99")
    db.commit()
    db.close()
    with pytest.raises(DataError, match="99"):
        RoboticsData(str(newer))


def test_many_threads_read_and_write(data):
    errors = []

    def worker(k):
        try:
            for i in range(40):
                name = f"t{k}_{i}"
                data.provision_service_logic(name, [dict(NODE, sn_name="a"), dict(NODE, sn_name="b")], [])
                data.provision_platform_instance(f"r{k}_{i}", name)
                assert data.service_logic(name)["sn_list"][1]["sn_name"] == "b"
                assert any(r["pi_name"] == f"r{k}_{i}" for r in data.platform_instances())
                try:
                    data.provision_platform_instance(f"r{k}_{i}", name)
                except Conflict:
                    pass
                else:
                    raise AssertionError("duplicate accepted")
        except Exception as exc:  # reported below, with the thread that failed
            errors.append((k, exc))
    threads = [threading.Thread(target=worker, args=(k,)) for k in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert not errors
    assert len(data.platform_instances()) == 320
    assert data.integrity_check() == "ok"
