"""The robotics data as the seed shows it: ``sqlite3 robotics_data.db`` (the sqlite3 program) reads readable tables."""

import os
import subprocess

from rcm_platform.rcmp_robotics_data import RoboticsData
from tests.unit.rcm_platform.test_rcmp_robotics_data import LAUNCHER, NODE


def test_sqlite3_cli_shows_readable_tables(tmp_path):
    path = str(tmp_path / "robotics_data.db")
    data = RoboticsData(path)
    try:
        _check_tables(data, path)
    finally:
        data.close()


def _check_tables(data, path):
    data.set_master("master", "198.51.100.1", [10100])
    data.provision_service_logic("demo", [NODE], [LAUNCHER])
    data.provision_platform_instance("robot1", "demo")
    tables = subprocess.run(["/usr/bin/sqlite3", "-readonly", path, ".tables"], capture_output=True, text=True,
                            timeout=30, check=True).stdout.split()
    assert set(tables) == {"schema_version", "service_logic", "service_node", "service_launcher",
                           "platform_instance", "connection", "service_space", "rdapi_token"}
    rows = subprocess.run(["/usr/bin/sqlite3", "-readonly", "-header", path,
                           "SELECT pi_name, slg_name, is_master, address, inbound_open_ports FROM platform_instance"],
                          capture_output=True, text=True, timeout=30, check=True).stdout.splitlines()
    assert rows == ["pi_name|slg_name|is_master|address|inbound_open_ports", "master||1|198.51.100.1|10100",
                    "robot1|demo|0||"]
    nodes = subprocess.run(["/usr/bin/sqlite3", "-readonly", path, "SELECT * FROM service_node WHERE slg_name='demo'"],
                           capture_output=True, text=True, timeout=30, check=True).stdout
    assert nodes == "demo|0|pkg|n.py|n1|-a 'b c'|R\n"
    assert os.path.getsize(path) > 0
