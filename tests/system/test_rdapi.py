"""The RDAPI through real HTTP against a real master (``python3 -m rcm_platform --home TMP``) on loopback.

Every row of CONTRACTS §2 (service spaces only as "none running"), the seed guide's curl commands run with the real
``curl``, CORS, restarts, and concurrent duplicate provisioning.
"""

import json
import subprocess
import threading

import pytest

from tests.support.rcmp_agent import RcmpAgent

WELCOME = "<html><body>Welcome to the RCM platform node server!</body></html>"

NODE = {"sn_package": "robotics_test", "sn_type": "talker.py", "sn_name": "talker",
        "sn_params": "--rate 2 'hello world'", "sn_side": "R"}
LAUNCHER = {"sl_package": "robotics_test", "sl_file_launcher": "two_talkers.launch", "sl_name": "talkers",
            "sl_params": "", "sl_side": "S"}


@pytest.fixture
def master(procs, tmp_path):
    return RcmpAgent(procs, tmp_path / "master").start()


def curl(*args):
    """Run the real curl (argv, no shell) and return its stdout."""
    done = subprocess.run(["/usr/bin/curl", "-s", "-S", *args], capture_output=True, text=True, timeout=30)
    assert done.returncode == 0, done.stderr
    return done.stdout


def test_seed_curl_sequence(master):
    ip = master.base_url.split("//", 1)[1]  # what the guide calls public_ip_master
    assert curl(f"http://{ip}") == WELCOME
    assert json.loads(curl(f"http://{ip}/platform_instance/read")) == {"reason": [], "result": "OK"}
    # exactly the seed's text for an empty platform
    assert curl(f"http://{ip}/platform_instance/read") == '{"reason": [], "result": "OK"}'

    body = json.dumps({"slg_name": "name_s_l", "sn_list": [NODE], "sl_list": [LAUNCHER]})
    answer = json.loads(curl("-H", "Content-Type: application/json", "-d", body,
                             f"http://{ip}/service_logic/provisioning"))
    assert answer["result"] == "OK" and "name_s_l" in answer["reason"]
    answer = json.loads(curl("-H", "Content-Type: application/json", "-d", '{"slg_name":"name_s"}',
                             f"http://{ip}/service_logic/provisioning"))
    assert answer["result"] == "OK"

    answer = json.loads(curl("-H", "Content-Type: application/json", "-d",
                             '{"pi_name":"name_r","pi_service_logic":"name_s_l"}',
                             f"http://{ip}/platform_instance/provisioning"))
    assert answer["result"] == "OK" and "name_r" in answer["reason"]
    assert json.loads(curl(f"http://{ip}/platform_instance/read")) == {"result": "OK", "reason": [
        {"pi_name": "name_r", "service_logic": "name_s_l", "connected": False, "paired": False}]}

    names = json.loads(curl(f"http://{ip}/service_logic/read"))
    assert names["result"] == "OK"
    assert {"slg_name": "name_s_l"} in names["reason"] and {"slg_name": "name_s"} in names["reason"]
    assert {"slg_name": "fiware_base"} in names["reason"]
    detail = json.loads(curl(f"http://{ip}/service_logic/read?slg_name=name_s_l"))
    assert detail == {"result": "OK", "reason": {"ss_side": "S", "sn_list": [NODE], "sl_list": [LAUNCHER]}}

    answer = json.loads(curl("-H", "Content-Type: application/json", "-d", '{"pi_name":"name_r"}',
                             f"http://{ip}/platform_instance/r_provisioning"))
    assert answer["result"] == "OK"
    assert json.loads(curl(f"http://{ip}/platform_instance/read"))["reason"] == []
    answer = json.loads(curl("-H", "Content-Type: application/json", "-d", '{"slg_name":"name_s"}',
                             f"http://{ip}/service_logic/r_provisioning"))
    assert answer["result"] == "OK"
    names = json.loads(curl(f"http://{ip}/service_logic/read"))["reason"]
    assert {"slg_name": "name_s"} not in names and {"slg_name": "name_s_l"} in names


