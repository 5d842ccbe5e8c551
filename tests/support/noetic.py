"""A test host that looks like a robot with Ubuntu 20.04 and ROS Noetic from ROS's own packages.

``add_noetic_host(lan, "robot")`` adds a host (tests/support/hosts.py) and makes, inside its mount namespace only:

- **Ubuntu 20.04's Python**: ``/usr/bin/python3`` (and ``python3.8``) is pyenv's CPython 3.8, whose site-packages
  is the ``ubuntu2004`` environment of tox.ini (Twisted 18.9.0, cryptography 2.8, netifaces 0.10.4, PyYAML, and
  ROS's Python dependencies at Ubuntu 20.04's versions), mounted as an overlay: what the host installs stays in
  the host. ``scripts/compat/matrix.sh`` makes that environment when it is missing (about a minute, once).
- **No ROS on the system's paths**: Debian's ROS programs are gone from ``/usr/bin`` (``rosmaster``, ``roscore``,
  ``rosrun``, ``catkin_make``, ...), ``/etc/ros`` too, and Python 3.8 never reads Debian's dist-packages.
- **``/opt/ros/noetic``**, as ROS's packages lay it out: ``setup.bash``/``setup.sh``/``_setup_util.py``/``.catkin``
  made by catkin itself (a catkin install space, so a workspace built on top chains onto it), ROS's environment
  hooks in ``etc/catkin/profile.d`` (``ROS_DISTRO=noetic``, ``ROS_PACKAGE_PATH``, ...), ``bin/`` (copies of
  Debian's ROS programs: their ``#!/usr/bin/python3`` is now 3.8), ``lib/python3/dist-packages`` (links to ROS's
  Python packages), ``share/<pkg>`` and ``lib/<pkg>`` (links to ROS's package folders), ``etc/ros``.
  Sourcing ``/opt/ros/noetic/setup.bash`` is the only way to ROS, as on a Noetic robot.
- **``/etc/os-release``** of Ubuntu 20.04.

``sourced(argv)`` wraps an argv to run with the setup script sourced first (as a user's shell would);
``PLAIN_ENV`` is a login shell's environment (no ROS variables), for ``host.run(..., env=PLAIN_ENV)``.
Root only, like every test host.
"""

import os
import shutil
import subprocess
import tempfile

from . import ros_packages
from .hosts import INSTALL_FRESH, INSTALL_PATHS

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
PREFIX = "/opt/ros/noetic"
SETUP = PREFIX + "/setup.bash"
TOX_ENV = os.path.join(ROOT, "build", "compat", "tox", "ubuntu2004")
# what the host keeps to itself: an installation's folders, /usr/bin (ROS's programs hidden, python3 replaced)
PRIVATE = INSTALL_PATHS + ("/usr/bin", "/home")
FRESH = INSTALL_FRESH
PLAIN_ENV = {"PATH": "/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin", "HOME": "/root",
             "LANG": "C.UTF-8"}
OS_RELEASE = """NAME="Ubuntu"
VERSION="20.04.6 LTS (Focal Fossa)"
ID=ubuntu
ID_LIKE=debian
PRETTY_NAME="Ubuntu 20.04.6 LTS"
VERSION_ID="20.04"
VERSION_CODENAME=focal
UBUNTU_CODENAME=focal
"""
# ROS's environment hooks, as ros-noetic-ros-environment installs them: Debian ships the same ones (for ROS_DISTRO
# "Debian"); they compute ROS_PACKAGE_PATH and ROS_ETC_DIR from the workspaces being sourced
ENV_HOOKS = "/usr/share/ros_environment/catkin_env_hook"
_SOURCED = 'setup=$1; shift; cmd=("$@"); set --; . "$setup" || exit 97; exec "${cmd[@]}"'


def sourced(argv, setup=SETUP):
    """``argv`` run by bash after sourcing ``setup`` (no arguments reach the setup script; argv is never parsed
    by a shell)."""
    return ["bash", "-c", _SOURCED, "bash", setup, *map(str, argv)]


