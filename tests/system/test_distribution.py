"""create_robotics_pkg: every zip's file list against the seed guide's listings, reproducibility, errors.

The expected listings below are written out from the seed guide ("Distribution" and "Installation"), not taken
from create_robotics_pkg, so that a drift on either side fails here. Two kinds of test: on the real source tree
(what we ship) and on a small synthetic tree (the tool's rules: exclusions, modes, missing files, options).
"""

import io
import os
import subprocess
import zipfile

import pytest

from tests.support.paths import REPO

ROOT = REPO
TOOL = os.path.join(ROOT, "create_robotics_pkg")
PYTHON = "/usr/bin/python3"

# --- the seed's listings ---------------------------------------------------------------------------------------
SEED_MASTER_MODULES = [
    "__init__.py", "rcmp_command.py", "rcmp_event.py", "rcmp_ext_connector.py", "rcmp_inter_communication.py",
    "rcmp_ms.py", "rcmp_node.py", "rcmp_platform_command.py", "rcmp_robotics_data.py",
    "rcmp_service_command.py", "rcmp_wd.py"]
EXTRA_MODULES = ["__main__.py",  # ours: `python3 -m rcm_platform` (CONTRACTS §1), recorded in docs/INSTALL.md
                 "rcmp_vpn.py",  # ours: the platform's VPN (CONTRACTS §7), in the master and the robot zips
                 # ours: split out of the seed's modules for one job each (CONTRACTS §6), master and robot zips
                 "rcmp_config.py", "rcmp_log_guard.py", "rcmp_process.py", "rcmp_service_item.py",
                 "rcmp_deps.py",  # ours: the one line naming a missing package, master and robot zips
                 "rcmp_resources.py"]  # ours: the agent's open-file limit and garbage collector, both zips
CONSOLE_MODULES = ["rcmp_console.py",   # ours: the console (CONTRACTS §9), master zip only
                   "rcmp_metrics.py"]   # ours: the RDAPI's /metrics, master zip only
CONSOLE_FILES = ["rcm_platform/console/console.css", "rcm_platform/console/console.js",
                 "rcm_platform/console/index.html"]  # its static files, master zip only
SEED_ROBOT_MODULES = [m for m in SEED_MASTER_MODULES if m not in ("rcmp_ext_connector.py", "rcmp_robotics_data.py")]
SEED_AGENT_FILES = ["ros/rosconsole.config", "install.sh", "sub_inst.sh", "uninstall.sh", "sub_uninst.sh", "rcmpd",
                    "rcmp_n"]
SEED_AGENT_SCRIPTS = ["install.sh", "sub_inst.sh", "uninstall.sh", "sub_uninst.sh", "rcmpd", "rcmp_n"]
SEED_RCM = ["rcm/scripts/rcm_driver.py", "rcm/CMakeLists.txt", "rcm/LICENSE.txt", "rcm/package.xml",
            "rcm/README.md"]
# the seed spells the service FIROS_info.srv; the issues, the contracts and the package say FIROS_Info.srv
SEED_ROBOTICS_MSGS = ["robotics_msgs/msg/CB_Event.msg", "robotics_msgs/msg/Robot_Event.msg",
                      "robotics_msgs/srv/FIROS_Info.srv", "robotics_msgs/CMakeLists.txt",
                      "robotics_msgs/LICENSE.txt", "robotics_msgs/package.xml", "robotics_msgs/README.md"]
SEED_FIROS_FILES = ["firos/scripts/core.py", "firos/CMakeLists.txt", "firos/License.txt", "firos/package.xml",
                    "firos/README.md"]
SEED_FIROS_DIRS = ["firos/", "firos/config/", "firos/scripts/", "firos/scripts/include/"]
SEED_FIROS_TOP = {"config", "scripts", "CMakeLists.txt", "License.txt", "package.xml", "README.md"}


def agent_listing(root, modules, extra=(), console=False):
    files = [f"{root}/rcm_platform/{m}" for m in modules] + [f"{root}/{f}" for f in SEED_AGENT_FILES]
    files += [f"{root}/{f}" for f in extra]
    dirs = [f"{root}/", f"{root}/rcm_platform/", f"{root}/ros/"]
    if console:
        files += [f"{root}/rcm_platform/{m}" for m in CONSOLE_MODULES] + [f"{root}/{f}" for f in CONSOLE_FILES]
        dirs.append(f"{root}/rcm_platform/console/")
    return sorted(files + dirs)


def with_dirs(files):
    dirs = set()
    for f in files:
        parts = f.split("/")[:-1]
        for i in range(1, len(parts) + 1):
            dirs.add("/".join(parts[:i]) + "/")
    return sorted(set(files) | dirs)


