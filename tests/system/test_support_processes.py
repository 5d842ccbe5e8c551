"""The test support itself: a ROS master comes up on a free port and leaves nothing behind; a process group's
grandchildren go with it."""

from tests.support.polling import wait_until
from tests.support.processes import ProcessGroup, group_alive
from tests.support.rosmaster import RosMaster


def test_ros_master_starts_and_stops_without_leftovers(tmp_path):
    with ProcessGroup(log_dir=str(tmp_path)) as procs:
        master = RosMaster(procs).start()
        assert master.api().is_online()
        pgid = master.process.pid
    assert not group_alive(pgid)
    assert not master.api().is_online()


def test_process_group_kills_grandchildren(tmp_path):
    with ProcessGroup(log_dir=str(tmp_path)) as procs:
        # a child that starts a grandchild which ignores SIGINT and SIGTERM
        proc = procs.start(["/usr/bin/python3", "-c",
                            "import signal, subprocess, sys, time\n"
                            "signal.signal(signal.SIGINT, signal.SIG_IGN)\n"
                            "signal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
                            "subprocess.Popen([sys.executable, '-c', 'import signal,time;"
                            "signal.signal(signal.SIGINT, signal.SIG_IGN);"
                            "signal.signal(signal.SIGTERM, signal.SIG_IGN);time.sleep(600)'])\n"
                            "print('ready', flush=True)\n"
                            "time.sleep(600)\n"])
        wait_until(lambda: "ready" in procs.output(proc), timeout=10)
        procs.stop(proc, timeouts=(0.3, 0.3, 5.0))
        assert not group_alive(proc.pid)