def ubuntu2004_python():
    """(CPython 3.8 interpreter, site-packages of tox.ini's ubuntu2004 environment), made first if missing."""
    run = subprocess.run(["bash", os.path.join(ROOT, "scripts", "compat", "matrix.sh"), "-e", "ubuntu2004",
                          "--notest"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                         stdin=subprocess.DEVNULL, universal_newlines=True, timeout=900)
    if run.returncode != 0:
        raise RuntimeError(f"the ubuntu2004 environment could not be made:\n{run.stdout[-4000:]}")
    with open(os.path.join(TOX_ENV, "pyvenv.cfg")) as f:
        cfg = dict(line.split(" = ", 1) for line in f.read().splitlines() if " = " in line)
    base = os.path.join(cfg["home"], "python3.8")
    site = os.path.join(TOX_ENV, "lib", "python3.8", "site-packages")
    if not (os.path.isfile(base) and os.path.isdir(site)):
        raise RuntimeError(f"no Python 3.8 at {base} or no {site}")
    return base, site


def _catkin_version():
    return subprocess.run(["dpkg-query", "-W", "-f", "${Version}", "catkin"], stdout=subprocess.PIPE,
                          stderr=subprocess.DEVNULL, universal_newlines=True).stdout.strip() or "unknown"


def install_space():
    """A catkin install space for PREFIX made by this machine's catkin (cached in build/compat, per catkin
    version): setup.bash, setup.sh, _setup_util.py, env.sh, local_setup.*, .catkin."""
    cache = os.path.join(ROOT, "build", "compat", "noetic-install-space", _catkin_version().replace("/", "_"))
    made = cache + PREFIX
    if os.path.isfile(os.path.join(made, "setup.bash")):
        return made
    with tempfile.TemporaryDirectory(prefix="noetic-ws-") as ws:
        os.mkdir(os.path.join(ws, "src"))
        staging = cache + ".new"
        shutil.rmtree(staging, ignore_errors=True)
        env = {"PATH": "/usr/bin:/bin:/usr/sbin:/sbin", "HOME": ws, "LANG": "C.UTF-8", "DESTDIR": staging}
        run = subprocess.run(["catkin_make", "install", f"-DCMAKE_INSTALL_PREFIX={PREFIX}",
                              "-DPYTHON_EXECUTABLE=/usr/bin/python3", "-DCATKIN_ENABLE_TESTING=OFF"], cwd=ws, env=env,
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, universal_newlines=True, timeout=300)
        if run.returncode != 0:
            raise RuntimeError(f"catkin_make install failed:\n{run.stdout[-4000:]}")
        shutil.rmtree(cache, ignore_errors=True)
        os.rename(staging, cache)
    return made


def build_prefix(target):
    """Fill ``target`` (the host's view of PREFIX, seen from outside) as ROS Noetic's packages would."""
    shutil.copytree(install_space(), target, symlinks=True)
    files = ros_packages.ros_files()
    hooks = os.path.join(target, "etc", "catkin", "profile.d")
    os.makedirs(hooks)
    for name in sorted(os.listdir(ENV_HOOKS)):
        with open(os.path.join(ENV_HOOKS, name)) as f:
            text = f.read()
        if name == "1.ros_distro.sh":
            text = text.replace('"Debian"', '"noetic"').replace("=Debian", "=noetic")
        with open(os.path.join(hooks, name), "w") as f:
            f.write(text)
    shutil.copytree("/etc/ros", os.path.join(target, "etc", "ros"))
    bin_dir = os.path.join(target, "bin")
    os.makedirs(bin_dir)
    for name, path in ros_packages.programs(files).items():
        shutil.copy2(path, os.path.join(bin_dir, name))
    ros_packages.link_into(os.path.join(target, "lib", "python3", "dist-packages"),
                           ros_packages.python_packages(files))
    shares = ros_packages.package_folders(files)
    ros_packages.link_into(os.path.join(target, "share"), shares)
    for name, path in ros_packages.library_folders(shares, files).items():
        os.symlink(path, os.path.join(target, "lib", name))


def make_noetic(host):
    """Turn ``host`` (made with ``private=PRIVATE, fresh=FRESH``) into an Ubuntu 20.04 + ROS Noetic machine."""
    python, site = ubuntu2004_python()
    # Python 3.8 sees the ubuntu2004 environment's packages as its own site-packages, in this host only
    base_site = os.path.join(os.path.dirname(os.path.dirname(python)), "lib", "python3.8", "site-packages")
    upper = os.path.join(host.state_dir, "python38", "upper")
    work = os.path.join(host.state_dir, "python38", "work")
    os.makedirs(upper)
    os.makedirs(work)
    host.run(["mount", "-t", "overlay", "overlay", "-o", f"lowerdir={site},upperdir={upper},workdir={work}",
              base_site])
    # the system's python3 is 3.8; Debian's ROS programs and its Python 3.11 are not there
    programs = sorted(ros_packages.programs().values())
    host.run(["rm", "-f", "/usr/bin/python3.11", *programs])
    host.run(["ln", "-sf", python, "/usr/bin/python3"])
    host.run(["ln", "-sf", python, "/usr/bin/python3.8"])
    host.run(["rm", "-rf", "/etc/ros"])
    release = os.path.join(host.state_dir, "os-release")
    with open(release, "w") as f:
        f.write(OS_RELEASE)
    host.run(["rm", "-f", "/etc/os-release"])
    host.run(["cp", release, "/etc/os-release"])
    build_prefix(host.private_path(PREFIX))
    return host


def add_noetic_host(lan, name, **kwargs):
    """A new host of ``lan`` made an Ubuntu 20.04 + ROS Noetic machine (see the module's docstring)."""
    return make_noetic(lan.add_host(name, private=PRIVATE, fresh=FRESH, **kwargs))