EXPECTED = {
    "master": ("rcm_platform_master.zip",
               agent_listing("rcm_platform_master", SEED_MASTER_MODULES + EXTRA_MODULES, console=True)),
    "robot": ("rcm_platform_robot.zip", agent_listing("rcm_platform_robot", SEED_ROBOT_MODULES + EXTRA_MODULES)),
    "rcm_driver": ("rcm_driver.zip", with_dirs(SEED_RCM)),
    "robotics_msgs": ("robotics_msgs.zip", with_dirs(SEED_ROBOTICS_MSGS)),
    None: ("robotics.zip", agent_listing("rcm_platform_master", SEED_MASTER_MODULES + EXTRA_MODULES,
                                         extra=["firos.zip", "rcm_driver.zip", "robotics_msgs.zip"],
                                         console=True)),
}


def run_tool(*args, env=None):
    return subprocess.run([PYTHON, TOOL, *args], capture_output=True, text=True, timeout=120, env=env)


def build(outdir, package=None, source=None, env=None):
    args = ([package] if package else []) + ["-o", str(outdir)] + (["--source", str(source)] if source else [])
    result = run_tool(*args, env=env)
    assert result.returncode == 0, f"create_robotics_pkg {' '.join(args)} failed: {result.stderr}"
    name = EXPECTED[package][0] if package in EXPECTED else f"{package}.zip"
    path = os.path.join(str(outdir), name)
    assert f"created {path}" in result.stdout
    return path, result


def names(zip_path_or_bytes):
    source = io.BytesIO(zip_path_or_bytes) if isinstance(zip_path_or_bytes, bytes) else zip_path_or_bytes
    with zipfile.ZipFile(source) as zf:
        return sorted(zf.namelist())


def check_firos_listing(listing):
    for entry in SEED_FIROS_FILES + SEED_FIROS_DIRS:
        assert entry in listing, f"firos.zip lacks {entry}"
    assert all(n.startswith("firos/") for n in listing)
    top = {n.split("/")[1] for n in listing if n != "firos/"}
    assert top <= SEED_FIROS_TOP, f"firos.zip has entries the seed does not list: {sorted(top - SEED_FIROS_TOP)}"
    for n in listing:
        parts = n.rstrip("/").split("/")
        assert "__pycache__" not in parts and not n.endswith(".pyc"), n
        assert not ({"test", "tests", "build", "devel"} & set(parts)), n
        assert not any(p.startswith(".") for p in parts), n


# --- the real tree: what we ship ---------------------------------------------------------------------------------
@pytest.mark.parametrize("package", ["master", "robot", "rcm_driver", "robotics_msgs", None],
                         ids=["master", "robot", "rcm_driver", "robotics_msgs", "robotics"])
def test_zip_lists_exactly_the_seed_files(tmp_path, package):
    path, _ = build(tmp_path, package)
    assert names(path) == EXPECTED[package][1]


def test_every_module_of_the_agents_package_is_in_the_master_zip():
    """A module added to rcm_platform/ and forgotten in create_robotics_pkg's listing would install an agent that
    cannot import it: every module of the source tree is in the master zip's listing."""
    modules = {name for name in os.listdir(os.path.join(ROOT, "rcm_platform")) if name.endswith(".py")}
    assert modules == set(SEED_MASTER_MODULES + EXTRA_MODULES + CONSOLE_MODULES)


def test_firos_zip_has_the_seed_layout(tmp_path):
    path, _ = build(tmp_path, "firos")
    check_firos_listing(names(path))


def test_robotics_zip_embeds_the_three_component_zips_as_built_alone(tmp_path):
    path, _ = build(tmp_path / "all")
    with zipfile.ZipFile(path) as zf:
        inner = {n: zf.read(f"rcm_platform_master/{n}") for n in ("firos.zip", "rcm_driver.zip", "robotics_msgs.zip")}
    for package, zip_name in (("firos", "firos.zip"), ("rcm_driver", "rcm_driver.zip"),
                              ("robotics_msgs", "robotics_msgs.zip")):
        alone, _ = build(tmp_path / package, package)
        with open(alone, "rb") as f:
            assert inner[zip_name] == f.read(), f"{zip_name} inside robotics.zip differs from one built alone"
    check_firos_listing(names(inner["firos.zip"]))
    assert names(inner["rcm_driver.zip"]) == EXPECTED["rcm_driver"][1]
    assert names(inner["robotics_msgs.zip"]) == EXPECTED["robotics_msgs"][1]


@pytest.mark.parametrize("package", [None, "robot", "firos"], ids=["robotics", "robot", "firos"])
def test_same_tree_gives_byte_identical_zips(tmp_path, package):
    first, _ = build(tmp_path / "one", package)
    second, _ = build(tmp_path / "two", package)
    with open(first, "rb") as a, open(second, "rb") as b:
        assert a.read() == b.read()


