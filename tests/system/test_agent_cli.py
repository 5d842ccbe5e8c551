"""The agent as a program (``python3 -m rcm_platform``, ``rcmp_n``): its command line, one-line errors and exit
statuses, signals, log rotation, each role starting and stopping."""

import os
import signal
import subprocess

import pytest

from tests.support.polling import wait_until
from tests.support.ports import free_port
from tests.support.rcmp_agent import PYTHON, REPO, RcmpAgent
from tests.unit.rcm_platform.test_rcmp_config import write


def run_agent(home, *extra, timeout=30):
    env = dict(os.environ, PYTHONPATH=REPO, PATH="/usr/bin:/bin:" + os.environ.get("PATH", ""))
    return subprocess.run([PYTHON, "-m", "rcm_platform", "--home", str(home), *extra], capture_output=True,
                          text=True, timeout=timeout, env=env, cwd=REPO)


@pytest.mark.parametrize("name,text,line", [
    (".init.cfg", "[main]\next_port=abc\n", "rcmp_n: {home}/.init.cfg: key 'ext_port': not a port number: 'abc'"),
    ("init.cfg", "[main]\nname=r1\nrobot=maybe\n", "rcmp_n: {home}/init.cfg: key 'robot': expected yes or no: 'maybe'"),
    (".init.cfg", "[main]\nvpn_interface=nosuch0\next_address=127.0.0.1\n",
     "rcmp_n: {home}/.init.cfg: no IPv4 address on the VPN interface 'nosuch0' (is the VPN up? or set vpn_address)"),
    (".init.cfg", "[main]\nvpn_address=127.0.0.1\next_interface=nosuch1\n",
     "rcmp_n: {home}/.init.cfg: no IPv4 address on the external interface 'nosuch1' "
     "(set ext_interface or ext_address)"),
])
def test_agent_exits_2_with_one_line(tmp_path, name, text, line):
    write(tmp_path, name, text)
    done = run_agent(tmp_path)
    assert done.returncode == 2, done.stderr
    assert done.stderr == line.format(home=tmp_path) + "\n"
    assert done.stdout == ""
    assert not os.path.exists(tmp_path / "robotics_data.db")


def test_master_without_vpn_address_by_default_names_tun0(tmp_path):
    done = run_agent(tmp_path)  # no .init.cfg: vpn_interface tun0, which this machine does not have
    assert done.returncode == 2
    assert done.stderr.count("\n") == 1 and "VPN interface 'tun0'" in done.stderr


def test_help_lists_every_option():
    done = run_agent("/nonexistent", "--help")
    assert done.returncode == 0
    for option in ("--home", "--log-level", "--no-stderr", "--help"):
        assert option in done.stdout
    script = os.path.join(REPO, "rcmp_n")
    done = subprocess.run([script, "--help"], capture_output=True, text=True, timeout=30,
                          env=dict(os.environ, PYTHONPATH=REPO))
    assert done.returncode == 0 and "--home" in done.stdout
    with open(script) as f:
        assert f.readline() == "#!/usr/bin/python3\n"


def test_cannot_listen_is_one_line_and_exit_1(procs, tmp_path):
    first = RcmpAgent(procs, tmp_path / "a").start()
    second = RcmpAgent(procs, tmp_path / "b", ext_port=first.ext_port)
    second.start(wait=False)
    wait_until(lambda: second.process.poll() is not None, timeout=20, message="the second master to give up")
    assert second.process.returncode == 1
    lines = [l for l in second.output().splitlines() if l.startswith("rcmp_n:")]
    assert len(lines) == 1 and "cannot start the master" in lines[0], second.output()


def test_sigint_and_sigterm_exit_0_and_log(procs, tmp_path):
    master = RcmpAgent(procs, tmp_path / "m").start()
    assert master.stop() == 0
    master.start()
    master.process.send_signal(signal.SIGINT)
    wait_until(lambda: master.process.poll() is not None, timeout=20, message="exit on SIGINT")
    assert master.process.returncode == 0
    text = master.log_text()
    assert "rcmp_n started as master 'master'" in text and text.rstrip().endswith("rcmp_n stopped")


def test_sigint_stops_an_agent_started_with_sigint_ignored(procs, tmp_path):
    """A shell's background job starts with SIGINT ignored; the agent still stops on it (CONTRACTS §1)."""
    master = RcmpAgent(procs, tmp_path / "m")
    master.process = procs.start(master.argv(), env=master.env(), name="rcmp-master", cwd=REPO,
                                 preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    master._log_size = 0
    master.wait_ready()
    master.process.send_signal(signal.SIGINT)
    wait_until(lambda: master.process.poll() is not None, timeout=20, message="exit on SIGINT")
    assert master.process.returncode == 0


def test_log_rotates_and_keeps_five(procs, tmp_path):
    master = RcmpAgent(procs, tmp_path / "m", log_max_bytes=1024).start()
    log_dir = os.path.join(master.home, "log")
    for i in range(150):  # every provisioning is logged at INFO (rejected ones are rate-limited: not those)
        assert master.post("/platform_instance/provisioning", {"pi_name": f"r{i}", "pi_service_logic": "empty"})[0] \
            == 200
    wait_until(lambda: os.path.exists(os.path.join(log_dir, "rcmp.log.5")), timeout=10, message="rcmp.log.5")
    names = sorted(os.listdir(log_dir))
    assert [n for n in names if n.startswith("rcmp.log")] == ["rcmp.log"] + [f"rcmp.log.{i}" for i in range(1, 6)]
    for name in names:
        if name.startswith("rcmp.log"):
            assert os.path.getsize(os.path.join(log_dir, name)) <= 1024 + 400
    assert master.stop() == 0


def test_robot_role_starts_and_stops(procs, tmp_path):
    robot = RcmpAgent(procs, tmp_path / "robot", role="robot", name="robot1", ip_master="127.0.0.1",
                      ic_port=free_port()).start()
    assert "rcmp_n started as robot 'robot1'" in robot.log_text()
    assert not os.path.exists(robot.db_path)
    assert robot.stop() == 0
