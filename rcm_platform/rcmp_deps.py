"""What the agent needs from the system, and the one line that says which package to install when it is missing.

Owns:
- ``PACKAGES``: each third-party Python module the agent imports (by its top-level name) -> its project's name,
  the Debian and Ubuntu package that installs it for ``/usr/bin/python3``, and, for ROS's own modules, the name of
  the package ROS's repository gives it (``ros-<distro>-NAME``) for a ROS installed under ``/opt/ros``;
- telling the system apart (``this_system``): ``/etc/os-release`` (Debian, Ubuntu and their derivatives speak
  apt-get with these names; any other system is told the project's name and the Debian name as a hint), ROS under
  ``/opt/ros/<distro>`` (``ROS_DISTRO`` first, then noetic, then any), and whether the running Python sees the
  system's packages (a pyenv or venv Python first on PATH does not);
- ``missing_line(exc)``: the one sentence for an ``ImportError`` (``rcmp_node.main`` turns any import failure into it
  and exit status ``EXIT_MISSING``), and ``require(modules)``, which checks modules without importing them and
  raises ``MissingDependency`` with that sentence (for what the agent imports late: ROS's loader, netifaces).

It imports nothing of ``rcm_platform`` and nothing outside the standard library, so it works on a Python that has
nothing else.
"""

import collections
import glob
import importlib.util
import os
import sys

OS_RELEASE = "/etc/os-release"
ROS_ROOT = "/opt/ros"
SYSTEM_PYTHON = "/usr/bin/python3"
SYSTEM_SITE = "/usr/lib/python3/dist-packages"     # where Debian's python3-* packages put their modules
DEBIAN_FAMILY = ("debian", "ubuntu")

# module -> (project, Debian/Ubuntu package, the ROS repository's package or None when it is the Debian name there
# too); "{distro}" is filled with the ROS distribution found under /opt/ros
Package = collections.namedtuple("Package", "project debian ros")
PACKAGES = {
    "twisted": Package("Twisted", "python3-twisted", None),
    "zope": Package("zope.interface", "python3-zope.interface", None),
    "netifaces": Package("netifaces", "python3-netifaces", None),
    "cryptography": Package("cryptography", "python3-cryptography", None),
    "OpenSSL": Package("pyOpenSSL", "python3-openssl", None),
    "service_identity": Package("service_identity", "python3-service-identity", None),
    "prometheus_client": Package("prometheus_client", "python3-prometheus-client", None),
    "yaml": Package("PyYAML", "python3-yaml", None),
    "rospkg": Package("rospkg", "python3-rospkg", None),
    "catkin_pkg": Package("catkin_pkg", "python3-catkin-pkg", None),
    "roslaunch": Package("ROS's roslaunch", "python3-roslaunch", "ros-{distro}-roslaunch"),
    "rosgraph": Package("ROS's rosgraph", "python3-rosgraph", "ros-{distro}-rosgraph"),
    "roslib": Package("ROS's roslib", "python3-roslib", "ros-{distro}-roslib"),
    "rospy": Package("ROS's rospy", "python3-rospy", "ros-{distro}-rospy"),
    "rosmaster": Package("ROS's rosmaster", "python3-rosmaster", "ros-{distro}-rosmaster"),
    "catkin": Package("ROS's catkin", "catkin", "ros-{distro}-catkin"),
    "genpy": Package("ROS's genpy", "python3-genpy", "ros-{distro}-genpy"),
}

# what the agent itself needs of ROS (the launch-file loader, and what it imports); the agent of every role starts
# ROS processes, so a missing one stops it at start rather than failing every service item later
ROS_MODULES = ("roslaunch", "rosgraph", "rospkg")

System = collections.namedtuple("System", "name apt ros_distro ros_prefix ros_site sees_system_site")


class MissingDependency(ImportError):
    """A module the agent needs is not available; ``str()`` is the one line naming the package to install."""


def _os_release(path):
    values = {}
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            for line in f:
                key, sep, value = line.strip().partition("=")
                if sep:
                    values[key] = value.strip().strip("'\"")
    except OSError:
        pass
    return values


def _ros_distro(ros_root, environ):
    """The ROS distribution installed under ``ros_root`` (``ROS_DISTRO`` when it is there, else noetic, else the
    first by name), or None."""
    try:
        found = sorted(d for d in os.listdir(ros_root) if os.path.isdir(os.path.join(ros_root, d)))
    except OSError:
        return None
    for wanted in (environ.get("ROS_DISTRO"), "noetic"):
        if wanted in found:
            return wanted
    return found[0] if found else None


