"""rcmp_service_item: what a service item is and how it becomes a process: its argv (never a shell), the executable
rosrun would run, its environment, the special items, its user (``resolve_run_as``)."""

import os
import pwd

import pytest

from rcm_platform import rcmp_command, rcmp_service_item


def node(name, side="S", package="robotics_test", node_type="talker.py", params=""):
    return {"sn_package": package, "sn_type": node_type, "sn_name": name, "sn_params": params, "sn_side": side}


def launcher(name, side="S", package="robotics_test", launch_file="two_talkers.launch", params=""):
    return {"sl_package": package, "sl_file_launcher": launch_file, "sl_name": name, "sl_params": params,
            "sl_side": side}


def test_item_argv_never_goes_through_a_shell():
    assert rcmp_service_item.node_argv("pkg", "node.py", "n1", "a:=1 'b c' _x:=2") == [
        "rosrun", "pkg", "node.py", "a:=1", "b c", "_x:=2", "__name:=n1"]
    argv = rcmp_service_item.launcher_argv("pkg", "x.launch", "prefix:=p; rm -rf /")
    assert argv[0] == "roslaunch" and "--wait" in argv
    assert argv[-6:] == ["pkg", "x.launch", "prefix:=p;", "rm", "-rf", "/"]  # just words; nothing runs them


def test_node_executables_find_what_rosrun_would_run():
    found = rcmp_service_item.NodeExecutables()
    env = dict(os.environ)
    argv = found.direct_argv(["rosrun", "robotics_test", "talker.py", "_a:=1", "__name:=t"], env)
    assert argv[0].endswith("/robotics_test/scripts/talker.py") and os.access(argv[0], os.X_OK)
    assert argv[1:] == ["_a:=1", "__name:=t"]
    # two matches (the script and its devel-space relay in the package's libexec): the relay, as rosrun picks
    assert "/devel/lib/firos/core.py" in found.direct_argv(["rosrun", "firos", "core.py"], env)[0]
    assert found.direct_argv(["rosrun", "rosout", "rosout"], env) == ["/usr/lib/rosout/rosout"]
    # what rosrun must decide (and explain in the item's log) stays rosrun's
    for argv in (["rosrun", "no_such_package", "x"], ["rosrun", "robotics_test", "no_such_node.py"],
                 ["rosrun", "--prefix", "gdb", "robotics_test", "talker.py"], ["roslaunch", "a", "b"]):
        assert found.direct_argv(argv, env) == argv
    # a child whose package path is not the agent's would find other files: rosrun, in the child, decides
    elsewhere = dict(env, ROS_PACKAGE_PATH="/elsewhere")
    assert found.direct_argv(["rosrun", "robotics_test", "talker.py"], elsewhere)[0] == "rosrun"


def test_node_executables_forget_a_file_that_is_no_longer_executable(tmp_path, monkeypatch):
    package = tmp_path / "src" / "tmp_pkg"
    (package / "scripts").mkdir(parents=True)
    (package / "package.xml").write_text(
        '<?xml version="1.0"?><package format="2"><name>tmp_pkg</name><version>0.0.1</version>'
        '<description>x</description><maintainer email="a@example.org">a</maintainer><license>BSD</license>'
        '<buildtool_depend>catkin</buildtool_depend></package>')
    script = package / "scripts" / "n.py"
    script.write_text("#!/usr/bin/python3\n")
    script.chmod(0o755)
    monkeypatch.setenv("ROS_PACKAGE_PATH", f"{tmp_path / 'src'}:{os.environ.get('ROS_PACKAGE_PATH', '')}")
    found = rcmp_service_item.NodeExecutables()
    assert found.find("tmp_pkg", "n.py") == str(script)
    script.chmod(0o644)
    assert found.find("tmp_pkg", "n.py") is None
    assert found.direct_argv(["rosrun", "tmp_pkg", "n.py"], dict(os.environ)) == ["rosrun", "tmp_pkg", "n.py"]


def test_child_env_points_at_the_space():
    env = rcmp_service_item.child_env({"PATH": "/root/.pyenv/shims:/usr/bin", "ROS_PACKAGE_PATH": "/ws/src",
                                       "ROS_NAMESPACE": "/x"}, "http://10.8.0.1:11312/", "10.8.0.1", "/h/log/ros")
    assert env["PATH"].split(":")[0] == "/usr/bin"
    assert env["PATH"].endswith("/root/.pyenv/shims")
    assert env["ROS_MASTER_URI"] == "http://10.8.0.1:11312/"
    assert env["ROS_IP"] == env["ROS_HOSTNAME"] == "10.8.0.1"
    assert env["ROS_LOG_DIR"] == "/h/log/ros"
    assert env["ROS_PACKAGE_PATH"] == "/ws/src"
    assert "ROS_NAMESPACE" not in env