def test_agent_scripts_are_executable_and_the_rest_is_not(tmp_path):
    path, _ = build(tmp_path, "master")
    with zipfile.ZipFile(path) as zf:
        for info in zf.infolist():
            mode = (info.external_attr >> 16) & 0o777
            rel = info.filename.split("/", 1)[1]
            if info.is_dir():
                assert mode == 0o755, info.filename
            elif rel in SEED_AGENT_SCRIPTS:
                assert mode == 0o755, info.filename
            else:
                assert mode == 0o644, info.filename


def test_robot_zip_runs_without_the_master_only_modules(tmp_path):
    """The robot agent from the unpacked robot zip starts its command line without RDAPI or database modules."""
    path, _ = build(tmp_path, "robot")
    with zipfile.ZipFile(path) as zf:
        zf.extractall(tmp_path / "unpacked")
    root = tmp_path / "unpacked" / "rcm_platform_robot"
    home = tmp_path / "home"
    home.mkdir()
    (home / "init.cfg").write_text("[main]\nname=robot1\nrobot=yes\nip_master=127.0.0.1\n"
                                   "vpn_address=127.0.0.1\n")
    env = dict(os.environ, PYTHONPATH=str(root), PATH="/usr/bin:/bin")
    code = ("import sys, rcm_platform.rcmp_node as n; c = n.load_config(sys.argv[1]); "
            "n.build_agent(c, __import__('twisted.internet.reactor', fromlist=['x'])); "
            "import rcm_platform; print(rcm_platform.__file__); "
            "print(sorted(m for m in sys.modules if m.startswith(('rcm_platform.', 'prometheus_client'))))")
    result = subprocess.run([PYTHON, "-c", code, str(home)], capture_output=True, text=True, env=env,
                            cwd=str(tmp_path), timeout=60)
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines()[0].startswith(str(root))
    assert "rcm_platform.rcmp_ext_connector" not in result.stdout
    assert "rcm_platform.rcmp_robotics_data" not in result.stdout
    assert "rcm_platform.rcmp_console" not in result.stdout
    assert "rcm_platform.rcmp_metrics" not in result.stdout and "prometheus_client" not in result.stdout


# --- the tool's rules, on a synthetic tree ---------------------------------------------------------------------
def make_tree(base):
    files = ["rcm_platform/" + m for m in SEED_MASTER_MODULES + EXTRA_MODULES + CONSOLE_MODULES] + SEED_AGENT_FILES
    files += CONSOLE_FILES
    files += SEED_RCM + SEED_ROBOTICS_MSGS + SEED_FIROS_FILES
    files += ["firos/config/config.json", "firos/scripts/include/ros/topicHandler.py",
              "firos/scripts/include/__init__.py"]
    for rel in files:
        path = base / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(f"content of {rel}\n")
    (base / "firos" / "scripts" / "core.py").chmod(0o755)
    (base / "rcmpd").chmod(0o600)  # the zip fixes the agent scripts' modes whatever the tree says
    # things that must never be shipped
    junk = ["firos/scripts/include/__pycache__/x.cpython-311.pyc", "firos/scripts/include/old.pyc",
            "firos/tests/test_core.py", "firos/scripts/tests/test_x.py", "firos/config/.hidden",
            "rcm/scripts/__pycache__/rcm_driver.cpython-311.pyc", "rcm/tests/test_driver.py",
            "rcm_platform/__pycache__/rcmp_node.cpython-311.pyc", "rcm_platform/rcmp_scratch.py",
            "robotics_msgs/build/junk.txt", "firos/notes.txt"]
    for rel in junk:
        path = base / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("junk\n")
    return base


@pytest.fixture
def tree(tmp_path):
    return make_tree(tmp_path / "tree")


def test_synthetic_tree_zips_leave_out_caches_tests_and_unlisted_files(tmp_path, tree):
    path, result = build(tmp_path / "out", None, source=tree)
    assert names(path) == EXPECTED[None][1]
    with zipfile.ZipFile(path) as zf:
        firos = names(zf.read("rcm_platform_master/firos.zip"))
        rcm = names(zf.read("rcm_platform_master/rcm_driver.zip"))
        msgs = names(zf.read("rcm_platform_master/robotics_msgs.zip"))
    check_firos_listing(firos)
    assert "firos/config/config.json" in firos and "firos/scripts/include/ros/topicHandler.py" in firos
    assert rcm == EXPECTED["rcm_driver"][1] and msgs == EXPECTED["robotics_msgs"][1]
    # unlisted files are named, so their owners learn they are not shipped
    assert "rcm_platform/rcmp_scratch.py is not one of the modules the agent ships" in result.stderr
    assert "firos/notes.txt is not in firos.zip's file list" in result.stderr


