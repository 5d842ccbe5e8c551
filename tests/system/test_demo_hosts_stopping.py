"""`./run demo-hosts` stops on Ctrl-C (or SIGTERM, or a closed terminal) however it was started, and its console
is reachable from this machine's browser through the loopback port it forwards into the master's machine.

Each case starts the demo its own way, waits until it says where the console is (the master answers; the robots
are being provisioned, started and paired: the demo is in the middle of its work), fetches the console and the
RDAPI through that address from this machine, sends the signal a person's action sends, and checks that the demo
said it stopped, and that no namespace, process or listening port of it is left. Starting the demo in the
background of a shell needs a shell: the fixed script ``"$@" & ...`` is run by ``bash -c`` with the demo's argv as
its arguments (nothing is built from input).
"""

import json
import os
import re
import signal
import urllib.request

import pytest

from tests.support.hosts import netns_names
from tests.support.lifecycle import processes_mentioning
from tests.support.polling import wait_until
from tests.support.ports import free_port, port_accepts
from tests.support.processes import group_alive, ros_env

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
DEMO = ["/usr/bin/python3", "-m", "demo.run_demo_hosts"]
# what a non-interactive shell does with `cmd &`: the child starts with SIGINT and SIGQUIT ignored
BACKGROUND = '"$@" & echo "background pid $!"; wait "$!"'

pytestmark = [pytest.mark.netns, pytest.mark.slow]


@pytest.fixture(autouse=True)
def _root_only():
    if os.geteuid() != 0:
        pytest.skip("the demo's machines are network namespaces (root only)")


def wait_for_console(procs, proc, timeout=120):
    """The console address the demo printed once its master answered."""
    def printed():
        text = procs.output(proc)
        if proc.poll() is not None:
            raise AssertionError(f"the demo exited {proc.returncode} before its console was up: {text[-2000:]}")
        found = re.search(r"demo-hosts: console on (http://127\.0\.0\.1:\d+)/console/", text)
        return found.group(1) if found else None
    return wait_until(printed, timeout=timeout, interval=0.3, message="the demo to print its console address")


def check_console_reachable(base):
    """This machine (not a namespace) reaches the master's console and RDAPI through the forwarded port."""
    with urllib.request.urlopen(base + "/console/", timeout=10) as page:
        assert "<title>RCM platform console</title>" in page.read().decode()
    with urllib.request.urlopen(base + "/platform_instance/read", timeout=10) as answer:
        assert json.loads(answer.read())["result"] == "OK"


def demo_pid(workdir):
    """The demo's own process (python running demo.run_demo_hosts with this workdir)."""
    pids = [pid for pid, cmd in processes_mentioning(workdir) if "demo.run_demo_hosts" in cmd and "python" in cmd
            and not cmd.startswith(("make", "bash"))]
    assert len(pids) == 1, processes_mentioning(workdir)
    return pids[0]


def assert_all_gone(procs, proc, pid, workdir, port):
    text = procs.output(proc)
    assert "demo-hosts: stopped; every machine (namespace) and process removed" in text, text[-3000:]
    assert not [n for n in netns_names() if n.startswith(f"rcmt-{pid}-")]
    wait_until(lambda: not processes_mentioning(workdir), timeout=15,
               message=f"every demo process to be gone: {processes_mentioning(workdir)}")
    assert not port_accepts(port)
    assert not group_alive(proc.pid)
    with open(os.path.join(workdir, "master", "log", "rcmp.log")) as log:
        assert "rcmp_n stopped" in log.read()


def demo_argv(tmp_path):
    workdir = str(tmp_path / "demo-hosts")
    port = free_port()
    return workdir, port, ["--workdir", workdir, "--console-port", str(port)]


def test_started_in_the_background_of_a_shell_it_stops_on_sigint_and_on_a_second_one_says_it_is_busy(procs,
                                                                                                     tmp_path):
    # the shell really starts background jobs with SIGINT ignored (what made the demo deaf to it)
    probe = procs.start(["bash", "-c", BACKGROUND, "bash", "sleep", "60"], name="probe")
    pid = wait_until(lambda: re.search(r"background pid (\d+)", procs.output(probe)), timeout=10).group(1)
    with open(f"/proc/{pid}/status") as status:
        ignored = int(re.search(r"^SigIgn:\s*([0-9a-f]+)", status.read(), re.M).group(1), 16)
    assert ignored & (1 << (signal.SIGINT - 1))
    procs.stop(probe)

    workdir, port, args = demo_argv(tmp_path)
    shell = procs.start(["bash", "-c", BACKGROUND, "bash", *DEMO, *args], env=ros_env(), cwd=ROOT,
                        name="demo-hosts-background")
    base = wait_for_console(procs, shell)
    assert base == f"http://127.0.0.1:{port}"
    check_console_reachable(base)
    pid = int(re.search(r"background pid (\d+)", procs.output(shell)).group(1))
    os.kill(pid, signal.SIGINT)
    wait_until(lambda: "SIGINT: stopping every agent" in procs.output(shell), timeout=10,
               message="the demo to say it is stopping")
    os.kill(pid, signal.SIGINT)       # impatience: answered, and the cleanup goes on
    assert shell.wait(timeout=120) == 0
    assert "SIGINT again: still removing the machines" in procs.output(shell)
    assert_all_gone(procs, shell, pid, workdir, port)


def test_through_run_and_make_ctrl_c_stops_it(procs, tmp_path):
    """``./run demo-hosts`` with the user's own PATH (pyenv's python first here) and Ctrl-C: SIGINT to the whole
    foreground process group (./run's make, the overlay script's shell, the demo)."""
    workdir, port, args = demo_argv(tmp_path)
    run = procs.start([os.path.join(ROOT, "run"), "demo-hosts", "DEMO_ARGS=" + " ".join(args)], env=dict(os.environ),
                      cwd=ROOT, name="run-demo-hosts")
    base = wait_for_console(procs, run, timeout=240)   # ./run first checks the dependencies and the build
    check_console_reachable(base)
    pid = demo_pid(workdir)
    os.killpg(run.pid, signal.SIGINT)
    run.wait(timeout=120)     # make reports the interrupt as make does (killed by SIGINT); the demo exits 0
    assert_all_gone(procs, run, pid, workdir, port)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP], ids=["sigterm", "sighup"])
def test_with_no_terminal_it_stops_on_sigterm_and_when_its_terminal_goes(procs, tmp_path, sig):
    """No controlling terminal (its own session, input from /dev/null, output to a file): SIGTERM as a service
    manager or ``kill`` sends it, SIGHUP as a closed terminal or ssh session sends it."""
    workdir, port, args = demo_argv(tmp_path)
    demo = procs.start([*DEMO, *args], env=ros_env(), cwd=ROOT, name="demo-hosts-detached")
    base = wait_for_console(procs, demo)
    check_console_reachable(base)
    os.kill(demo.pid, sig)
    assert demo.wait(timeout=120) == 0
    assert f"{signal.Signals(sig).name}: stopping every agent" in procs.output(demo)
    assert_all_gone(procs, demo, demo.pid, workdir, port)