def this_system(os_release=OS_RELEASE, ros_root=ROS_ROOT, environ=None, path=None):
    """What this machine is: its name (``PRETTY_NAME``), whether it speaks apt-get with Debian's package names,
    the ROS distribution under ``ros_root`` and its Python folder, and whether this Python sees the system's
    packages (``SYSTEM_SITE`` on ``sys.path``)."""
    environ = os.environ if environ is None else environ
    release = _os_release(os_release)
    family = {release.get("ID", "")} | set(release.get("ID_LIKE", "").split())
    distro = _ros_distro(ros_root, environ)
    prefix = os.path.join(ros_root, distro) if distro else None
    return System(name=release.get("PRETTY_NAME") or release.get("NAME") or "this system",
                  apt=bool(family & set(DEBIAN_FAMILY)), ros_distro=distro, ros_prefix=prefix,
                  ros_site=os.path.join(prefix, "lib", "python3", "dist-packages") if prefix else None,
                  sees_system_site=SYSTEM_SITE in (sys.path if path is None else path))


def _present_in(folder, module):
    """True when ``folder`` holds the top-level module ``module`` (a package folder, a .py file, an extension)."""
    if not folder:
        return False
    base = os.path.join(folder, module)
    return os.path.isdir(base) or os.path.isfile(base + ".py") or bool(glob.glob(glob.escape(base) + ".*.so"))


def package_for(module, system):
    """The package that installs ``module`` on ``system`` (a name for apt-get, or the Debian name as a hint)."""
    known = PACKAGES.get(module)
    if known is None:   # Debian's policy: python3- and the module's name, lower case, "_" as "-"
        return "python3-" + module.lower().replace("_", "-")
    if known.ros and system.ros_distro:
        return known.ros.format(distro=system.ros_distro)
    return known.debian


def missing_line(exc, system=None, why=None):
    """The one line for the ImportError ``exc`` (or a module's name): what is missing and how to get it here."""
    system = system or this_system()
    if isinstance(exc, str):
        module, detail = exc, None
    else:
        module = (getattr(exc, "name", None) or "").split(".")[0] or None
        detail = None if isinstance(exc, ModuleNotFoundError) else (str(exc).splitlines() or [""])[0]
        if module is None:
            return f"a Python module cannot be imported: {detail or exc}"
    known = PACKAGES.get(module)
    what = f"{known.project if known else module} (Python module '{module}')"
    package = package_for(module, system)
    purpose = f" ({why})" if why else ""
    python = sys.executable or "this Python"
    if detail:   # it is there, but not usable: too old, or half installed
        return f"{what} cannot be used{purpose}: {detail}; reinstall or upgrade {package}"
    if known is not None and known.ros and system.ros_distro:
        if _present_in(system.ros_site, module):
            return (f"{what} is not on this Python's path{purpose}: ROS is installed in {system.ros_prefix}; "
                    f"source {os.path.join(system.ros_prefix, 'setup.bash')} first")
        return f"{what} is missing{purpose}: install it with 'sudo apt-get install {package}' ({system.name})"
    if not system.sees_system_site:
        if _present_in(SYSTEM_SITE, module):
            return (f"{what} is not available to {python}{purpose}, which does not see the system's Python "
                    f"packages: run '{SYSTEM_PYTHON} -m rcm_platform' instead ({package} is installed for it)")
        if system.apt:
            return (f"{what} is not available to {python}{purpose}: install it with 'sudo apt-get install "
                    f"{package}' and run rcmp_n with {SYSTEM_PYTHON}")
    if system.apt:
        return f"{what} is missing{purpose}: install it with 'sudo apt-get install {package}' ({system.name})"
    project = known.project if known else module
    return (f"{what} is missing{purpose}: install {project} for {python} (on Debian and Ubuntu: the package "
            f"{package})")


def require(modules, why=None, system=None):
    """Raise MissingDependency (its one line) for the first of ``modules`` this Python cannot import; the modules
    are looked up, not imported."""
    for module in modules:
        try:
            found = importlib.util.find_spec(module) is not None
        except (ImportError, ValueError):
            found = False
        if not found:
            raise MissingDependency(missing_line(module, system, why), name=module)