def test_special_items_are_recognised_in_one_table():
    logic = {"sn_list": [node("f", package="firos", node_type="core.py"),
                         node("d", package="rcm", node_type="rcm_driver.py", params="port=1 x:=2"),
                         node("t")],
             "sl_list": [launcher("l", package="firos", launch_file="core.py")]}
    items = {i.name: i for i in rcmp_service_item.items_of_logic(logic)}
    assert items["f"].special is rcmp_service_item.SPECIAL_ITEMS[("firos", "core.py")]
    assert items["d"].special is rcmp_service_item.SPECIAL_ITEMS[("rcm", "rcm_driver.py")]
    assert items["t"].special is None and items["l"].special is None   # only nodes are special
    items["f"].inbound_port, items["d"].driver_port = 10100, 9999
    firos, driver = items["f"].special, items["d"].special
    assert items["f"].argv(firos.params(items["f"]), firos.extra_argv(items["f"]))[-2:] == ["-P", "10100"]
    argv = items["d"].argv(driver.params(items["d"]), driver.extra_argv(items["d"]))
    assert argv == ["rosrun", "rcm", "rcm_driver.py", "x:=2", "port=9999", "__name:=d"]


class _Host:
    def choose_driver_port(self):
        return 9998


def test_rcm_driver_gets_a_one_time_key_in_its_environment_never_on_its_command_line():
    logic = {"sn_list": [node("d", package="rcm", node_type="rcm_driver.py"), node("t")], "sl_list": []}
    driver, plain = rcmp_service_item.items_of_logic(logic)
    driver.special.prepare(_Host(), None, driver)
    other = rcmp_service_item.items_of_logic(logic)[0]
    other.special.prepare(_Host(), None, other)
    assert len(driver.driver_key) == 32 and driver.driver_key != other.driver_key     # one per start
    env = driver.special.environment(driver, {"ROS_MASTER_URI": "http://x:1/"})
    assert env == {"ROS_MASTER_URI": "http://x:1/", "RCM_DRIVER_KEY": driver.driver_key}
    assert not any(driver.driver_key in word for word in driver.argv(driver.special.params(driver)))
    assert plain.special is None


def test_items_are_built_from_validated_entries_only():
    with pytest.raises(rcmp_command.BadRequest, match=r"sn_list\[0\] lacks the required field 'sn_side'"):
        rcmp_service_item.items_of_logic({"sn_list": [{"sn_name": "x", "sn_package": "p", "sn_type": "t"}]})
    with pytest.raises(rcmp_command.BadRequest, match="cannot be split"):
        rcmp_service_item.ServiceItem.from_entry(node("x", params="'unbalanced"), "robot1")


# -- the user items run as ------------------------------------------------------------------------------------

needs_root = pytest.mark.skipif(os.geteuid() != 0, reason="switching users needs a root agent")

NOBODY = pwd.getpwnam("nobody")


@needs_root
def test_default_is_the_workspace_owner_and_their_children_get_its_code_paths(tmp_path):
    from rcm_platform.rcmp_config import make_config
    from rcm_platform.rcmp_service_item import RunAs, WorkspaceOverlay, resolve_run_as
    workspace = tmp_path / "rcmp_ws"
    workspace.mkdir()
    os.chown(workspace, NOBODY.pw_uid, NOBODY.pw_gid)
    config = make_config("robot", str(tmp_path), name="r1")
    run_as = resolve_run_as(config, {"RCMP_WS": str(workspace)})
    assert (run_as.name, run_as.uid, run_as.gid) == ("nobody", NOBODY.pw_uid, NOBODY.pw_gid)
    assert run_as.setpriv_args() == [f"--reuid={NOBODY.pw_uid}", f"--regid={NOBODY.pw_gid}", "--init-groups"]
    # HOME=~/rcmp_ws's owner has none of their own here: a private folder, theirs only
    assert os.stat(run_as.home).st_uid == NOBODY.pw_uid and not os.stat(run_as.home).st_mode & 0o077
    # no workspace and no run_as: the agent's own user (None), said in the log by a root agent
    assert resolve_run_as(config, {"RCMP_WS": str(tmp_path / "none")}) is None
    # the owner's children get the workspace's code paths; another user's do not
    overlay = WorkspaceOverlay(str(workspace), NOBODY.pw_uid, NOBODY.pw_gid, False,
                               {"ROS_PACKAGE_PATH": "/ws/src"}, {"PYTHONPATH": "/ws/devel/lib/python3/dist-packages"})
    owner = RunAs.for_user(NOBODY, overlay).environment({"PATH": "/usr/bin:/bin", "HOME": "/root"})
    assert owner["PYTHONPATH"] == "/ws/devel/lib/python3/dist-packages" and owner["HOME"] != "/root"
    other = RunAs.for_user(NOBODY).environment({"PATH": "/usr/bin:/bin"})
    assert "PYTHONPATH" not in other and other["USER"] == "nobody"
