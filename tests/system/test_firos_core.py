"""FIROS's `core.py` as a real child (`rosrun firos core.py --config DIR`): a wrong configuration stops it with
one clear line and exit 1, before anything starts."""

import json
import subprocess

import pytest

from tests.support.firos import write_config
from tests.support.processes import ros_env

pytestmark = pytest.mark.slow   # FIROS as a child (rosrun)


def _config(tmp_path, block, env="test"):
    (tmp_path / "config.json").write_text(json.dumps({"environment": env, env: block}))
    return str(tmp_path)


def _run_core(config_dir, *extra):
    env = ros_env({"ROS_LOG_DIR": str(config_dir) + "/roslog", "ROS_MASTER_URI": "http://127.0.0.1:9/"})
    return subprocess.run(["/usr/bin/rosrun", "firos", "core.py", "--config", str(config_dir), *extra],
                          env=env, capture_output=True, text=True, timeout=60)


@pytest.mark.parametrize("breakage,expected", [
    ("config", "config.json: test.contextbroker.address is missing or empty"),
    ("json", "whitelist.json: not valid JSON"),
    ("regex", "whitelist.json: robot regex 'turtle(' is not a valid regular expression"),
])
def test_core_stops_with_one_clear_line(tmp_path, breakage, expected):
    write_config(str(tmp_path), 1026)
    if breakage == "config":
        _config(tmp_path, {"contextbroker": {"port": 1026}})
    elif breakage == "json":
        (tmp_path / "whitelist.json").write_text('{"turtle1": ')
    else:
        (tmp_path / "whitelist.json").write_text('{"turtle(": {"publisher": []}}')
    result = _run_core(tmp_path)
    assert result.returncode == 1, result
    lines = [l for l in result.stderr.splitlines() if l.strip()]
    assert len(lines) == 1 and expected in lines[0] and "Traceback" not in result.stderr, result.stderr
