"""The stand-in broker's command line as a real child process (``python3 -m tests.ngsi_broker``)."""

import os
import signal
import socket
import subprocess

import pytest

from tests.ngsi_broker.testing import REPO_ROOT, start_broker


# --- the command line -------------------------------------------------------------------------------------

def run_cli(*args):
    return subprocess.run(["/usr/bin/python3", "-m", "tests.ngsi_broker", *args], cwd=REPO_ROOT,
                          capture_output=True, text=True, timeout=20, check=False)


def test_help_lists_every_option():
    done = run_cli("--help")
    assert done.returncode == 0
    for option in ("--port", "--host", "--notify-timeout", "--max-body", "--no-v1-initial-notification",
                   "--quiet"):
        assert option in done.stdout


def test_bad_options_are_refused_with_one_clear_line():
    for args, words in [(["--port", "70000"], "--port 70000"), (["--port", "abc"], "--port"),
                        (["--notify-timeout", "0"], "--notify-timeout")]:
        done = run_cli(*args)
        assert done.returncode == 2
        assert words in done.stderr and "Traceback" not in done.stderr


def test_port_in_use_is_one_line_and_exit_1():
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        done = run_cli("--port", str(taken.getsockname()[1]))
    assert done.returncode == 1
    assert done.stderr.strip().count("\n") == 0 and "cannot listen on 127.0.0.1:" in done.stderr


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_stops_cleanly_on_signal(procs, sig):
    broker = start_broker(procs)
    os.kill(broker.process.pid, sig)
    assert broker.process.wait(timeout=10) == 0
