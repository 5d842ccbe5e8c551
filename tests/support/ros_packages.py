"""ROS's share of this machine's Debian packages: its Python packages, programs and package folders.

Debian installs ROS 1 beside everything else: its Python packages (``rospy``, ``rosgraph``, ``genpy``,
``std_msgs``, ``catkin_pkg``, ...) in ``/usr/lib/python3/dist-packages`` next to Debian's Twisted and
cryptography, its programs (``rosmaster``, ``rosrun``, ``catkin_make``, ...) in ``/usr/bin``, its packages'
folders in ``/usr/share/<pkg>`` and ``/usr/lib/<pkg>``. ROS's own are the files of the Debian packages built
from a source package named ``ros-*``; this module finds them with ``dpkg-query`` (no list of names to keep up
to date) and links them into a folder of their own, so that:

- a Python of another version (a venv of the compatibility matrix) sees ROS's packages but keeps its own
  Twisted: ``python -m tests.support.ros_packages FOLDER`` fills FOLDER with links to ROS's Python packages,
  and the caller puts FOLDER on that Python's path (tox.ini does);
- ``tests/support/noetic.py`` can build an ``/opt/ros/noetic``-shaped prefix out of links and copies, and hide
  ROS's programs from a test host's ``/usr/bin``.

Pure Python 3.8+, no ROS needed to import it.
"""

import os
import subprocess
import sys

DIST_PACKAGES = "/usr/lib/python3/dist-packages"


def _dpkg_query(args):
    return subprocess.run(["dpkg-query", *args], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                          stdin=subprocess.DEVNULL, universal_newlines=True).stdout


def ros_debian_packages():
    """Names of the installed Debian packages built from one of ROS's source packages (``ros-*``)."""
    names = []
    for line in _dpkg_query(["-W", "-f", "${Package} ${source:Package} ${db:Status-Abbrev}\n"]).splitlines():
        parts = line.split()
        if len(parts) >= 3 and parts[1].startswith("ros-") and parts[2] == "ii":
            names.append(parts[0])
    return sorted(names)


def ros_files():
    """Every path the ROS Debian packages installed (files and folders)."""
    packages = ros_debian_packages()
    if not packages:
        return []
    return [line for line in _dpkg_query(["-L", *packages]).splitlines() if line.startswith("/")]


def _entries_below(paths, folder):
    """Names of the entries directly in ``folder`` among ``paths``."""
    prefix = folder.rstrip("/") + "/"
    return sorted({p[len(prefix):] for p in paths if p.startswith(prefix) and "/" not in p[len(prefix):]})


def python_packages(files=None):
    """{name: path} of ROS's top-level Python packages and modules in Debian's dist-packages, with their metadata
    (``*.egg-info``: catkin's console scripts look their distribution up by name)."""
    files = ros_files() if files is None else files
    found = {}
    for name in _entries_below(files, DIST_PACKAGES):
        if name.endswith(".pth") or name == "__pycache__":
            continue
        found[name] = os.path.join(DIST_PACKAGES, name)
    return found


def programs(files=None):
    """{name: path} of ROS's programs in /usr/bin (``rosmaster``, ``roscore``, ``rosrun``, ``catkin_make``, ...)."""
    files = ros_files() if files is None else files
    return {name: os.path.join("/usr/bin", name) for name in _entries_below(files, "/usr/bin")}


def package_folders(files=None):
    """{name: path} of ROS's package folders: ``/usr/share/<pkg>`` holding a package.xml (what rospack finds)."""
    files = ros_files() if files is None else files
    shared = set(files)
    return {name: os.path.join("/usr/share", name) for name in _entries_below(files, "/usr/share")
            if os.path.join("/usr/share", name, "package.xml") in shared}


def library_folders(packages, files=None):
    """{name: path} of ``/usr/lib/<pkg>`` for each ROS package name in ``packages``: the programs of a package
    that ``rosrun`` and roslaunch find (``/usr/lib/rosout/rosout``, ...)."""
    files = ros_files() if files is None else files
    return {name: os.path.join("/usr/lib", name) for name in _entries_below(files, "/usr/lib")
            if name in packages and os.path.isdir(os.path.join("/usr/lib", name))}


def link_into(folder, entries):
    """Make ``folder`` hold exactly one symbolic link per ``{name: target}`` entry (others are removed)."""
    os.makedirs(folder, exist_ok=True)
    for name in os.listdir(folder):
        if name not in entries:
            path = os.path.join(folder, name)
            if os.path.islink(path):
                os.unlink(path)
    for name, target in entries.items():
        path = os.path.join(folder, name)
        if os.path.islink(path) and os.readlink(path) == target:
            continue
        if os.path.lexists(path):
            os.unlink(path)
        os.symlink(target, path)


def main(argv):
    if len(argv) != 1 or argv[0].startswith("-"):
        print("usage: python -m tests.support.ros_packages FOLDER  (links to ROS's Python packages of "
              f"{DIST_PACKAGES})", file=sys.stderr)
        return 2
    packages = python_packages()
    if not packages:
        print(f"ros_packages: no ROS Python package in {DIST_PACKAGES} (are Debian's ROS packages installed? "
              "./run deps)", file=sys.stderr)
        return 1
    link_into(argv[0], packages)
    print(f"ros_packages: ROS's Python packages linked into {argv[0]} ({len(packages)} entries)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
