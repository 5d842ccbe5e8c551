"""rcmp_deps: which system this is, and the one line naming the package to install for a missing module."""

import os
import sys

import pytest

from rcm_platform import rcmp_deps

DEBIAN = 'PRETTY_NAME="Debian GNU/Linux 12 (bookworm)"\nNAME="Debian GNU/Linux"\nID=debian\n'
UBUNTU = 'PRETTY_NAME="Ubuntu 20.04.6 LTS"\nNAME="Ubuntu"\nID=ubuntu\nID_LIKE=debian\n'
MINT = 'PRETTY_NAME="Linux Mint 21"\nID=linuxmint\nID_LIKE="ubuntu debian"\n'
FEDORA = 'PRETTY_NAME="Fedora Linux 40"\nID=fedora\n'


def system(tmp_path, release, ros=(), ros_modules=(), sees_system_site=True, environ=None):
    """A System read from real files: an os-release and an /opt/ros-like tree made under ``tmp_path``."""
    os_release = tmp_path / "os-release"
    os_release.write_text(release)
    ros_root = tmp_path / "ros"
    ros_root.mkdir(exist_ok=True)
    for distro in ros:
        site = ros_root / distro / "lib" / "python3" / "dist-packages"
        site.mkdir(parents=True, exist_ok=True)
        for module in ros_modules:
            (site / module).mkdir(exist_ok=True)
    path = [rcmp_deps.SYSTEM_SITE] if sees_system_site else ["/somewhere/else"]
    return rcmp_deps.this_system(str(os_release), str(ros_root), environ=environ or {}, path=path)


@pytest.mark.parametrize("release,apt,name", [
    (DEBIAN, True, "Debian GNU/Linux 12 (bookworm)"),
    (UBUNTU, True, "Ubuntu 20.04.6 LTS"),
    (MINT, True, "Linux Mint 21"),
    (FEDORA, False, "Fedora Linux 40"),
    ("", False, "this system"),
])
def test_the_system_is_read_from_os_release(tmp_path, release, apt, name):
    found = system(tmp_path, release)
    assert (found.apt, found.name, found.ros_distro) == (apt, name, None)


def test_the_ros_distribution_under_opt_ros(tmp_path):
    assert system(tmp_path, UBUNTU, ros=("melodic", "noetic")).ros_distro == "noetic"
    assert system(tmp_path, UBUNTU, ros=("melodic", "noetic"), environ={"ROS_DISTRO": "melodic"}).ros_distro \
        == "melodic"
    (tmp_path / "x").mkdir()
    only = system(tmp_path / "x", UBUNTU, ros=("jade",))
    assert only.ros_distro == "jade" and only.ros_prefix.endswith("/ros/jade")


def test_a_missing_module_on_debian_names_the_apt_package(tmp_path):
    line = rcmp_deps.missing_line(ModuleNotFoundError("No module named 'twisted'", name="twisted"),
                                  system(tmp_path, DEBIAN))
    assert line == ("Twisted (Python module 'twisted') is missing: install it with 'sudo apt-get install "
                    "python3-twisted' (Debian GNU/Linux 12 (bookworm))")
    assert "\n" not in line


@pytest.mark.parametrize("module,package", [
    ("netifaces", "python3-netifaces"), ("cryptography", "python3-cryptography"),
    ("prometheus_client", "python3-prometheus-client"), ("OpenSSL", "python3-openssl"),
    ("roslaunch", "python3-roslaunch"), ("rospkg", "python3-rospkg"), ("catkin", "catkin"),
    ("some_new_module", "python3-some-new-module"),   # Debian's naming policy for what the table lacks
])
def test_debian_and_ubuntu_package_names(tmp_path, module, package):
    for release in (DEBIAN, UBUNTU):
        line = rcmp_deps.missing_line(module, system(tmp_path, release))
        assert f"'sudo apt-get install {package}'" in line, line


def test_ros_from_opt_ros_gets_the_ros_repositorys_names(tmp_path):
    ubuntu = system(tmp_path, UBUNTU, ros=("noetic",))
    assert "'sudo apt-get install ros-noetic-roslaunch' (Ubuntu 20.04.6 LTS)" in \
        rcmp_deps.missing_line("roslaunch", ubuntu)
    # rospkg is not a ROS package: the same name in ROS's repository and Ubuntu's
    assert "'sudo apt-get install python3-rospkg'" in rcmp_deps.missing_line("rospkg", ubuntu)
    # installed under /opt/ros but not on the path: the environment, not a package, is missing
    sourced = system(tmp_path, UBUNTU, ros=("noetic",), ros_modules=("roslaunch",))
    line = rcmp_deps.missing_line("roslaunch", sourced)
    assert "not on this Python's path" in line and "source " + str(tmp_path / "ros" / "noetic" / "setup.bash") \
        in line and "apt-get" not in line


def test_a_python_that_does_not_see_the_system_packages_is_told_to_use_the_systems(tmp_path):
    other = system(tmp_path, DEBIAN, sees_system_site=False)
    present = next(m for m in ("twisted", "netifaces", "yaml")
                   if os.path.isdir(os.path.join(rcmp_deps.SYSTEM_SITE, m)))
    line = rcmp_deps.missing_line(present, other)
    assert f"is not available to {sys.executable}" in line
    assert "run '/usr/bin/python3 -m rcm_platform' instead" in line and "is installed for it" in line
    line = rcmp_deps.missing_line("no_such_module_here", other)
    assert "'sudo apt-get install python3-no-such-module-here' and run rcmp_n with /usr/bin/python3" in line


def test_another_system_is_told_the_project_and_the_debian_name(tmp_path):
    line = rcmp_deps.missing_line("twisted", system(tmp_path, FEDORA))
    assert line.endswith("install Twisted for " + sys.executable + " (on Debian and Ubuntu: the package "
                         "python3-twisted)")
    assert "apt-get" not in line


def test_a_module_that_is_there_but_broken_says_so(tmp_path):
    exc = ImportError("cannot import name 'ssl' from 'twisted.internet'", name="twisted.internet")
    line = rcmp_deps.missing_line(exc, system(tmp_path, DEBIAN))
    assert line == ("Twisted (Python module 'twisted') cannot be used: cannot import name 'ssl' from "
                    "'twisted.internet'; reinstall or upgrade python3-twisted")


def test_why_is_said(tmp_path):
    line = rcmp_deps.missing_line("prometheus_client", system(tmp_path, DEBIAN), why="for /metrics")
    assert "is missing (for /metrics): install it" in line


def test_require_looks_modules_up_without_importing_them(tmp_path):
    rcmp_deps.require(["json", "twisted"])
    with pytest.raises(rcmp_deps.MissingDependency) as info:
        rcmp_deps.require(["json", "no_such_module_x", "twisted"], system=system(tmp_path, DEBIAN))
    assert info.value.name == "no_such_module_x"
    assert str(info.value).startswith("no_such_module_x (Python module 'no_such_module_x') is missing")
    assert isinstance(info.value, ImportError)