def test_zip_is_reproducible_whatever_the_file_dates(tmp_path, tree):
    first, _ = build(tmp_path / "one", None, source=tree)
    for current, _, files in os.walk(tree):
        for f in files:
            os.utime(os.path.join(current, f), (1_700_000_000, 1_700_000_000))
    second, _ = build(tmp_path / "two", None, source=tree)
    with open(first, "rb") as a, open(second, "rb") as b:
        assert a.read() == b.read()
    with zipfile.ZipFile(first) as zf:
        assert {i.date_time for i in zf.infolist()} == {(2016, 1, 1, 0, 0, 0)}


def test_source_date_epoch_sets_the_entry_dates(tmp_path, tree):
    env = dict(os.environ, SOURCE_DATE_EPOCH="1443020619")  # 2015-09-23 15:03:39 UTC, the seed's test date
    path, _ = build(tmp_path, "rcm_driver", source=tree, env=env)
    with zipfile.ZipFile(path) as zf:
        assert {i.date_time for i in zf.infolist()} == {(2015, 9, 23, 15, 3, 38)}  # zip keeps even seconds


def test_modes_come_from_the_rules_not_from_the_tree(tmp_path, tree):
    path, _ = build(tmp_path, None, source=tree)
    with zipfile.ZipFile(path) as zf:
        modes = {i.filename: (i.external_attr >> 16) & 0o777 for i in zf.infolist()}
        firos = zipfile.ZipFile(io.BytesIO(zf.read("rcm_platform_master/firos.zip")))
        firos_modes = {i.filename: (i.external_attr >> 16) & 0o777 for i in firos.infolist()}
    assert modes["rcm_platform_master/rcmpd"] == 0o755
    assert modes["rcm_platform_master/rcm_platform/rcmp_node.py"] == 0o644
    assert firos_modes["firos/scripts/core.py"] == 0o755
    assert firos_modes["firos/package.xml"] == 0o644


@pytest.mark.parametrize("missing, package, zip_name", [
    ("rcm/README.md", "rcm_driver", "rcm_driver.zip"),
    ("robotics_msgs/srv/FIROS_Info.srv", "robotics_msgs", "robotics_msgs.zip"),
    ("rcm_platform/rcmp_ms.py", "robot", "rcm_platform_robot.zip"),
    ("firos/README.md", None, "robotics.zip"),
])
def test_missing_file_is_named_and_no_zip_is_left(tmp_path, tree, missing, package, zip_name):
    os.remove(tree / missing)
    out = tmp_path / "out"
    result = run_tool(*([package] if package else []), "-o", str(out), "--source", str(tree))
    assert result.returncode == 1
    assert missing in result.stderr and "Traceback" not in result.stderr
    assert not out.exists() or os.listdir(out) == []


def test_robot_zip_never_holds_master_only_modules_even_when_present(tmp_path, tree):
    path, _ = build(tmp_path, "robot", source=tree)
    listing = names(path)
    assert "rcm_platform_robot/rcm_platform/rcmp_ext_connector.py" not in listing
    assert "rcm_platform_robot/rcm_platform/rcmp_robotics_data.py" not in listing
    assert not [n for n in listing if "rcmp_console" in n or "rcm_platform/console" in n]
    assert "rcm_platform_robot/rcm_platform/rcmp_metrics.py" not in listing


def test_rebuild_replaces_the_zip(tmp_path, tree):
    out = tmp_path / "out"
    path, _ = build(out, "robotics_msgs", source=tree)
    with open(path, "wb") as f:
        f.write(b"stale")
    build(out, "robotics_msgs", source=tree)
    assert names(path) == EXPECTED["robotics_msgs"][1]
    assert sorted(os.listdir(out)) == ["robotics_msgs.zip"]  # no partial file left next to it


@pytest.mark.parametrize("args, message", [
    (["bogus"], "invalid choice: 'bogus'"),
    (["--bogus"], "unrecognized arguments: --bogus"),
    (["master", "robot"], "unrecognized arguments: robot"),
    (["-o"], "expected one argument"),
])
def test_bad_command_line_is_a_clear_error_with_status_2(tmp_path, args, message):
    result = run_tool(*args)
    assert result.returncode == 2
    assert message in result.stderr and "usage: create_robotics_pkg" in result.stderr
    assert "Traceback" not in result.stderr


def test_help_lists_every_package(tmp_path):
    result = run_tool("--help")
    assert result.returncode == 0
    for word in ("master", "robot", "firos", "rcm_driver", "robotics_msgs", "robotics.zip", "--output"):
        assert word in result.stdout
