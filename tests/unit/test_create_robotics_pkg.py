"""create_robotics_pkg as a file: it runs with the system's Python (what it builds is tested in
``tests/system/test_distribution.py``)."""

import os
import stat

from tests.support.paths import REPO

TOOL = os.path.join(REPO, "create_robotics_pkg")


def test_tool_runs_with_the_system_python():
    with open(TOOL) as f:
        assert f.readline().strip() == "#!/usr/bin/python3"
    assert os.stat(TOOL).st_mode & stat.S_IXUSR
