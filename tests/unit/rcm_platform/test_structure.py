"""The agent's modules import one way down: no circle, not even inside a function.

The configuration is the bottom layer (any module may take a ``Config``); the rules of user input, the process
table, what a service item is, the data and the RDAPI build on it; the runtime (``rcmp_ms``), the agents
(``rcmp_event``) and the console stand side by side above them without knowing each other; ``rcmp_node``
assembles the agent and passes the runtime in. Read from the source with ``ast`` (every import statement,
wherever it is).
"""

import ast
import os

from tests.support.paths import REPO

PACKAGE = os.path.join(REPO, "rcm_platform")

# a module may import only modules of a lower layer
LAYERS = {
    "rcmp_config": 0, "rcmp_log_guard": 0, "rcmp_wd": 0, "rcmp_deps": 0, "rcmp_resources": 0,
    "rcmp_inter_communication": 1,
    "rcmp_command": 1, "rcmp_process": 1,
    "rcmp_service_item": 2, "rcmp_robotics_data": 2, "rcmp_platform_command": 2, "rcmp_service_command": 2,
    "rcmp_ext_connector": 2, "rcmp_vpn": 2,
    "rcmp_ms": 3, "rcmp_event": 3, "rcmp_console": 3, "rcmp_metrics": 3,
    "rcmp_node": 4,
    "__main__": 5,
}


def _imported(module):
    with open(os.path.join(PACKAGE, module + ".py"), encoding="utf-8") as f:
        tree = ast.parse(f.read())
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level == 1 and not base:                 # from . import a, b
                found.update(alias.name for alias in node.names)
            elif node.level == 1 or base.startswith("rcm_platform"):
                name = base.split(".")[-1] if base != "rcm_platform" else ""
                if name:
                    found.add(name)
                else:                                         # from rcm_platform import a, b
                    found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.Import):
            found.update(a.name.split(".")[1] for a in node.names if a.name.startswith("rcm_platform."))
    return found


def test_the_seed_modules_have_a_layer():
    modules = {f[:-3] for f in os.listdir(PACKAGE) if f.endswith(".py") and f != "__init__.py"}
    assert set(LAYERS) == modules   # every module has its place, those beside the seed's list too


def test_imports_go_one_way_down():
    wrong = []
    for module, layer in LAYERS.items():
        for target in _imported(module):
            if target in LAYERS and LAYERS[target] >= layer:
                wrong.append(f"{module} imports {target}")
    assert wrong == []


def test_the_runtime_and_the_agents_do_not_know_each_other():
    assert "rcmp_ms" not in _imported("rcmp_event")
    assert "rcmp_event" not in _imported("rcmp_ms")
    assert "rcmp_node" not in _imported("rcmp_ms") | _imported("rcmp_event")


def test_the_configuration_is_the_bottom_layer():
    assert _imported("rcmp_config") == set()
    assert all(layer >= LAYERS["rcmp_config"] for layer in LAYERS.values())


def test_the_process_table_needs_only_the_bottom():
    """The VPN and the console start children through it, so it knows neither the runtime nor the items."""
    assert _imported("rcmp_process") <= {"rcmp_config"}


ROS_MODULES = ("catkin", "catkin_pkg", "genpy", "genmsg")


def _is_ros_module(name):
    top = name.split(".")[0]
    return top.startswith("ros") or top in ROS_MODULES or top.endswith(("_msgs", "_srvs"))


def _imports_run_at_import(tree):
    """The module names imported by statements that run when the module is imported (not in a function)."""
    found, pending = [], list(tree.body)
    while pending:
        node = pending.pop()
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            continue
        if isinstance(node, ast.Import):
            found.extend(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and not node.level:
            found.append(node.module or "")
        pending.extend(ast.iter_child_nodes(node))
    return found


def test_no_module_imports_ros_when_it_is_imported():
    """ROS's Python packages reach the agent's sys.path only when it starts (``apply_ros_environment``, from a
    setup script such as /opt/ros/noetic/setup.bash): an import at a module's top level would run before."""
    wrong = []
    for module in LAYERS:
        with open(os.path.join(PACKAGE, module + ".py"), encoding="utf-8") as f:
            tree = ast.parse(f.read())
        wrong += [f"{module} imports {name}" for name in _imports_run_at_import(tree) if _is_ros_module(name)]
    assert wrong == []
