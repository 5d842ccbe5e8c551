"""The compatibility matrix (tox.ini, run by scripts/compat/matrix.sh): each supported system's Python with that
system's Twisted, cryptography and netifaces runs ``python -m rcm_platform --help`` and the unit tests.

The first run makes the environments (a few minutes: Twisted 18.9 and netifaces build from source); they are kept
in build/compat/tox and made again only when their pins change, so later runs take seconds. The README's table of
supported systems must say what tox.ini pins.
"""

import configparser
import json
import os
import re
import subprocess

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
TOX_INI = os.path.join(ROOT, "tox.ini")
README = os.path.join(ROOT, "README.md")
TABLE_HEADER = "| system | Python | Twisted | cryptography | netifaces | ROS 1 |"


def systems():
    """[(env name, {"system", "ros", "python", pins...})] in tox.ini's env_list order."""
    ini = configparser.ConfigParser(interpolation=None)
    ini.read(TOX_INI)
    found = []
    for env in [e.strip() for e in ini["tox"]["env_list"].split(",")]:
        section = ini[f"testenv:{env}"]
        system, _, ros = section["description"].partition(": ")
        pins = dict(line.strip().split("==", 1) for line in section["deps"].splitlines() if "==" in line)
        python = re.fullmatch(r"python(3\.\d+)", section["base_python"]).group(1)
        found.append((env, {"system": system, "ros": ros, "python": python, **pins}))
    return found


def readme_rows():
    """The table rows tox.ini's systems give, as README.md must show them."""
    return [f"| {s['system']} | {s['python']} | {s['Twisted']} | {s['cryptography']} | {s['netifaces']} | "
            f"{s['ros']} |" for _, s in systems()]


def test_tox_ini_names_every_system_of_the_contract():
    names = [s["system"] for _, s in systems()]
    assert [n.split(" (")[0] for n in names] == ["Ubuntu 20.04", "Ubuntu 22.04", "Ubuntu 24.04", "Debian 12",
                                                 "Debian 13"]
    noetic = dict(systems())["ubuntu2004"]
    assert (noetic["python"], noetic["Twisted"], noetic["cryptography"]) == ("3.8", "18.9.0", "2.8")
    assert noetic["netifaces"].startswith("0.10.")


def test_readme_table_of_supported_systems_matches_tox_ini():
    with open(README) as f:
        text = f.read()
    assert TABLE_HEADER in text, "README.md has no table of supported systems"
    rows = readme_rows()
    shown = text.split(TABLE_HEADER, 1)[1].splitlines()[2:2 + len(rows)]  # after the header's separator line
    assert shown == rows, "README.md's supported systems differ from tox.ini; its rows should be:\n" + "\n".join(rows)


@pytest.mark.slow
@pytest.mark.timeout(1500)
def test_every_supported_system_runs_the_agents_help_and_the_unit_tests(tmp_path):
    result_file = tmp_path / "result.json"
    run = subprocess.run(["bash", os.path.join(ROOT, "scripts", "compat", "matrix.sh"),
                          "--result-json", str(result_file)], cwd=ROOT, stdout=subprocess.PIPE,
                         stderr=subprocess.STDOUT, universal_newlines=True, stdin=subprocess.DEVNULL, timeout=1450)
    assert run.returncode == 0, run.stdout[-8000:]
    results = json.loads(result_file.read_text())["testenvs"]
    for env, want in systems():
        got = results[env]
        assert got["result"]["success"], (env, got["result"])
        assert ".".join(map(str, got["python"]["version_info"][:2])) == want["python"], env
        installed = dict(p.split("==", 1) for p in got["installed_packages"] if "==" in p)
        for name in ("Twisted", "cryptography", "netifaces", "PyYAML"):
            assert installed.get(name) == want[name], (env, name, installed.get(name))
        outputs = {" ".join(c["command"][1:]): c for c in got["test"]}
        help_run = next(c for cmd, c in outputs.items() if cmd.endswith("-m rcm_platform --help"))
        assert help_run["retcode"] == 0 and "--home DIR" in help_run["output"], (env, help_run["output"][-2000:])
        tests_run = next(c for cmd, c in outputs.items() if " -m pytest " in f" {cmd} ")
        summary = tests_run["output"].strip().splitlines()[-1]
        assert tests_run["retcode"] == 0 and re.search(r"\b\d+ passed\b", summary), (env, tests_run["output"][-4000:])
        assert "failed" not in summary and "error" not in summary, (env, summary)