def test_every_call_and_its_answers(master):
    status, page, headers = master.request("GET", "/")
    assert (status, page) == (200, WELCOME) and headers["content-type"].startswith("text/html")

    assert master.get("/platform_instance/read") == (200, {"result": "OK", "reason": []})

    # defaults of a new platform
    status, names = master.get("/service_logic/read")
    assert status == 200 and names["result"] == "OK"
    assert [n["slg_name"] for n in names["reason"]][:2] == ["empty", "fiware_base"]
    status, base = master.get("/service_logic/read?slg_name=fiware_base")
    assert status == 200
    assert base["reason"] == {"ss_side": "S", "sl_list": [], "sn_list": [
        {"sn_package": "rcm", "sn_type": "rcm_driver.py", "sn_name": "rcm_driver", "sn_params": "",
         "sn_side": "S"},
        {"sn_package": "firos", "sn_type": "core.py", "sn_name": "firos", "sn_params": "", "sn_side": "S"}]}
    assert master.get("/service_logic/read?slg_name=empty")[1]["reason"] == {"ss_side": "S", "sn_list": [],
                                                                             "sl_list": []}

    # service logic: lists absent, empty, null; params absent means empty
    assert master.post("/service_logic/provisioning", {"slg_name": "only_name"})[0] == 200
    assert master.post("/service_logic/provisioning", {"slg_name": "nulls", "sn_list": None, "sl_list": []})[0] == 200
    node = dict(NODE)
    del node["sn_params"]
    status, answer = master.post("/service_logic/provisioning", {"slg_name": "sl1", "sn_list": [node, dict(
        NODE, sn_name="talker2")], "sl_list": [LAUNCHER], "ss_side": "S"})
    assert status == 200 and answer["result"] == "OK", answer
    detail = master.get("/service_logic/read?slg_name=sl1")[1]["reason"]
    assert detail["sn_list"] == [dict(NODE, sn_params=""), dict(NODE, sn_name="talker2")]
    assert detail["sl_list"] == [LAUNCHER]
    assert master.get("/service_logic/read?slg_name=only_name")[1]["reason"] == {"ss_side": "S", "sn_list": [],
                                                                                 "sl_list": []}
    # duplicate service logic
    status, answer = master.post("/service_logic/provisioning", {"slg_name": "sl1"})
    assert status == 409 and answer["result"] == "ERROR" and "sl1" in answer["reason"]

    # robots
    assert master.post("/platform_instance/provisioning", {"pi_name": "robot1", "pi_service_logic": "sl1"})[0] == 200
    assert master.post("/platform_instance/provisioning", {"pi_name": "robot2", "pi_service_logic": "sl1"})[0] == 200
    status, answer = master.post("/platform_instance/provisioning", {"pi_name": "robot1", "pi_service_logic": "sl1"})
    assert status == 409 and answer["result"] == "ERROR" and "robot1" in answer["reason"]
    status, answer = master.post("/platform_instance/provisioning", {"pi_name": "master", "pi_service_logic": "sl1"})
    assert status == 409 and "master" in answer["reason"]
    status, answer = master.post("/platform_instance/provisioning", {"pi_name": "robot3", "pi_service_logic": "nope"})
    assert status == 404 and answer["result"] == "ERROR" and "nope" in answer["reason"]
    assert master.get("/platform_instance/read")[1]["reason"] == [
        {"pi_name": "robot1", "service_logic": "sl1", "connected": False, "paired": False},
        {"pi_name": "robot2", "service_logic": "sl1", "connected": False, "paired": False}]

    # a service logic in use cannot go
    status, answer = master.post("/service_logic/r_provisioning", {"slg_name": "sl1"})
    assert status == 409 and "robot1" in answer["reason"]
    status, answer = master.post("/service_logic/r_provisioning", {"slg_name": "nope"})
    assert status == 404 and answer["result"] == "ERROR"

    # service spaces: none runs (no robot connected)
    status, answer = master.get("/service_space/read?ss_name=robot1")
    assert status == 404 and answer["result"] == "ERROR" and "robot1" in answer["reason"]
    status, answer = master.get("/service_space/read?ss_name=ghost")
    assert status == 404 and answer["result"] == "ERROR"

    # removal
    assert master.post("/platform_instance/r_provisioning", {"pi_name": "robot1"})[0] == 200
    status, answer = master.post("/platform_instance/r_provisioning", {"pi_name": "robot1"})
    assert status == 404 and answer["result"] == "ERROR" and "robot1" in answer["reason"]
    status, answer = master.post("/platform_instance/r_provisioning", {"pi_name": "master"})
    assert status == 404
    assert master.post("/platform_instance/r_provisioning", {"pi_name": "robot2"})[0] == 200
    assert master.post("/service_logic/r_provisioning", {"slg_name": "sl1"})[0] == 200
    assert master.get("/service_logic/read?slg_name=sl1")[0] == 404
    # defaults can be removed and the name reused
    assert master.post("/service_logic/r_provisioning", {"slg_name": "empty"})[0] == 200
    assert master.post("/service_logic/provisioning", {"slg_name": "empty"})[0] == 200


