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
                                       "ROS_NAMESPACE": "/x"}, "http://198.51.100.1:11312/", "198.51.100.1", "/h/log/ros")
    assert env["PATH"].split(":")[0] == "/usr/bin"
    assert env["PATH"].endswith("/root/.pyenv/shims")
    assert env["ROS_MASTER_URI"] == "http://198.51.100.1:11312/"
    assert env["ROS_IP"] == env["ROS_HOSTNAME"] == "198.51.100.1"
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


# -- the ROS installation's environment (ros_setup) ---------------------------------------------------------------

NOETIC = "/opt/ros/noetic"
# what sourcing /opt/ros/noetic/setup.bash leaves in an environment holding only PATH, HOME and LC_ALL
NOETIC_SOURCED = {
    "PATH": f"{NOETIC}/bin:/usr/bin:/bin:/usr/sbin:/sbin", "HOME": "/root", "LC_ALL": "C", "PWD": "/", "SHLVL": "1",
    "_": "/usr/bin/env", "PYTHONPATH": f"{NOETIC}/lib/python3/dist-packages", "LD_LIBRARY_PATH": f"{NOETIC}/lib",
    "PKG_CONFIG_PATH": f"{NOETIC}/lib/pkgconfig", "CMAKE_PREFIX_PATH": NOETIC, "ROSLISP_PACKAGE_DIRECTORIES": "",
    "ROS_PACKAGE_PATH": f"{NOETIC}/share", "ROS_DISTRO": "noetic", "ROS_VERSION": "1", "ROS_PYTHON_VERSION": "3",
    "ROS_ETC_DIR": f"{NOETIC}/etc/ros", "ROS_ROOT": f"{NOETIC}/share/ros",
    "ROS_MASTER_URI": "http://localhost:11311", "ROS_IP": "127.0.0.1", "ROS_HOSTNAME": "localhost",
    "CATKIN_SHELL": "bash", "UNRELATED": "1",
}
NOETIC_KEPT = {
    "PATH": f"{NOETIC}/bin", "PYTHONPATH": f"{NOETIC}/lib/python3/dist-packages", "LD_LIBRARY_PATH": f"{NOETIC}/lib",
    "PKG_CONFIG_PATH": f"{NOETIC}/lib/pkgconfig", "CMAKE_PREFIX_PATH": NOETIC, "ROS_PACKAGE_PATH": f"{NOETIC}/share",
    "ROS_DISTRO": "noetic", "ROS_VERSION": "1", "ROS_PYTHON_VERSION": "3", "ROS_ETC_DIR": f"{NOETIC}/etc/ros",
    "ROS_ROOT": f"{NOETIC}/share/ros",
}


def test_ros_variables_keep_paths_and_ros_variables_but_no_master_and_no_address():
    # ROS's own hook sets ROS_MASTER_URI to localhost: each service space says where its master is
    assert rcmp_service_item.ros_variables(NOETIC_SOURCED) == NOETIC_KEPT
    assert rcmp_service_item.ros_variables({"PATH": "/usr/bin:/bin:/usr/sbin:/sbin", "HOME": "/root"}) == {}


def test_ros_goes_under_the_agents_environment_and_the_workspace_on_top():
    ros = rcmp_service_item.RosEnvironment(f"{NOETIC}/setup.bash", NOETIC_KEPT)
    env = ros.for_child({"PATH": "/root/.pyenv/shims:/usr/bin:/usr/local/bin", "PYTHONPATH": "/src/repo",
                         "ROS_DISTRO": "Debian", "HOME": "/root"})
    # the system's folders first (the PATH trap), then ROS's, then the rest; ROS's Python before the caller's
    assert env["PATH"] == f"/usr/bin:/bin:/usr/sbin:/sbin:{NOETIC}/bin:/root/.pyenv/shims:/usr/local/bin"
    assert env["PYTHONPATH"] == f"{NOETIC}/lib/python3/dist-packages:/src/repo"
    assert (env["ROS_DISTRO"], env["ROS_PACKAGE_PATH"], env["HOME"]) == ("noetic", f"{NOETIC}/share", "/root")
    assert "ROS_MASTER_URI" not in env
    assert ros.for_child(env) == env   # applied twice: nothing listed twice
    # a workspace built on that ROS chains onto it: its search paths replace ROS's, ROS's bin stays on PATH
    overlay = rcmp_service_item.WorkspaceOverlay(
        "/root/rcmp_ws", 0, 0, True, {"ROS_PACKAGE_PATH": f"/root/rcmp_ws/src:{NOETIC}/share"},
        {"PATH": f"{NOETIC}/bin:/usr/bin:/bin", "PYTHONPATH": f"/root/rcmp_ws/devel/lib/python3/dist-packages:"
                                                            f"{NOETIC}/lib/python3/dist-packages"})
    top = overlay.for_child(env)
    assert top["ROS_PACKAGE_PATH"] == f"/root/rcmp_ws/src:{NOETIC}/share"
    assert top["PATH"] == env["PATH"] and top["ROS_DISTRO"] == "noetic"
    # and each child of a space: /usr/bin first, ROS's programs found, the space's master and address
    child = rcmp_service_item.child_env(top, "http://198.51.100.1:11312/", "198.51.100.2", "/h/log/ros")
    assert child["PATH"].split(":")[:5] == ["/usr/bin", "/bin", "/usr/sbin", "/sbin", f"{NOETIC}/bin"]
    assert (child["ROS_MASTER_URI"], child["ROS_IP"], child["ROS_DISTRO"]) == (
        "http://198.51.100.1:11312/", "198.51.100.2", "noetic")


