"""A master killed with SIGKILL in the middle of a burst of provisioning writes restarts with a consistent database.

Writers keep provisioning service logics (each with several items) and robots while the master is killed; after
the restart SQLite's integrity check passes, no service logic is half there (every stored one has exactly the
items it was sent with), every robot points at an existing service logic, and every write the master answered
OK before dying is still there.
"""

import json
import sqlite3
import threading
import http.client

from tests.support.polling import wait_until
from tests.support.rcmp_agent import RcmpAgent

ITEMS = 6


JSON = {"Content-Type": "application/json"}


def service_logic(i):
    nodes = [{"sn_package": "pkg", "sn_type": "node.py", "sn_name": f"n{j}", "sn_params": f"--index {j}",
              "sn_side": "S" if j % 2 else "R"} for j in range(ITEMS)]
    launchers = [{"sl_package": "pkg", "sl_file_launcher": "a.launch", "sl_name": f"l{j}", "sl_params": "",
                  "sl_side": "S"} for j in range(ITEMS)]
    return {"slg_name": f"burst_{i}", "sn_list": nodes, "sl_list": launchers}


def writer(agent, start, step, acknowledged, stop):
    i = start
    while not stop.is_set():
        try:
            conn = http.client.HTTPConnection(agent.host, agent.ext_port, timeout=5)
            conn.request("POST", "/service_logic/provisioning", json.dumps(service_logic(i)), JSON)
            if conn.getresponse().status == 200:
                acknowledged.append(("sl", i))
            conn.request("POST", "/platform_instance/provisioning",
                         json.dumps({"pi_name": f"robot_{i}", "pi_service_logic": f"burst_{i}"}), JSON)
            if conn.getresponse().status == 200:
                acknowledged.append(("pi", i))
            conn.close()
        except (OSError, http.client.HTTPException):
            if stop.is_set():
                return
        i += step


def test_sigkill_during_write_burst_leaves_consistent_db(procs, tmp_path):
    master = RcmpAgent(procs, tmp_path / "master").start()
    acknowledged, stop = [], threading.Event()
    threads = [threading.Thread(target=writer, args=(master, k, 4, acknowledged, stop)) for k in range(4)]
    for t in threads:
        t.start()
    try:
        wait_until(lambda: len(acknowledged) >= 60, timeout=30, message="a burst of acknowledged writes")
        master.kill()
    finally:
        stop.set()
        for t in threads:
            t.join(10)
    done = list(acknowledged)

    db = sqlite3.connect(master.db_path)
    try:
        assert db.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    finally:
        db.close()

    master.start()
    logics = {n["slg_name"] for n in master.get("/service_logic/read")[1]["reason"]}
    robots = master.get("/platform_instance/read")[1]["reason"]
    for kind, i in done:
        if kind == "sl":
            assert f"burst_{i}" in logics, f"acknowledged service logic burst_{i} lost"
        else:
            assert any(r["pi_name"] == f"robot_{i}" for r in robots), f"acknowledged robot_{i} lost"
    for name in logics:
        if name.startswith("burst_"):
            detail = master.get(f"/service_logic/read?slg_name={name}")[1]["reason"]
            expected = service_logic(int(name.split("_")[1]))
            assert detail["sn_list"] == expected["sn_list"] and detail["sl_list"] == expected["sl_list"], name
    for robot in robots:
        assert robot["service_logic"] in logics
        assert robot["connected"] is False and robot["paired"] is False

    db = sqlite3.connect(master.db_path)
    try:
        assert db.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        assert db.execute("PRAGMA foreign_key_check").fetchall() == []
        orphans = db.execute("SELECT count(*) FROM service_node WHERE slg_name NOT IN "
                             "(SELECT slg_name FROM service_logic)").fetchone()[0]
        assert orphans == 0
    finally:
        db.close()