def test_cors_options_and_content_types(master):
    # without an Origin (curl, scripts) the answers carry the read-only CORS headers; writes from foreign pages
    # are tested in test_rdapi_security.py
    for path in ("/", "/platform_instance/read", "/service_logic/provisioning"):
        status, _, headers = master.request("OPTIONS", path)
        assert status == 204
        assert headers["allow"] == ("GET, OPTIONS" if path.endswith("read") or path == "/" else "POST, OPTIONS")
        assert headers["access-control-allow-origin"] == "*"
        assert set(headers["access-control-allow-methods"].replace(" ", "").split(",")) == {"GET", "HEAD",
                                                                                             "OPTIONS"}
    status, _, headers = master.request("GET", "/platform_instance/read")
    assert status == 200 and headers["access-control-allow-origin"] == "*"
    assert headers["content-type"] == "application/json"
    status, _, headers = master.request("POST", "/platform_instance/provisioning", b"{}",
                                        {"Content-Type": "application/json"})
    assert status == 400 and headers["access-control-allow-origin"] == "*"
    # application/json, with or without parameters, in any case; nothing else (415, as Orion answers)
    assert master.request("POST", "/service_logic/provisioning", b'{"slg_name": "a1"}',
                          {"Content-Type": "application/json; charset=utf-8"})[0] == 200
    assert master.request("POST", "/service_logic/provisioning", b'{"slg_name": "a2"}',
                          {"Content-Type": "Application/JSON"})[0] == 200
    for headers in ({}, {"Content-Type": "text/plain"}, {"Content-Type": "application/x-www-form-urlencoded"},
                    {"Content-Type": "application/jsonp"}):
        status, answer, _ = master.request("POST", "/service_logic/provisioning", b'{"slg_name": "a9"}', headers)
        assert status == 415 and answer["result"] == "ERROR" and "application/json" in answer["reason"], answer
    assert master.get("/service_logic/read?slg_name=a9")[0] == 404
    # a trailing newline, as curl -d @file sends, and UTF-8 unicode inside a param
    status, answer, _ = master.request("POST", "/service_logic/provisioning", json.dumps(
        {"slg_name": "a3", "sn_list": [dict(NODE, sn_params="msg:=\u00e9t\u00e9")]}).encode() + b"\n",
        {"Content-Type": "application/json"})
    assert status == 200, answer
    # HEAD behaves as GET without a body
    status, body, _ = master.request("HEAD", "/platform_instance/read")
    assert status == 200 and body == ""


def test_provisioning_survives_restart(master):
    assert master.post("/service_logic/provisioning", {"slg_name": "keep", "sn_list": [NODE]})[0] == 200
    assert master.post("/platform_instance/provisioning", {"pi_name": "r1", "pi_service_logic": "keep"})[0] == 200
    assert master.post("/service_logic/r_provisioning", {"slg_name": "empty"})[0] == 200
    assert master.stop() == 0
    master.start()
    assert master.get("/platform_instance/read")[1]["reason"] == [
        {"pi_name": "r1", "service_logic": "keep", "connected": False, "paired": False}]
    assert master.get("/service_logic/read?slg_name=keep")[1]["reason"]["sn_list"] == [NODE]
    names = [n["slg_name"] for n in master.get("/service_logic/read")[1]["reason"]]
    assert "empty" not in names, "a removed default service logic must stay removed"
    assert "fiware_base" in names and "keep" in names


@pytest.mark.parametrize("path,body", [
    ("/platform_instance/provisioning", {"pi_name": "twin", "pi_service_logic": "fiware_base"}),
    ("/service_logic/provisioning", {"slg_name": "twin", "sn_list": [NODE]}),
])
def test_concurrent_duplicate_provisioning(master, path, body):
    for round_ in range(5):
        this = dict(body, **{k: f"{v}{round_}" for k, v in body.items() if v == "twin"})
        barrier = threading.Barrier(4)
        results = []

        def one():
            barrier.wait()
            results.append(master.post(path, this))
        threads = [threading.Thread(target=one) for _ in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(30)
        statuses = sorted(s for s, _ in results)
        assert statuses == [200, 409, 409, 409], results
        assert all(a["result"] == ("OK" if s == 200 else "ERROR") for s, a in results)
