"""rcmp_service_item's workspace overlay (issue 12 row 14): a catkin workspace's setup script (run by bash, a child
process) runs as the workspace's owner, never as root for somebody else's files, and its code paths reach only
children that run as that owner unless the workspace is root's alone. The daemon side (rcmpd) is tested in
tests/system/test_install_hosts.py."""

import os
import shutil
import tempfile

import pytest

from rcm_platform import rcmp_service_item

pytestmark = pytest.mark.skipif(os.geteuid() != 0, reason="changes file owners: needs root")

NOBODY = 65534
SETUP = """
id -u > "$(dirname "${BASH_SOURCE[0]}")/ran-as"
export ROS_PACKAGE_PATH=/ws/src:/usr/share
export CMAKE_PREFIX_PATH=/ws/devel
export PYTHONPATH=/ws/devel/lib/python3/dist-packages
export LD_LIBRARY_PATH=/ws/devel/lib
export PATH=/ws/devel/bin:$PATH
export UNRELATED=1
"""


@pytest.fixture
def workspace():
    base = tempfile.mkdtemp(prefix="rcmp-ws-test-")
    os.chmod(base, 0o755)  # others may enter, as a home folder would let them
    ws = os.path.join(base, "rcmp_ws")
    os.makedirs(os.path.join(ws, "devel"))
    with open(os.path.join(ws, "devel", "setup.bash"), "w") as f:
        f.write(SETUP)
    rcmp_service_item._overlays.clear()
    try:
        yield ws
    finally:
        rcmp_service_item._overlays.clear()
        shutil.rmtree(base)


def chown_tree(path, uid):
    for root, dirs, files in os.walk(path):
        os.chown(root, uid, uid)
        for name in files:
            os.chown(os.path.join(root, name), uid, uid)


def test_a_users_workspace_runs_as_its_owner_and_lends_root_only_its_search_paths(workspace):
    chown_tree(workspace, NOBODY)
    overlay = rcmp_service_item.workspace_overlay(workspace)
    with open(os.path.join(workspace, "devel", "ran-as")) as f:
        assert f.read().strip() == str(NOBODY)  # never as root
    assert (overlay.owner_uid, overlay.trusted) == (NOBODY, False)
    assert overlay.search == {"ROS_PACKAGE_PATH": "/ws/src:/usr/share", "CMAKE_PREFIX_PATH": "/ws/devel"}
    assert "UNRELATED" not in overlay.code and overlay.code["PYTHONPATH"] == "/ws/devel/lib/python3/dist-packages"
    base = {"PATH": "/usr/bin:/bin", "HOME": "/root"}
    for_root = overlay.for_child(base)
    assert for_root["ROS_PACKAGE_PATH"] == "/ws/src:/usr/share"
    assert "PYTHONPATH" not in for_root and "LD_LIBRARY_PATH" not in for_root and "/ws" not in for_root["PATH"]
    for_owner = overlay.for_child(base, as_owner=True)
    assert for_owner["PYTHONPATH"] == "/ws/devel/lib/python3/dist-packages"
    assert for_owner["LD_LIBRARY_PATH"] == "/ws/devel/lib"
    # the system's folders stay first: a workspace cannot shadow the tools a child is started with
    assert for_owner["PATH"].split(":")[:4] == rcmp_service_item.SYSTEM_PATH.split(":")
    assert for_owner["PATH"].endswith("/ws/devel/bin")


def test_a_root_only_workspace_is_trusted(workspace):
    overlay = rcmp_service_item.workspace_overlay(workspace)
    with open(os.path.join(workspace, "devel", "ran-as")) as f:
        assert f.read().strip() == "0"
    assert overlay.trusted
    assert overlay.for_child({"PATH": "/usr/bin"})["PYTHONPATH"] == "/ws/devel/lib/python3/dist-packages"


def test_a_root_owned_workspace_others_can_write_is_not_trusted(workspace):
    os.chmod(os.path.dirname(workspace), 0o777)  # anybody can swap the workspace folder
    assert not rcmp_service_item.root_only(workspace)
    assert not rcmp_service_item.workspace_overlay(workspace).trusted


def test_apply_workspace_fills_the_environment_and_survives_a_broken_script(workspace):
    environ = {"PATH": "/usr/bin", "RCMP_WS": workspace}
    chown_tree(workspace, NOBODY)
    assert rcmp_service_item.apply_workspace(environ) is not None
    assert environ["ROS_PACKAGE_PATH"] == "/ws/src:/usr/share" and "PYTHONPATH" not in environ
    rcmp_service_item._overlays.clear()
    with open(os.path.join(workspace, "devel", "setup.bash"), "w") as f:
        f.write("exit 7\n")
    environ = {"PATH": "/usr/bin", "RCMP_WS": workspace}
    assert rcmp_service_item.apply_workspace(environ) is None
    assert environ == {"PATH": "/usr/bin", "RCMP_WS": workspace}
    assert rcmp_service_item.apply_workspace({"PATH": "/usr/bin"}) is None  # no workspace: nothing changes