def ros_config(home, text=""):
    """A robot's configuration in ``home`` with ``text`` under its [main] section, as the agent loads it."""
    from rcm_platform.rcmp_config import load_config
    home.mkdir()
    (home / "init.cfg").write_text("[main]\nname=robot1\n" + text)
    return load_config(home)


def setup_script(root, distro="noetic"):
    (root / distro).mkdir(parents=True)
    script = root / distro / "setup.bash"
    script.write_text("# ROS's setup script\n")
    return script


def test_without_a_setup_script_nothing_changes(tmp_path):
    setup_script(tmp_path / "ros")
    for name, text, root in (("debian", "", tmp_path / "no-ros"), ("chosen", "ros_setup=none\n", tmp_path / "ros")):
        environ, path = {"PATH": "/usr/bin:/bin", "PYTHONPATH": "/src/repo"}, ["", "/usr/lib/python3/dist-packages"]
        config = ros_config(tmp_path / name, text)
        assert rcmp_service_item.apply_ros_environment(config, environ, path, search_root=str(root)) is None
        assert environ == {"PATH": "/usr/bin:/bin", "PYTHONPATH": "/src/repo"}
        assert path == ["", "/usr/lib/python3/dist-packages"]


@needs_root
def test_the_found_script_goes_under_the_environment_and_its_python_packages_on_the_path(tmp_path, monkeypatch):
    script = setup_script(tmp_path / "ros")
    # its environment as ros_environment computes it (running bash is a system test's: test_ros_environment.py)
    monkeypatch.setitem(rcmp_service_item._ros_environments, str(script),
                        rcmp_service_item.RosEnvironment(str(script), NOETIC_KEPT))
    config = ros_config(tmp_path / "home")
    environ, path = {"PATH": "/usr/bin:/bin", "PYTHONPATH": "/src/repo"}, ["/here", "/usr/lib/python3.8"]
    ros = rcmp_service_item.apply_ros_environment(config, environ, path, search_root=str(tmp_path / "ros"))
    assert ros.setup == str(script)
    assert environ["ROS_DISTRO"] == "noetic" and environ["PATH"].endswith(f":{NOETIC}/bin")
    assert environ["PYTHONPATH"] == f"{NOETIC}/lib/python3/dist-packages:/src/repo"
    assert path == ["/here", f"{NOETIC}/lib/python3/dist-packages", "/usr/lib/python3.8"]  # where PYTHONPATH goes
    rcmp_service_item.apply_ros_environment(config, environ, path, search_root=str(tmp_path / "ros"))
    assert path.count(f"{NOETIC}/lib/python3/dist-packages") == 1


@needs_root
@pytest.mark.parametrize("change", ["script", "folder", "owner"])
def test_a_root_agent_refuses_a_setup_script_somebody_else_can_change(tmp_path, monkeypatch, change):
    script = setup_script(tmp_path / "ros")
    monkeypatch.setitem(rcmp_service_item._ros_environments, str(script),
                        rcmp_service_item.RosEnvironment(str(script), NOETIC_KEPT))   # never used: refused first
    if change == "script":
        script.chmod(0o666)
    elif change == "folder":
        script.parent.chmod(0o775)
    else:
        os.chown(script, NOBODY.pw_uid, NOBODY.pw_gid)
    config = ros_config(tmp_path / "home", f"ros_setup={script}\n")
    environ, path = {"PATH": "/usr/bin:/bin"}, [""]
    with pytest.raises(rcmp_service_item.RosSetupError) as info:
        rcmp_service_item.apply_ros_environment(config, environ, path)
    message = str(info.value)
    assert message.startswith(f"{config.config_file}: key 'ros_setup': {script} or a folder above it is not "
                              f"root's alone"), message
    assert "\n" not in message and environ == {"PATH": "/usr/bin:/bin"} and path == [""]

    # found rather than given: the line says where it was found
    config = ros_config(tmp_path / "found")
    with pytest.raises(rcmp_service_item.RosSetupError, match=r"key 'ros_setup' \(not set; .* found in "):
        rcmp_service_item.apply_ros_environment(config, {}, [], search_root=str(tmp_path / "ros"))


def test_a_given_setup_script_that_is_missing_stops_the_agent_with_one_line(tmp_path):
    config = ros_config(tmp_path / "home", "ros_setup=/nonexistent/ros/setup.bash\n")
    with pytest.raises(rcmp_service_item.RosSetupError) as info:
        rcmp_service_item.apply_ros_environment(config, {}, [])
    assert str(info.value) == (f"{config.config_file}: key 'ros_setup': /nonexistent/ros/setup.bash is not a "
                               f"readable file")
