"""Every module of the product imports, on whichever Python and library versions runs the tests.

The compatibility matrix (tox.ini) runs this file on each supported system's Python (3.8 to 3.13) with that
system's Twisted, cryptography and netifaces: an annotation such as ``str | None`` evaluated at import, a
3.9+ function called at module level, or an API a library gained later fails here, module by module.
The modules: the agent's package ``rcm_platform`` (``__main__`` is run by ``python -m rcm_platform --help``
instead), FIROS's ``core.py`` and ``include/*`` (as ``rosrun firos core.py`` loads them, ``scripts/`` first on the
path), and ``rcm_driver.py``.
"""

import glob
import importlib
import importlib.util
import os
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
FIROS_SCRIPTS = os.path.join(ROOT, "firos", "scripts")
RCM_DRIVER = os.path.join(ROOT, "rcm", "scripts", "rcm_driver.py")


def _module_names(folder, package=None):
    names = sorted(os.path.splitext(os.path.basename(p))[0] for p in glob.glob(os.path.join(folder, "*.py")))
    names = [n for n in names if n not in ("__init__", "__main__")]
    return [f"{package}.{n}" if package else n for n in names]


AGENT_MODULES = ["rcm_platform"] + _module_names(os.path.join(ROOT, "rcm_platform"), "rcm_platform")
FIROS_MODULES = ["core", "include"] + _module_names(os.path.join(FIROS_SCRIPTS, "include"), "include")


def test_the_lists_are_not_empty():
    assert "rcm_platform.rcmp_node" in AGENT_MODULES
    assert "include.config" in FIROS_MODULES and os.path.isfile(RCM_DRIVER)


@pytest.mark.parametrize("name", AGENT_MODULES)
def test_agent_module_imports(name):
    importlib.import_module(name)


@pytest.mark.parametrize("name", FIROS_MODULES)
def test_firos_module_imports(name):
    if FIROS_SCRIPTS not in sys.path:
        sys.path.insert(0, FIROS_SCRIPTS)  # what core.py does for its include/ package
    importlib.import_module(name)


def test_rcm_driver_imports():
    spec = importlib.util.spec_from_file_location("rcm_driver", RCM_DRIVER)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)  # its node starts only under __main__
    assert callable(getattr(module, "main", None))
