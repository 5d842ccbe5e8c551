"""Child processes owned by a test: each in its own session, stopped as a group, checked gone.

``ProcessGroup`` starts children with ``start_new_session=True`` (never through a shell) and, on ``stop_all``,
signals each child's whole process group (SIGINT, then SIGTERM, then SIGKILL, as roslaunch does) and asserts
that no process of any group is left. Use it as a context manager or through the ``procs`` fixture.
"""

import os
import signal
import subprocess

from .polling import wait_until

ROS_PATH = "/usr/bin:/bin:/usr/sbin:/sbin"


def ros_env(extra=None, master_uri=None):
    """The environment for a ROS child: this process's, /usr/bin first on PATH, optional ROS_MASTER_URI."""
    env = dict(os.environ)
    env["PATH"] = ROS_PATH + ":" + env.get("PATH", "")
    env.setdefault("ROS_LOG_DIR", os.environ.get("ROS_LOG_DIR", "/tmp/robotics-test-roslog"))
    if master_uri:
        env["ROS_MASTER_URI"] = master_uri
    env.pop("ROS_IP", None)
    env.pop("ROS_HOSTNAME", None)
    if extra:
        env.update(extra)
    return env


def group_alive(pgid):
    """True while any process of process group ``pgid`` exists (zombies of ours are reaped first)."""
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    # killpg(0) succeeds on zombies too: look for a member that is not a zombie
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        state, pgrp = fields[0], int(fields[2])
        if pgrp == pgid and state != "Z":
            return True
    return False


class ProcessGroup:
    """The child processes one test started."""

    def __init__(self, log_dir=None):
        self.children = []
        self.log_dir = log_dir

    def start(self, argv, env=None, name=None, **popen_kwargs):
        """Start ``argv`` (a list, no shell) in a new session; output goes to a log file if log_dir is set."""
        assert isinstance(argv, (list, tuple)), "argv must be a list: no shell"
        name = name or os.path.basename(str(argv[0]))
        log_path = None
        if self.log_dir and "stdout" not in popen_kwargs:
            log_path = os.path.join(self.log_dir, f"{name}-{len(self.children)}.log")
            with open(log_path, "wb") as log:
                popen_kwargs["stdout"] = log
                popen_kwargs.setdefault("stderr", subprocess.STDOUT)
                popen_kwargs.setdefault("stdin", subprocess.DEVNULL)
                proc = subprocess.Popen(list(argv), env=env, start_new_session=True, **popen_kwargs)
        else:
            popen_kwargs.setdefault("stdin", subprocess.DEVNULL)
            proc = subprocess.Popen(list(argv), env=env, start_new_session=True, **popen_kwargs)
        proc.test_name = name
        proc.log_path = log_path
        self.children.append(proc)
        return proc

    def output(self, proc):
        """The text the child wrote so far (when it logs to a file)."""
        if not getattr(proc, "log_path", None):
            return ""
        with open(proc.log_path, "rb") as f:
            return f.read().decode("utf-8", "replace")

    def stop(self, proc, timeouts=(5.0, 3.0, 3.0)):
        """Stop one child's whole group: SIGINT, SIGTERM, SIGKILL, each after the previous timed out."""
        pgid = proc.pid
        for sig, timeout in zip((signal.SIGINT, signal.SIGTERM, signal.SIGKILL), timeouts):
            try:
                os.killpg(pgid, sig)
            except ProcessLookupError:
                break
            try:
                wait_until(lambda: proc.poll() is not None and not group_alive(pgid), timeout=timeout,
                           message=f"{proc.test_name} (pgid {pgid}) to exit")
                break
            except AssertionError:
                continue
        try:
            proc.wait(timeout=1)
        except subprocess.TimeoutExpired:
            pass
        assert not group_alive(pgid), f"process group {pgid} of {proc.test_name} is still alive"

    def stop_all(self):
        errors = []
        for proc in reversed(self.children):
            try:
                self.stop(proc)
            except AssertionError as exc:
                errors.append(str(exc))
        self.children.clear()
        assert not errors, "; ".join(errors)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop_all()
